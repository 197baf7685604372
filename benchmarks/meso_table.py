"""The Luxembourg meso table of docs/meso: every policy's profit, its paired difference from equal
distribution on the same seeds, rebalancing cost, waiting time, utilisation and the equity metrics.

    python benchmarks/meso_table.py runs/meso_eval/*.json [--reuse docs/results/lux.json] \
        [--label "a2c_gnn_lux=Graph-RL trained in meso"] [--out docs/meso/lux_meso]

Inputs are ``marl-amod evaluate --output`` files (one policy each, or several under "results").
``--reuse`` adds the rows of a committed results table for policies not measured here (they are
marked with their own episode count). Writes ``<out>.json`` (the records, per-episode values
dropped) and ``<out>.md`` (the table).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.metrics import SCORE_ANCHORS

ORDER = ("no-rebalancing", "plus-one", "equal-distribution")  # then trained policies, then the MPCs


def records(path: Path) -> list[dict[str, Any]]:
    data = json.loads(path.read_text())
    return data["results"] if "results" in data else [data]


def paired_gap(row: dict[str, Any], floor: dict[str, Any] | None) -> str:
    """Profit minus equal distribution's on the same episodes (same seed, same demand):
    mean ± std over the episodes both ran, and how many episodes the row wins."""
    if floor is None or "per_episode" not in row or "per_episode" not in floor or row is floor:
        return "–"
    if row.get("seed") != floor.get("seed"):
        return "–"
    k = min(len(row["per_episode"]), len(floor["per_episode"]))
    d = np.array([row["per_episode"][i]["profit"] - floor["per_episode"][i]["profit"] for i in range(k)])
    return f"{d.mean():+,.0f} ± {d.std():,.0f} ({int((d > 0).sum())}/{k})"


def cell(metrics: dict[str, Any], key: str, digits: int = 0, percent: bool = False) -> str:
    m = metrics.get(key)
    if m is None:
        return "–"
    scale, suffix = (100.0, "%") if percent else (1.0, "")
    text = f"{scale * m['mean']:,.{digits}f}{suffix}"
    return text + (f" ± {scale * m['std']:,.{digits}f}{suffix}" if "std" in m else "")


def markdown(rows: list[dict[str, Any]]) -> str:
    by_name = {r["policy"]: r for r in rows}
    floor, ceiling = (by_name.get(name) for name in SCORE_ANCHORS)
    head = (
        "| policy | episodes | profit | vs ED, paired (wins) | % of MPC-Oracle | rebalancing cost | wait (min) "
        "| utilisation | wait Gini | service-rate Gini |"
    )
    lines = [head, "|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|"]
    for r in rows:
        m = r["metrics"]
        rel = f"{100 * (m['profit']['mean'] / ceiling['metrics']['profit']['mean'] - 1):+.1f}%" if ceiling else "–"
        lines.append(
            f"| {r.get('label', r['policy'])} | {r['episodes']} | {cell(m, 'profit')} | {paired_gap(r, floor)} | {rel} "
            f"| {cell(m, 'rebalancing_cost')} | {cell(m, 'wait_time', 2)} | {cell(m, 'utilization', percent=True)} "
            f"| {cell(m, 'wait_time_gini', 3)} | {cell(m, 'service_rate_gini', 3)} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("inputs", nargs="+", type=Path)
    parser.add_argument("--reuse", type=Path, default=None, help="a committed table whose other rows are added")
    parser.add_argument("--out", default="docs/meso/lux_meso")
    parser.add_argument("--label", action="append", default=[], metavar="POLICY=TEXT", help="the row label of a policy (repeatable)")
    args = parser.parse_args()
    labels = dict(item.split("=", 1) for item in args.label)
    rows = [dict(r, label=labels[r["policy"]]) if r["policy"] in labels else r for p in args.inputs for r in records(p)]
    if args.reuse:
        measured = {r["policy"] for r in rows}
        rows += [
            dict(r, label=f"{r['policy']} (reused from {args.reuse})") for r in records(args.reuse) if r["policy"] not in measured
        ]
    rank = lambda r: ORDER.index(r["policy"]) if r["policy"] in ORDER else 4 if r["policy"].startswith("mpc") else 3  # noqa: E731
    rows.sort(key=rank)
    md = markdown(rows)
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    out.with_suffix(".md").write_text(md)
    keep = [
        {k: v for k, v in r.items() if k != "per_episode"} | {"episode_profit": [e["profit"] for e in r.get("per_episode", [])]}
        for r in rows
    ]
    out.with_suffix(".json").write_text(json.dumps({"scenario": "lux", "results": keep}, indent=1))
    print(md)


if __name__ == "__main__":
    main()
