"""Training seeds of the offline table: each config trained with several seeds, scored on the report seeds.

    python benchmarks/offline_seeds.py --configs configs/bc/nyc_brooklyn_dtv.yaml --seeds 0 1 2
    python benchmarks/offline_seeds.py --configs configs/cql/nyc_brooklyn_inf.yaml --seeds 0 1 2

One offline run is one draw of minibatches, initial weights and (``keep: best``) validation
checkpoints: the table's single policy per cell says little about the next run. For every
config and seed this trains the config with ``seed`` replaced (logs, policy and card under
``runs/seeds/``; the config's own seed is the shipped policy, reused when its card was trained
from the same arguments), reads the card's profit on the report seeds (10 episodes, seed 0) and
records it in ``docs/offline/seeds.json`` keyed by the policy's file stem.
``benchmarks/offline_table.py`` reports mean +- std over the training seeds beside each cell.

A config that starts from another policy (``init_actor``, the BC start of CQL and of the
conservative IQL) starts seed s from that policy's seed-s run where it has been trained (train the
start's seeds first: then the seeds are independent end to end), else from the config's own start
(the shipped BC policy: the seeds then vary the improvement step only); each result records its start, and a
run whose start was retrained since (its card's `start_sha256`) is trained again.
Each (config, seed) already in the file with the same arguments is skipped, so an interrupted
sweep resumes; each run is one offline training (minutes), so run the sweep in pieces.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parent.parent
SEED_DIR = Path("runs/seeds")
RUN_KEYS = ("seed", "run_dir", "policy_out", "init_actor")  # what differs between the seeds of one cell


def seed_path(policy_out: str, seed: int) -> Path:
    """Where seed ``seed`` of the policy ``policy_out`` lives (the shipped file for the config's own seed)."""
    return SEED_DIR / f"{Path(policy_out).stem}_s{seed}.pt"


def seed_args(args: Any, seed: int) -> Any:
    """``args`` for training seed ``seed``: its own logs and policy file, its start's seed-s run."""
    if seed == args.seed:
        return args
    stem = Path(args.policy_out).stem
    update = {"seed": seed, "run_dir": str(SEED_DIR / f"{stem}_s{seed}"), "policy_out": str(seed_path(args.policy_out, seed))}
    if args.init_actor and seed_path(args.init_actor, seed).is_file():
        update["init_actor"] = str(seed_path(args.init_actor, seed))
    return args.model_copy(update=update)


def essential(cls: type, values: dict[str, Any]) -> dict[str, Any]:
    """``values`` (run arguments as JSON) without where a run writes and without the arguments at
    their default: an option added to the run arguments after a run was recorded (off by default)
    leaves that run the same experiment, so it is not retrained."""
    from pydantic_core import to_jsonable_python

    defaults = {k: to_jsonable_python(f.get_default(call_default_factory=True))
                for k, f in cls.model_fields.items() if not f.is_required()}  # fmt: skip
    return {k: v for k, v in values.items() if k not in RUN_KEYS and not (k in defaults and defaults[k] == v)}


def comparable(args: Any) -> dict[str, Any]:
    """The arguments that make two runs the same experiment (all but where they write and the defaults)."""
    return essential(type(args), args.model_dump(mode="json"))


def started_elsewhere(card: dict[str, Any], start: str | None) -> bool:
    """Whether the policy of ``card`` was trained from another version of ``start`` than the file
    there now (its start was retrained since), by content: the card's ``start_sha256``. Cards
    written before it was recorded count as current (file times say nothing after a clone)."""
    from marl_amod.files import file_sha256

    recorded = card.get("start_sha256")
    return bool(start) and recorded is not None and Path(start).is_file() and file_sha256(start) != recorded


def run_one(config: Path, seed: int, done: dict[str, Any], retrain: bool = False) -> dict[str, Any] | None:
    """Train (or reuse) one seed of ``config``; None when ``done`` already has it with these arguments
    (``retrain``: train it anyway, e.g. when the policy it starts from was retrained)."""
    from marl_amod.algos.registry import load_train_config, run_training

    algo, base = load_train_config(config)
    args = seed_args(base, seed)
    key = Path(base.policy_out).stem
    same = comparable(args)
    recorded = essential(type(args), done[key]["args"]) if key in done else None
    if not retrain and recorded == same and str(seed) in done[key]["seeds"]:
        return None
    card_path = Path(args.policy_out).with_suffix(".json")
    card = json.loads(card_path.read_text()) if card_path.is_file() else None
    stale = card is not None and started_elsewhere(card, args.init_actor)
    if retrain or stale or card is None or essential(type(args), card.get("args", {})) != same:
        t = time.time()
        card = run_training(algo, args, config_path=str(config))["card"]
        print(f"{key} seed {seed}: trained in {time.time() - t:.0f} s", flush=True)
    return {"key": key, "config": str(config), "args": same, "seed": seed,
            "result": {"profit_mean": card["profit_mean"], "profit_std": card["profit_std"],
                       "best_validation": card.get("best_validation"), "training_wall_s": card.get("training_wall_s"),
                       "policy": str(args.policy_out), "start": args.init_actor or None}}  # fmt: skip


def record(path: Path, entry: dict[str, Any]) -> None:
    """Add one seed's result to ``path`` (a config whose arguments changed starts its cell afresh)."""
    table = json.loads(path.read_text()) if path.is_file() else {}
    cell = table.get(entry["key"])
    if cell is None or cell["args"] != entry["args"]:  # both from comparable(): defaults left out
        cell = {"config": entry["config"], "args": entry["args"], "seeds": {}}
    cell["seeds"][str(entry["seed"])] = entry["result"]
    table[entry["key"]] = dict(sorted(cell.items()))
    path.write_text(json.dumps(dict(sorted(table.items())), indent=2) + "\n")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", type=Path, nargs="+", required=True)
    ap.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    ap.add_argument("--retrain", action="store_true", help="train every (config, seed) even where its policy and card exist")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/offline/seeds.json")
    args = ap.parse_args()
    for config in args.configs:
        for seed in args.seeds:
            done = json.loads(args.out.read_text()) if args.out.is_file() else {}
            entry = run_one(config, seed, done, args.retrain)
            if entry is not None:
                record(args.out, entry)
                r = entry["result"]
                print(f"{entry['key']} seed {seed}: {r['profit_mean']:,.0f} ± {r['profit_std']:,.0f}", flush=True)


if __name__ == "__main__":
    main()
