"""Scenario MPC (``mpc-scenarios``) against MPC-Forecast, plain and scaled, on validation episodes.

    python benchmarks/mpc_scenarios.py --scenario synthetic --episodes 60 --seed 3000 \
        --scenarios 4 8 --horizon 10 --output runs/mpc_scenarios.json

Every variant plays the same episodes (episode k draws demand from (seed, k)), so differences are
paired (``paired`` from ``mpc_demand_scale.py``): against MPC-Forecast at its default horizon and
against the scaled forecast (``demand_scale`` 1.2 at horizon 10, the adopted teacher). The JSON is
rewritten after each variant and variants already in it are skipped, so a stopped run resumes.
Use validation seeds (not the report seeds 0..9) when the result chooses a teacher.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from mpc_demand_scale import paired, resume

from marl_amod.evaluation import evaluate
from marl_amod.scenario import load_city


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--episodes", type=int, default=30)
    parser.add_argument("--seed", type=int, default=3000)
    parser.add_argument("--scenarios", type=int, nargs="+", default=[4, 8])
    parser.add_argument("--horizon", type=int, default=10)
    parser.add_argument("--output", type=Path, default=Path("runs/mpc_scenarios.json"))
    args = parser.parse_args()

    city = load_city(args.scenario)
    done = resume(args.output, city.name, args.episodes, args.seed)
    variants = {
        "forecast_h20": ("mpc-forecast", {}),
        f"forecast_h{args.horizon}_s1.2": ("mpc-forecast", {"horizon": args.horizon, "demand_scale": 1.2}),
    } | {f"scenarios_h{args.horizon}_S{s}": ("mpc-scenarios", {"horizon": args.horizon, "scenarios": s}) for s in args.scenarios}
    for key, (policy, options) in variants.items():
        if key in done["variants"]:
            continue
        start = time.perf_counter()
        res = evaluate(policy, city, args.episodes, args.seed, **options)
        done["variants"][key] = {
            "policy": res["policy"],
            "options": options,
            "profit": [ep["profit"] for ep in res["per_episode"]],
            "served": [ep["served_demand"] for ep in res["per_episode"]],
            "reb_cost": [ep["rebalancing_cost"] for ep in res["per_episode"]],
            "seconds": time.perf_counter() - start,
        }
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(done, indent=1))
    refs = [k for k in variants if k in done["variants"]][:2]
    print(f"{city.name}: {args.episodes} episodes from seed {args.seed}; paired against {' and '.join(refs)}")
    for key, v in done["variants"].items():
        diffs = "  ".join(
            "vs {}: {:+7.1f} ± {:4.1f}".format(r, *paired(np.asarray(v["profit"]), np.asarray(done["variants"][r]["profit"])).values())
            for r in refs
        )
        print(
            f"{key:>22}  profit {np.mean(v['profit']):>9,.1f}  served {np.mean(v['served']):6.1f}  "
            f"reb {np.mean(v['reb_cost']):6.1f}  {diffs}  ({v['seconds'] / args.episodes:.2f} s/episode)"
        )


if __name__ == "__main__":
    main()
