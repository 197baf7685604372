"""DAgger: imitate an expert on the states the learner itself reaches, not only on the expert's.

Behaviour cloning fits the expert on the expert's own state distribution; the clone's small
mistakes then lead it to states the expert never visited, where it has no data (on Luxembourg
in meso the clone of MPC-Forecast wins 8 of 10 paired episodes against ED, but by less than the
spread). DAgger (Ross, Gordon & Bagnell, 2011) closes that gap by rounds. Round k:

1. roll the current policy (round k-1's; round 1 starts from ``start``) through the env for
   ``episodes`` episodes on collection seed ``seed + k - 1`` (demand streams disjoint from the base
   dataset's and from evaluation's), logging at every state the *expert's* action at that state
   (:func:`marl_amod.datasets.collect` with ``labeller``; the env steps with the learner's);
2. aggregate: the base dataset (the expert's own episodes) plus rounds 1..k;
3. retrain BC on the aggregate with the base config (``configs/bc/...``: same start actor,
   updates and validation), writing ``<run_root>/round<k>.pt``.

Every round's files stay under ``run_root`` and a round whose policy exists is skipped, so an
interrupted run resumes at the round it stopped in (and a long run can be split into jobs by
``rounds``). The kept policy is the round with the best validation profit (the BC run's
validation seeds, never the report seeds), written to the config's ``policy_out`` with a card
whose algorithm is ``dagger`` and whose ``reproduce`` is the command that makes it.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from marl_amod.algos.offline import check_fits
from marl_amod.algos.registry import args_for, run_training
from marl_amod.checkpoints import write_policy
from marl_amod.config import read_config
from marl_amod.datasets import OfflineDataset, collect, concatenate
from marl_amod.errors import ConfigError
from marl_amod.files import check_folder, write_json
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city


def dagger(
    config: str | Path, *, start: str, expert: str = "mpc-forecast", rounds: int = 3, episodes: int = 20, seed: int = 1,
    run_root: str | Path = "runs/dagger", progress: Callable[[str], None] | None = None,
) -> dict[str, Any]:
    """Run DAgger rounds 1..``rounds`` (module docstring) on top of the BC config ``config``;
    returns the summary also written to ``<run_root>/dagger.json``."""
    raw = read_config(config)
    if raw.get("algo") != "bc":
        raise ConfigError(f"{config}: DAgger retrains behaviour cloning; algo: is {raw.get('algo')!r}")
    if rounds < 1 or episodes < 1:
        raise ConfigError(f"rounds and episodes must be >= 1, got {rounds} and {episodes}")
    base = dict(raw.get("args") or {})
    root = Path(run_root)
    bc = args_for("bc", {**base, "run_dir": str(root / "bc1"), "policy_out": str(root / "round1.pt")}, where=str(config))  # now, not after round 1
    if base.get("policy_out") and Path(base["policy_out"]).resolve() == Path(start).resolve():
        raise ConfigError(f"{config}: policy_out {base['policy_out']} is the --start policy, which the kept round would overwrite; "
                          "give the DAgger result its own policy_out")  # fmt: skip
    city = load_city(bc.scenario)
    expert_data = OfflineDataset.load(bc.dataset)
    check_fits(expert_data, bc.dataset, city, bc.lookahead, bc.arrivals_now)  # each round's data is collected with these features
    settings = {"config": str(config), "start": start, "expert": expert, "episodes": episodes, "seed": seed}
    check_folder(root, what="--run-root")
    say = progress or (lambda _msg: None)
    summary_path = root / "dagger.json"
    saved = json.loads(summary_path.read_text()) if summary_path.is_file() else {}
    if changed := [k for k, v in settings.items() if k in saved and saved[k] != v]:
        raise ConfigError(f"{run_root} holds DAgger rounds made with other {', '.join(changed)} "
                          f"({', '.join(f'{k} {saved[k]!r}' for k in changed)}); resume with those or give another --run-root")  # fmt: skip
    done = saved.get("rounds", [])
    parts = [expert_data]
    policy = start
    for k in range(1, rounds + 1):
        data_path, policy_path = root / f"round{k}.npz", root / f"round{k}.pt"
        if not data_path.is_file():
            say(f"round {k}: rolling {policy} for {episodes} episodes, labels from {expert}")
            part = collect(city, make_policy(policy, city), episodes=episodes, seed=seed + k - 1, lookahead=bc.lookahead,
                           max_wait=int(expert_data.meta.get("max_wait", 0)), labeller=make_policy(expert, city),
                           arrivals_now=bc.arrivals_now)  # the base data's features  # fmt: skip
            part.save(data_path)
        parts.append(OfflineDataset.load(data_path))
        if not policy_path.is_file() or len(done) < k:
            aggregate = root / f"aggregate{k}.npz"
            concatenate(parts).save(aggregate)
            args = args_for("bc", {**base, "dataset": str(aggregate), "run_dir": str(root / f"bc{k}"), "policy_out": str(policy_path)})
            say(f"round {k}: BC on {sum(len(p) for p in parts):,} transitions")
            card = run_training("bc", args, config_path=str(config))["card"]
            done = done[: k - 1] + [{
                "round": k, "policy": str(policy_path), "rollout_policy": str(policy), "episodes": episodes,
                "collection_seed": seed + k - 1, "rollout_profit_mean": parts[-1].meta["episode_profit_mean"],
                "transitions": card["dataset"]["transitions"], "validation_profit": card["best_validation"],
                "wall_s": card["training_wall_s"],
            }]  # fmt: skip
            write_json(summary_path, {**settings, "rounds": done})
        policy = str(policy_path)
    best = max(done[:rounds], key=lambda r: r["validation_profit"])
    summary = {**settings, "rounds": done[:rounds], "kept": best["round"], "policy_out": base.get("policy_out")}
    if summary["policy_out"]:
        ship(best["policy"], summary["policy_out"], summary, f"marl-amod dagger --config {config} --start {start} --expert {expert} "
             f"--rounds {rounds} --episodes {episodes} --seed {seed} --run-root {run_root}")  # fmt: skip
    write_json(summary_path, summary)
    return summary


def ship(policy: str | Path, out: str | Path, summary: dict[str, Any], command: str) -> Path:
    """The kept round's policy as ``out``, its card saying it is DAgger's (rounds, validation
    profits) and how to make it again (one BC run does not)."""
    blob = torch.load(policy, map_location="cpu", weights_only=True)
    rounds = [{k: r[k] for k in ("round", "transitions", "validation_profit")} for r in summary["rounds"]]
    card = {**blob["card"], "algorithm": "dagger", "reproduce": command,
            "dagger": {"expert": summary["expert"], "start": summary["start"], "kept_round": summary["kept"], "rounds": rounds}}  # fmt: skip
    return write_policy(out, blob["state_dict"], card)
