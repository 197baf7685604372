"""Profit of every non-learning baseline per city, with the wall time of one control step.

    MARL_AMOD_DATA=/path/to/data python benchmarks/baselines_table.py --episodes 10 --output results.json

Each policy runs ``--episodes`` episodes (episode k draws demand from (seed, k), the same draws
for every policy); a control step is the policy's decision plus the coordinator's rebalancing,
the simulator's advance and the next dispatch. Prints a markdown table; cities whose data is
missing are skipped with a note.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

from marl_amod.errors import DataError
from marl_amod.evaluation import evaluate
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city

CITIES = ["synthetic", "nyc_brooklyn", "san_francisco", "shenzhen_downtown_west"]
POLICIES = ["no-rebalancing", "equal-distribution", "plus-one", "inf", "dtv", "prop", "mpc-forecast", "mpc-oracle"]


def run(cities: list[str], policies: list[str], episodes: int, seed: int) -> list[dict]:
    rows = []
    for name in cities:
        try:
            city = load_city(name)
        except DataError as exc:
            print(f"skipping {name}: {exc}")
            continue
        for pol_name in policies:
            policy = make_policy(pol_name, city)
            start = time.perf_counter()
            result = evaluate(policy, city, episodes, seed)
            seconds = time.perf_counter() - start
            profit = result["metrics"]["profit"]
            rows.append({
                "city": city.name, "policy": pol_name, "episodes": episodes, "seed": seed,
                "profit_mean": profit["mean"], "profit_std": profit["std"],
                "served_mean": result["metrics"]["served_demand"]["mean"],
                "rebalancing_cost_mean": result["metrics"]["rebalancing_cost"]["mean"],
                "ms_per_step": 1000 * seconds / (episodes * (city.horizon - 1)),
                "horizon": getattr(policy, "horizon", None),
            })
            print(f"{city.name:24s} {pol_name:20s} {profit['mean']:12,.0f} ± {profit['std']:8,.0f}", flush=True)
    return rows


def markdown(rows: list[dict]) -> str:
    """Cities as blocks of rows; the best mean profit per city in bold."""
    best = {}
    for r in rows:
        best[r["city"]] = max(best.get(r["city"], float("-inf")), r["profit_mean"])
    lines = ["| city | policy | profit (mean ± std) | served | rebalancing cost | ms / step |", "|---|---|---:|---:|---:|---:|"]
    for r in rows:
        profit = f"{r['profit_mean']:,.0f} ± {r['profit_std']:,.0f}"
        if r["profit_mean"] == best[r["city"]]:
            profit = f"**{profit}**"
        lines.append(
            f"| {r['city']} | {r['policy']} | {profit} | {r['served_mean']:,.0f} | {r['rebalancing_cost_mean']:,.0f} | {r['ms_per_step']:.1f} |"
        )
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cities", nargs="+", default=CITIES)
    parser.add_argument("--policies", nargs="+", default=POLICIES)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=None, help="also write the rows as JSON here")
    args = parser.parse_args()
    rows = run(args.cities, args.policies, args.episodes, args.seed)
    print()
    print(markdown(rows))
    if args.output is not None:
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(rows, indent=2))


if __name__ == "__main__":
    main()
