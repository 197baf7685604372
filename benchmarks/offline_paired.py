"""Paired validation of offline recipes: each recipe's training seeds against a reference, episode by episode.

    python benchmarks/offline_paired.py --sets 7000 8000 --out runs/inf15/score.json \
        --reference cql=policies/cql_gnn_nyc_brooklyn_inf.pt \
        --recipe cql_l1=runs/inf15/cql_gnn_nyc_brooklyn_inf_l1.pt,runs/seeds/cql_gnn_nyc_brooklyn_inf_l1_s1.pt \
        --recipe behaviour=inf

Every policy (a policy file, or a registered policy such as a dataset's behaviour ``inf``) is
scored on each validation set (``--episodes`` episodes of ``marl-amod evaluate --seed <set>``;
the report seed 0 is refused: these are selection numbers) and its per-episode profits are kept in
``--out`` (keyed by the file's sha256 and the scenario, so a retrained file is scored again and the rest resumes).
A recipe is one or more training seeds' files; per episode its profit is their mean, and against
the reference (one file, the shipped cell; or another recipe, seed s against seed s) it gets the paired mean difference over all episodes
of all sets, its standard error (the per-episode differences' std / sqrt(episodes): the seeds
share the episodes, so they are not counted as independent), how many episodes it is above, and
each seed's own difference. ``passes``: the difference is at least ``--margin`` and two standard
errors (docs/offline/bc_fidelity.md, "BC fidelity" 12 and 15).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import sem

from marl_amod.config import REPORT_SEED


def profits(policy: str, scenario: str, seed: int, episodes: int, cache: dict[str, Any]) -> list[float]:
    """Per-episode profit of ``policy`` on validation set ``seed`` (from ``cache`` when there)."""
    from marl_amod.evaluation import evaluate
    from marl_amod.files import file_sha256

    if seed == REPORT_SEED:
        raise SystemExit(f"seed {REPORT_SEED} is the report seeds: validate on other sets")
    ident = file_sha256(policy)[:16] if Path(policy).is_file() else policy
    key = f"{policy}|{ident}|{scenario}@{seed}x{episodes}"  # another --scenario over the same --out is scored anew
    if key not in cache:
        result = evaluate(policy, scenario, episodes, seed)
        cache[key] = [float(m["profit"]) for m in result["per_episode"]]
        print(f"{policy} @ {seed}: {np.mean(cache[key]):,.0f}", flush=True)
    return cache[key]


def compare(recipe: np.ndarray, reference: np.ndarray, margin: float) -> dict[str, Any]:
    """``recipe`` (seeds, episodes) against ``reference`` (one file's or as many seeds' episodes): the
    paired test of the docs' rules."""
    if len(reference) not in (1, len(recipe)):
        raise SystemExit(f"a reference of {len(reference)} seeds pairs with one of 1 or {len(recipe)}")
    d = (recipe - reference).mean(0)
    se = float(sem(d))
    diff = float(d.mean())
    return {"diff": diff, "se": se, "above": int((d > 0).sum()), "episodes": int(d.size),
            "per_seed": [float(x) for x in (recipe - reference).mean(1)], "passes": diff >= margin and diff >= 2 * se}  # fmt: skip


def named(spec: str) -> tuple[str, list[str]]:
    name, _, files = spec.partition("=")
    if not name or not files:
        raise SystemExit(f"{spec!r}: give NAME=policy[,policy...]")
    return name, files.split(",")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nyc_brooklyn")
    ap.add_argument("--sets", type=int, nargs="+", required=True, help="validation seeds (never the report seed 0)")
    ap.add_argument("--episodes", type=int, default=10)
    ap.add_argument("--reference", action="append", default=[], help="NAME=policy: a shipped cell (one file)")
    ap.add_argument("--recipe", action="append", default=[], help="NAME=policy[,policy...]: one recipe's training seeds")
    ap.add_argument("--against", action="append", default=[], help="RECIPE:REFERENCE pairs to test")
    ap.add_argument("--margin", type=float, default=100.0)
    ap.add_argument("--out", type=Path, required=True)
    args = ap.parse_args()
    import torch

    torch.set_num_threads(1)
    known = [named(spec)[0] for spec in args.reference + args.recipe]
    for pair in args.against:  # before any episode is scored, not a KeyError after all of them
        if any(name not in known for name in pair.partition(":")[::2]):
            raise SystemExit(f"--against {pair!r}: give RECIPE:REFERENCE, two of the names {known}")
    table: dict[str, Any] = json.loads(args.out.read_text()) if args.out.is_file() else {}
    cache = table.setdefault("profits", {})
    scored: dict[str, np.ndarray] = {}
    for spec in args.reference + args.recipe:
        name, files = named(spec)
        scored[name] = np.array(
            [[p for s in args.sets for p in profits(f, args.scenario, s, args.episodes, cache)] for f in files]
        )
        args.out.parent.mkdir(parents=True, exist_ok=True)
        args.out.write_text(json.dumps(table, indent=1) + "\n")
    n = args.episodes
    table["summary"] = {name: {"sets": [float(p[:, i * n:(i + 1) * n].mean()) for i in range(len(args.sets))], "mean": float(p.mean()),
                               "per_seed": [float(x) for x in p.mean(1)]} for name, p in scored.items()}  # fmt: skip
    table["tests"] = {}
    for pair in args.against:
        rec, _, ref = pair.partition(":")
        table["tests"][pair] = compare(scored[rec], scored[ref], args.margin)
    args.out.write_text(json.dumps(table, indent=1) + "\n")
    for name, s in table["summary"].items():
        print(
            f"{name}: {' / '.join(f'{v / 1000:.2f}' for v in s['sets'])}k, mean {s['mean'] / 1000:.2f}k, seeds {', '.join(f'{v / 1000:.2f}' for v in s['per_seed'])}"
        )
    for pair, t in table["tests"].items():
        print(f"{pair}: {t['diff'] / 1000:+.2f}k ± {t['se'] / 1000:.2f}k (above in {t['above']} of {t['episodes']}; per seed "
              f"{' / '.join(f'{x / 1000:+.2f}' for x in t['per_seed'])}) {'PASSES' if t['passes'] else 'does not pass'}")  # fmt: skip


if __name__ == "__main__":
    main()
