"""MPC-Forecast's ``demand_scale`` (and horizon) on validation episodes, paired against the plain forecast.

    python benchmarks/mpc_demand_scale.py --scenario synthetic --episodes 50 --seed 2000 \
        --scales 1.0 1.1 1.2 1.35 1.5 1.75 --horizons 20 10 --output runs/mpc_demand_scale.json

Every variant plays the same episodes (episode k draws demand from (seed, k)), so the difference
to the reference (scale 1, the first horizon) is paired: its standard error is the spread of the
per-episode differences over sqrt(episodes), far tighter than the spread across episodes. The
JSON is rewritten after each variant and variants already in it are skipped, so a stopped sweep
resumes. Use validation seeds (not the report seeds 0..9) when the result chooses a teacher.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np
from scipy.stats import sem

from marl_amod.evaluation import evaluate
from marl_amod.scenario import load_city


def paired(profit: np.ndarray, reference: np.ndarray) -> dict[str, float]:
    """Mean and standard error of the per-episode difference to the reference."""
    diff = profit - reference
    return {"diff": float(diff.mean()), "se": float(sem(diff, axis=None))}


def resume(output: Path, scenario: str, episodes: int, seed: int) -> dict:
    """The results a paired sweep wrote so far (none: a new one); a file of another sweep is refused,
    since its episodes would not pair with these."""
    done = json.loads(output.read_text()) if output.exists() else {}
    if done and (done["scenario"], done["episodes"], done["seed"]) != (scenario, episodes, seed):
        raise SystemExit(f"{output} holds another sweep; give another --output")
    return {"scenario": scenario, "episodes": episodes, "seed": seed, "variants": done.get("variants", {})}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--episodes", type=int, default=50)
    parser.add_argument("--seed", type=int, default=2000)
    parser.add_argument("--scales", type=float, nargs="+", default=[1.0, 1.1, 1.2, 1.35, 1.5])
    parser.add_argument("--horizons", type=int, nargs="+", default=[20])
    parser.add_argument("--output", type=Path, default=Path("runs/mpc_demand_scale.json"))
    args = parser.parse_args()

    city = load_city(args.scenario)
    done = resume(args.output, city.name, args.episodes, args.seed)
    ref_key = f"h{args.horizons[0]}_s1"
    variants = [(args.horizons[0], 1.0)] + [
        (h, s) for h in args.horizons for s in args.scales if (h, s) != (args.horizons[0], 1.0)
    ]
    for horizon, scale in variants:
        key = f"h{horizon}_s{scale:g}"
        if key in done["variants"]:
            continue
        start = time.perf_counter()
        res = evaluate("mpc-forecast", city, args.episodes, args.seed, horizon=horizon, demand_scale=scale)
        profit = [ep["profit"] for ep in res["per_episode"]]
        done["variants"][key] = {
            "horizon": horizon,
            "demand_scale": scale,
            "profit": profit,
            "served": [ep["served_demand"] for ep in res["per_episode"]],
            "reb_cost": [ep["rebalancing_cost"] for ep in res["per_episode"]],
            "seconds": time.perf_counter() - start,
        }
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(done, indent=1))
    ref = np.asarray(done["variants"][ref_key]["profit"])
    print(f"{city.name}: {args.episodes} episodes from seed {args.seed}; paired against {ref_key} ({ref.mean():,.1f})")
    for key, v in done["variants"].items():
        p = paired(np.asarray(v["profit"]), ref)
        print(f"{key:>10}  profit {np.mean(v['profit']):>9,.1f}  diff {p['diff']:+8.1f} ± {p['se']:5.1f}  ({v['seconds']:.0f} s)")


if __name__ == "__main__":
    main()
