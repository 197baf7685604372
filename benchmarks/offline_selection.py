"""Q-guided action selection on an offline cell: does playing the critic's best candidate beat the mean?

    python benchmarks/offline_selection.py                       # MPC-Forecast: IQL and CQL, training seeds 0 1 2 (4 min)
    python benchmarks/offline_selection.py --configs configs/iql/nyc_brooklyn_mpc_forecast_expectile09.yaml \
        --candidates 8 32 --concentrations 1000 10000 --report  # a sharper IQL critic, then the chosen setting on the report seeds

The page's table (docs/offline/bc_fidelity.md, "BC fidelity" 8) is what the script prints at the end.

For each config (default: IQL and CQL on the MPC-Forecast dataset) and training seed this trains
the config again with its critic shipped in the file (``runs/selection/<stem>_s<seed>.pt``; seed s
starts from the BC policy's seed-s run where ``benchmarks/offline_seeds.py`` trained one, as the
seeds table does, so the actor is that table's), then:

* checks the critic where the data can: on the dataset's held-out episodes (the last 10%), how
  often it scores the logged action above the actor's mean (a critic that can pick better actions
  must at least prefer the behaviour's own action to a clone's miss of it);
* evaluates the policy on both validation seed sets (1000+ and 2000+, 10 episodes each; never the
  report seeds) with no selection (the mean) and with every setting of the grid (``--candidates``
  x ``--concentrations``, min of the twin critics).

The setting chosen is the (config, candidates, concentration) with the highest mean over seeds
and both validation sets; ``--report`` scores it, and the mean, once on the report seeds (10
episodes, seed 0) for every training seed. Results go to ``docs/offline/selection.json``; every
training run and evaluation already there is reused, so an interrupted run resumes.
"""

from __future__ import annotations

import argparse
import itertools
import json
import time
from pathlib import Path
from typing import Any

import numpy as np
import torch

ROOT = Path(__file__).resolve().parent.parent
OUT_DIR = Path("runs/selection")
CONFIGS = [ROOT / "configs/iql/nyc_brooklyn_mpc_forecast.yaml", ROOT / "configs/cql/nyc_brooklyn_mpc_forecast.yaml"]
VALIDATION = (1000, 2000)
REPORT = 0


def train(config: Path, seed: int) -> Path:
    """The config's seed-``seed`` run with its critic in the policy file (trained once, then reused)."""
    from offline_seeds import seed_path  # the sibling script (benchmarks/ is on sys.path when this one runs)

    from marl_amod.algos.registry import load_train_config, run_training

    algo, args = load_train_config(config)
    stem = Path(args.policy_out).stem
    out = OUT_DIR / f"{stem}_s{seed}.pt"
    if out.is_file():
        return out
    update: dict[str, Any] = {"seed": seed, "run_dir": str(OUT_DIR / f"{stem}_s{seed}"), "policy_out": str(out)}
    if args.init_actor and seed_path(args.init_actor, seed).is_file():
        update["init_actor"] = str(seed_path(args.init_actor, seed))
    t = time.time()
    run_training(algo, args.model_copy(update=update), config_path=str(config))
    print(f"{out.name}: trained in {time.time() - t:.0f} s", flush=True)
    return out


@torch.no_grad()
def critic_prefers_logged(policy: Path, held_out: float = 0.1) -> float:
    """Share of the dataset's held-out transitions where the file's critic scores the logged action
    above the actor's mean (0.5: the critic cannot tell them apart)."""
    from marl_amod.checkpoints import load_actor, load_critic
    from marl_amod.datasets import OfflineDataset
    from marl_amod.models.dense import DenseGraph
    from marl_amod.scenario import load_city

    city = load_city(json.loads(policy.with_suffix(".json").read_text())["scenario"])
    actor, card = load_actor(policy, city)
    critic, _ = load_critic(policy)
    view = OfflineDataset.load(card["args"]["dataset"]).global_view()
    start = int(len(view["x"]) * (1 - held_out))
    x, y = torch.tensor(view["x"][start:]), torch.tensor(view["action"][start:])
    graph = DenseGraph(torch.tensor(np.array(city.edge_index), dtype=torch.long), city.n_regions)
    alpha = actor(x, graph)
    mean = alpha / alpha.sum(-1, keepdim=True)
    q_logged, q_mean = (torch.min(*critic(x, graph, a)) for a in (y / y.sum(-1, keepdim=True), mean))
    return float((q_logged > q_mean).float().mean())


def profit(policy: Path, selection: dict[str, Any] | None, seed: int, episodes: int = 10) -> dict[str, float]:
    from marl_amod.checkpoints import load_policy
    from marl_amod.evaluation import evaluate

    card = json.loads(policy.with_suffix(".json").read_text())
    off = {"candidates": 0, "concentration": 1.0}
    m = evaluate(load_policy(policy, card["scenario"], selection=selection or off), card["scenario"], episodes, seed)["metrics"]
    return {"profit": m["profit"]["mean"], "served": m["served_demand"]["mean"]}


def evaluate_policy(name: str, scenario: str, seed: int, episodes: int = 10) -> dict[str, float]:
    """A registered policy (the dataset's behaviour policy) on the same seeds."""
    from marl_amod.evaluation import evaluate

    m = evaluate(name, scenario, episodes, seed)["metrics"]
    return {"profit": m["profit"]["mean"], "served": m["served_demand"]["mean"]}


def setting_name(selection: dict[str, Any] | None) -> str:
    return "mean" if selection is None else f"n{selection['candidates']}_c{selection['concentration']:g}"


def summary(table: dict[str, Any]) -> str:
    """The page's table: validation profit per setting (mean over training seeds, k$), each config a column pair."""
    runs = [r for r in table.values() if isinstance(r, dict) and "validation" in r]
    configs = sorted({r["config"] for r in runs}, key=lambda c: ("cql" in c, c))
    settings = sorted({k.split("@")[0] for r in runs for k in r["validation"]}, key=lambda s: (s != "mean", len(s), s))
    head = "| setting | " + " | ".join(f"{Path(c).parent.name} {Path(c).stem.removeprefix('nyc_brooklyn_mpc_forecast').strip('_') or ''}".strip() + f", {v}+" for c in configs for v in VALIDATION) + " |"
    lines = [head, "|---" * (1 + 2 * len(configs)) + "|"]
    for setting in settings:
        cells = []
        for config, v in itertools.product(configs, VALIDATION):
            vals = [r["validation"][f"{setting}@{v}"]["profit"] for r in runs if r["config"] == config and f"{setting}@{v}" in r["validation"]]
            cells.append(f"{np.mean(vals) / 1000:.2f}k" if vals else "-")
        lines.append(f"| {setting} | " + " | ".join(cells) + " |")
    prefers = {c: [round(r["critic_prefers_logged"], 2) for r in runs if r["config"] == c] for c in configs}
    lines.append("")
    lines.append("critic scores the logged action above the actor's mean (held-out transitions, per seed): " + "; ".join(f"{Path(c).parent.name} {Path(c).stem}: {v}" for c, v in prefers.items()))
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=Path, nargs="+", default=CONFIGS)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--candidates", type=int, nargs="+", default=[8, 32])
    ap.add_argument("--concentrations", type=float, nargs="+", default=[100.0, 1000.0, 10000.0])
    ap.add_argument("--report", action="store_true", help="score the validation-chosen setting (and the mean) on the report seeds")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/offline/selection.json")
    args = ap.parse_args()
    from marl_amod.algos.registry import load_train_config

    torch.set_num_threads(1)
    table: dict[str, Any] = json.loads(args.out.read_text()) if args.out.is_file() else {}
    grid = [None] + [{"candidates": n, "concentration": c, "seed": 0} for n, c in itertools.product(args.candidates, args.concentrations)]

    def save() -> None:
        args.out.write_text(json.dumps(table, indent=2, sort_keys=True) + "\n")

    behaviour = table.setdefault("_behaviour", {})
    for config in args.configs:
        data_card = json.loads(Path(load_train_config(config)[1].dataset).with_suffix(".json").read_text())
        for seed in (*VALIDATION, REPORT):
            key = f"{data_card['policy']}@{seed}"
            if key not in behaviour:
                m = evaluate_policy(data_card["policy"], data_card["scenario"], seed)
                behaviour[key] = m
                print(f"behaviour {key}: {m['profit']:,.0f}", flush=True)
        for seed in args.seeds:
            policy = train(config, seed)
            run = table.setdefault(f"{policy.stem}", {"config": str(config.resolve().relative_to(ROOT)), "seed": seed, "validation": {}})
            card = json.loads(policy.with_suffix(".json").read_text())
            run.update(policy=str(policy), start=card["args"]["init_actor"], kept=card["kept"], best_validation=card["best_validation"], report_mean=card["profit_mean"])
            if "critic_prefers_logged" not in run:
                run["critic_prefers_logged"] = critic_prefers_logged(policy)
            for selection, val in itertools.product(grid, VALIDATION):
                key = f"{setting_name(selection)}@{val}"
                if key not in run["validation"]:
                    run["validation"][key] = profit(policy, selection, val)
                    print(f"{policy.stem} {key}: {run['validation'][key]['profit']:,.0f}", flush=True)
            save()
    # the choice: the highest mean over seeds and both validation sets
    scores: dict[tuple[str, str], list[float]] = {}
    for run in table.values():
        if not isinstance(run, dict) or "validation" not in run:
            continue
        for key, r in run["validation"].items():
            scores.setdefault((run["config"], key.split("@")[0]), []).append(r["profit"])
    means = {k: float(np.mean(v)) for k, v in scores.items()}
    best = max((k for k in means if k[1] != "mean"), key=means.get)
    table["_chosen"] = {"config": best[0], "setting": best[1], "validation_mean": means[best],
                        "mean_validation_mean": means[(best[0], "mean")]}  # fmt: skip
    print(f"chosen: {best[0]} {best[1]} validates {means[best]:,.0f} (its mean: {means[(best[0], 'mean')]:,.0f})", flush=True)
    if args.report:
        n, c = best[1][1:].split("_c")
        chosen = {"candidates": int(n), "concentration": float(c), "seed": 0}
        for run in (r for r in table.values() if isinstance(r, dict) and "validation" in r and r["config"] == best[0]):
            report = run.setdefault("report", {})
            for selection in (None, chosen):
                if setting_name(selection) not in report:
                    report[setting_name(selection)] = profit(Path(run["policy"]), selection, REPORT)
                    print(f"{Path(run['policy']).stem} {setting_name(selection)}@report: {report[setting_name(selection)]['profit']:,.0f}", flush=True)
    save()
    print(summary(table))


if __name__ == "__main__":
    main()
