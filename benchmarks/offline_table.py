"""The offline-learning table (the paper's "online (SAC) vs offline (BC, IQL, CQL)" in NY Brooklyn).

    python benchmarks/offline_table.py                 # from the shipped cards, no evaluation
    MARL_AMOD_DATA=... python benchmarks/offline_table.py --evaluate   # re-score every .pt on the report seeds

Rows: one per dataset (its card in ``docs/offline/datasets/``: behaviour policy, its score and
the ED / MPC-Oracle references on the same evaluation seeds). Columns: the behaviour policy,
online SAC (``policies/sac_gnn_<city>_fast.json``, 29 min on the batched path), and BC / IQL / CQL trained on the dataset
(``policies/<algo>_gnn_<city>_<dataset>.json``). Every cell is profit (mean +- std over the 10
evaluation episodes of ``marl-amod evaluate --seed 0``) and the normalised score (0 = equal
distribution, 100 = MPC-Oracle). Writes ``docs/offline/table.md`` and ``table.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

from marl_amod.datasets import normalised_score

ROOT = Path(__file__).resolve().parent.parent
DATASETS = ["inf", "dtv", "prop", "mpc_forecast", "prop_noise"]
ALGOS = ["bc", "iql", "cql"]
ONLINE = "sac_gnn_{city}_fast"


def score(card_path: Path, evaluate: bool) -> dict | None:
    """Profit mean/std of a shipped policy: from its card, or re-evaluated on the card's seeds."""
    if not card_path.is_file():
        return None
    card = json.loads(card_path.read_text())
    if evaluate:
        from marl_amod.evaluation import evaluate as run

        p = run(str(card_path.with_suffix(".pt")), card["scenario"], card.get("eval_episodes", 10), card.get("eval_seed", 0))
        return {"mean": p["metrics"]["profit"]["mean"], "std": p["metrics"]["profit"]["std"], "card": card}
    return {"mean": card["profit_mean"], "std": card["profit_std"], "card": card}


def build(city: str, cards: Path, policies: Path, evaluate: bool) -> dict:
    online = score(policies / f"{ONLINE.format(city=city)}.json", evaluate)
    rows = []
    for ds in DATASETS:
        path = cards / f"{city}_{ds}.json"
        if not path.is_file():
            continue
        dcard = json.loads(path.read_text())
        refs, beh = dcard["reference_scores"], dcard["behaviour_score"]
        row = {"dataset": ds, "behaviour_policy": dcard["policy"], "episodes": dcard["episodes"], "transitions": dcard["transitions"],
               "behaviour": {"mean": beh["mean"], "std": beh["std"], "normalised": normalised_score(beh["mean"], refs)}}
        if online:
            row["sac_online"] = {"mean": online["mean"], "std": online["std"], "normalised": normalised_score(online["mean"], refs)}
        for algo in ALGOS:
            s = score(policies / f"{algo}_gnn_{city}_{ds}.json", evaluate)
            if s is not None:
                row[algo] = {"mean": s["mean"], "std": s["std"], "normalised": normalised_score(s["mean"], refs),
                             "vs_behaviour_pct": 100.0 * (s["mean"] / beh["mean"] - 1.0),
                             "training_wall_s": s["card"].get("training_wall_s"), "updates": s["card"].get("updates")}
        rows.append(row)
    refs = json.loads((cards / f"{city}_{rows[0]['dataset']}.json").read_text())["reference_scores"] if rows else {}
    return {"scenario": city, "evaluation": {"episodes": 10, "seed": 0}, "reference_scores": refs, "rows": rows,
            "reproduce": ["marl-amod datasets --scenario nyc_brooklyn",
                          "marl-amod train --config configs/<algo>/nyc_brooklyn_<dataset>.yaml",
                          "python benchmarks/offline_table.py [--evaluate]"]}


def cell(entry: dict | None, bold: bool = False) -> str:
    if entry is None:
        return "-"
    text = f"{entry['mean'] / 1000:.1f}k ±{entry['std'] / 1000:.1f} ({entry['normalised']:.0f})"
    return f"**{text}**" if bold else text


def markdown(table: dict) -> str:
    refs = table["reference_scores"]
    lines = [
        f"Profit on {table['scenario']} (thousands of $, mean ± std over 10 evaluation episodes, seed 0; "
        "normalised score in brackets: 0 = equal distribution "
        f"{refs['equal-distribution']['mean'] / 1000:.1f}k, 100 = MPC-Oracle {refs['mpc-oracle']['mean'] / 1000:.1f}k). "
        "SAC is online (no dataset); BC, IQL and CQL learn from the dataset alone. Bold: the best offline result per row.",
        "",
        "| Dataset | Beh. pol. | SAC (online) | BC | IQL | CQL | BC vs beh. | best of IQL/CQL vs beh. |",
        "|---|---|---|---|---|---|---|---|",
    ]
    for r in table["rows"]:
        offline = [a for a in ALGOS if a in r]
        best = max(offline, key=lambda a: r[a]["mean"]) if offline else None
        rl = max([a for a in ("iql", "cql") if a in r], key=lambda a: r[a]["mean"], default=None)
        bc = f"{r['bc']['vs_behaviour_pct']:+.1f}%" if "bc" in r else "-"
        gain = f"{bc} | " + (f"{r[rl]['vs_behaviour_pct']:+.1f}% ({rl.upper()})" if rl else "-")
        lines.append(
            f"| {r['dataset'].upper().replace('_', '-')} ({r['episodes']} ep.) | {cell(r['behaviour'])} | {cell(r.get('sac_online'))} | "
            + " | ".join(cell(r.get(a), a == best) for a in ALGOS) + f" | {gain} |"
        )
    return "\n".join(lines) + "\n"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nyc_brooklyn")
    ap.add_argument("--cards", type=Path, default=ROOT / "docs/offline/datasets", help="folder of dataset cards")
    ap.add_argument("--policies", type=Path, default=ROOT / "policies")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/offline")
    ap.add_argument("--evaluate", action="store_true", help="re-evaluate every policy instead of reading its card")
    args = ap.parse_args()
    table = build(args.scenario, args.cards, args.policies, args.evaluate)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    md = markdown(table)
    (args.out / "table.md").write_text(md)
    print(md)


if __name__ == "__main__":
    main()
