"""How good a forecast MPC-Forecast needs: its gap to MPC-Oracle as its demand forecast gets noisier.

    python benchmarks/mpc_forecast_noise.py            # -> docs/meta/forecast_noise.md and .json

Why: the paper's MPC-Forecast plans on "a noisy and unbiased estimate of demand" whose noise it
does not give (RL4AMOD's public code has only the oracle MPC), and it lands 1.2-17.4% below
MPC-Oracle on the generalisation tables; ours plans on the exact expected rates the simulator
draws from (noise 0, every table here) and lands 0.9-4.0% below it. This measures ours with
``MPCForecast(noise=s)``: each planned rate times a mean-one log-normal factor of standard
deviation s, drawn afresh per OD pair, step and plan, on the tables' report episodes (seed 0: a
baseline measured, nothing chosen), next to equal distribution and MPC-Oracle on the same
episodes, so the gaps and normalised scores read like the tables' (docs/meta/README.md).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from marl_amod.evaluation import evaluate
from marl_amod.metrics import SCORE_ANCHORS, normalised_score
from marl_amod.scenario import load_city

SCENARIOS = ["san_francisco", "nyc_brooklyn", "shenzhen_downtown_west", "nyc_brooklyn_event"]
NOISES = [0.0, 0.5, 1.0, 2.0]
# the paper's MPC-Forecast below its MPC-Oracle (profit, thousands): the inter-city and special-event tables
PAPER_GAP = {"san_francisco": (13.9, 15.9), "nyc_brooklyn": (56.5, 57.2), "shenzhen_downtown_west": (60.6, 65.2),
             "nyc_brooklyn_event": (47.5, 57.5)}  # fmt: skip


def mean_profit(policy: str, scenario: str, episodes: int, seed: int, **options: float) -> float:
    result = evaluate(policy, load_city(scenario), episodes, seed, **options)
    return float(np.mean([ep["profit"] for ep in result["per_episode"]]))


def table(rows: dict, noises: list[float], episodes: int, seed: int) -> str:
    """The markdown page: one row per scenario, MPC-Forecast's gap (score) at each noise, under the
    command that makes it (the scenarios and noises named when they are not the defaults)."""
    command = f"python benchmarks/mpc_forecast_noise.py --episodes {episodes} --seed {seed}"
    command += f" --noises {' '.join(f'{s:g}' for s in noises)}" if list(noises) != NOISES else ""
    command += f" --scenarios {' '.join(rows)}" if list(rows) != SCENARIOS else ""
    lines = [
        f"<!-- {command} -->",
        f"MPC-Forecast's profit gap to MPC-Oracle (normalised score in brackets: equal distribution 0, "
        f"MPC-Oracle 100) as its forecast's log-normal noise grows; {episodes} episodes, seed {seed} (the tables' "
        "report episodes). The last column is the paper's MPC-Forecast against its own MPC-Oracle.",
        "",
        "| scenario | " + " | ".join(f"noise {s:g}" for s in noises) + " | the paper |",
        "|---|" + "---:|" * (len(noises) + 1),
    ]
    for scenario, r in rows.items():
        cells = []
        for s in noises:
            p = r["mpc-forecast"][f"{s:g}"]
            score = normalised_score(p, *(r[name] for name in SCORE_ANCHORS))
            cells.append(f"{100 * (1 - p / r['mpc-oracle']):.1f}% ({score:.0f})")
        forecast, oracle = PAPER_GAP[scenario]
        lines.append(f"| {scenario} | " + " | ".join(cells) + f" | {100 * (1 - forecast / oracle):.1f}% |")
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=SCENARIOS)
    parser.add_argument("--noises", type=float, nargs="+", default=NOISES)
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--output", type=Path, default=Path("docs/meta/forecast_noise.md"))
    args = parser.parse_args()
    unknown = sorted(set(args.scenarios) - set(PAPER_GAP))
    if unknown:
        raise SystemExit(f"no paper number for {unknown}; scenarios: {sorted(PAPER_GAP)}")

    rows = {}
    for scenario in args.scenarios:
        refs = {p: mean_profit(p, scenario, args.episodes, args.seed) for p in SCORE_ANCHORS}
        noisy = {f"{s:g}": mean_profit("mpc-forecast", scenario, args.episodes, args.seed, noise=s) for s in args.noises}
        rows[scenario] = {**refs, "mpc-forecast": noisy}
        print(scenario, {k: round(v) for k, v in refs.items()}, {k: round(v) for k, v in noisy.items()}, flush=True)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(table(rows, args.noises, args.episodes, args.seed))
    args.output.with_suffix(".json").write_text(json.dumps({"episodes": args.episodes, "seed": args.seed, "profit": rows}, indent=1))
    print(f"wrote {args.output} and {args.output.with_suffix('.json')}")


if __name__ == "__main__":
    main()
