"""The offline-learning table (the paper's "online (SAC) vs offline (BC, IQL, CQL)" in NY Brooklyn).

    python benchmarks/offline_table.py                 # from the shipped cards, no evaluation
    MARL_AMOD_DATA=... python benchmarks/offline_table.py --evaluate   # re-score every .pt on the report seeds

Rows: one per dataset (its card in ``docs/offline/datasets/``: behaviour policy, its score and
the ED / MPC-Oracle references on the same evaluation seeds). Columns: the behaviour policy,
online SAC (``policies/sac_gnn_<city>_fast.json``, 29 min on the batched path), and BC / IQL / CQL trained on the dataset
(``policies/<algo>_<actor>_<city>_<dataset>.json``, actor ``gnn`` or ``mlp``: the file names the actor the card
records). Every cell is profit (mean +- std over the 10
evaluation episodes of ``marl-amod evaluate --seed 0``) and the normalised score (0 = equal
distribution, 100 = MPC-Oracle). Writes ``docs/offline/table.md``, ``table.json`` and ``table.png`` (the first table as bars).

Training seeds: where ``docs/offline/seeds.json`` (``benchmarks/offline_seeds.py``) holds two or
more seeds of a cell's config, a second table gives their mean +- std over training seeds (each
seed's profit is its 10-episode mean on the report seeds) beside the mean per-seed evaluation std.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from marl_amod.datasets import normalised_score
from marl_amod.errors import ConfigError
from marl_amod.metrics import SCORE_ANCHORS, score_points

ROOT = Path(__file__).resolve().parent.parent
DATASETS = ["inf", "dtv", "prop", "mpc_forecast", "prop_noise"]
ALGOS = ["bc", "iql", "cql"]
ONLINE = "sac_gnn_{city}_fast"
ACTORS = ("gnn", "mlp")  # the centralised actors an offline cell may ship (its file name says which)


def cell_name(policies: Path, algo: str, city: str, ds: str) -> str | None:
    """The file stem of the offline policy of one cell (``bc_mlp_nyc_brooklyn_dtv``), None if none is shipped."""
    names = [f"{algo}_{actor}_{city}_{ds}" for actor in ACTORS if (policies / f"{algo}_{actor}_{city}_{ds}.json").is_file()]
    if len(names) > 1:
        raise ConfigError(f"two policies for one table cell: {', '.join(names)} in {policies}; keep one")
    return names[0] if names else None


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


def over_seeds(cell: dict | None, behaviour: float, refs: dict) -> dict | None:
    """Mean +- std over the training seeds of one cell (None under two seeds)."""
    if not cell or len(cell["seeds"]) < 2:
        return None
    profits = np.array([r["profit_mean"] for r in cell["seeds"].values()])
    mean = float(profits.mean())
    return {"n": len(profits), "mean": mean, "std": float(profits.std(ddof=1)), "eval_std": float(np.mean([r["profit_std"] for r in cell["seeds"].values()])),
            "min": float(profits.min()), "normalised": normalised_score(mean, refs), "vs_behaviour_pct": 100.0 * (mean / behaviour - 1.0),
            "per_seed": {k: r["profit_mean"] for k, r in sorted(cell["seeds"].items())}}  # fmt: skip


def build(city: str, cards: Path, policies: Path, evaluate: bool, seeds: dict | None = None) -> dict:
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
            name = cell_name(policies, algo, city, ds)
            s = score(policies / f"{name}.json", evaluate) if name else None
            if s is not None:
                row[algo] = {"policy": f"policies/{name}.pt", "mean": s["mean"], "std": s["std"], "normalised": normalised_score(s["mean"], refs),
                             "vs_behaviour_pct": 100.0 * (s["mean"] / beh["mean"] - 1.0),
                             "training_wall_s": s["card"].get("training_wall_s"), "updates": s["card"].get("updates")}
                seeded = over_seeds((seeds or {}).get(name), beh["mean"], refs)
                if seeded:
                    row[algo]["seeds"] = seeded
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


def seeds_markdown(table: dict) -> str:
    """The second table: mean +- std over training seeds, [mean per-seed evaluation std], n seeds."""
    lines = [
        "Over training seeds (`benchmarks/offline_seeds.py`, `seeds.json`): profit mean ± std over n training seeds of each "
        "seed's 10-episode mean on the same report seeds; in square brackets the mean per-seed evaluation std.",
        "",
        "| Dataset | Beh. pol. | BC | IQL | CQL | BC vs beh. | best of IQL/CQL vs beh. |",
        "|---|---|---|---|---|---|---|",
    ]
    for r in table["rows"]:
        seeded = {a: r[a]["seeds"] for a in ALGOS if a in r and "seeds" in r[a]}
        if not seeded:
            continue
        text = lambda s: f"{s['mean'] / 1000:.1f}k ±{s['std'] / 1000:.1f} [±{s['eval_std'] / 1000:.1f}] (n={s['n']})" if s else "-"  # noqa: E731
        rl = max([a for a in ("iql", "cql") if a in seeded], key=lambda a: seeded[a]["mean"], default=None)
        bc = f"{seeded['bc']['vs_behaviour_pct']:+.1f}%" if "bc" in seeded else "-"
        gain = f"{seeded[rl]['vs_behaviour_pct']:+.1f}% ({rl.upper()})" if rl else "-"
        lines.append(f"| {r['dataset'].upper().replace('_', '-')} | {r['behaviour']['mean'] / 1000:.1f}k | "
                     + " | ".join(text(seeded.get(a)) for a in ALGOS) + f" | {bc} | {gain} |")  # fmt: skip
    return "\n".join(lines) + "\n" if len(lines) > 4 else ""


def groups(table: dict) -> dict[str, list[tuple[str, float, float]]]:
    """The first table's cells for :func:`marl_amod.plots.score_bars`: per dataset, the behaviour
    policy and BC / IQL / CQL in normalised score with the episode std in score points; SAC
    online, which reads no dataset, is left out."""
    ed, oracle = (table["reference_scores"][name]["mean"] for name in SCORE_ANCHORS)
    return {
        r["dataset"].upper().replace("_", "-"): [
            (name, r[key]["normalised"], score_points(r[key]["std"], ed, oracle))
            for key, name in (("behaviour", "behaviour policy"), *((a, a.upper()) for a in ALGOS))
            if key in r
        ]
        for r in table["rows"]
    }


def figure(table: dict, path: Path) -> Path:
    """The first table as bars (:func:`groups`)."""
    from marl_amod.plots import score_bars

    return score_bars(groups(table), path, f"Offline RL on {table['scenario']}: normalised score over 10 episodes")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="nyc_brooklyn")
    ap.add_argument("--cards", type=Path, default=ROOT / "docs/offline/datasets", help="folder of dataset cards")
    ap.add_argument("--policies", type=Path, default=ROOT / "policies")
    ap.add_argument("--seeds", type=Path, default=ROOT / "docs/offline/seeds.json", help="training seeds (benchmarks/offline_seeds.py)")
    ap.add_argument("--out", type=Path, default=ROOT / "docs/offline")
    ap.add_argument("--evaluate", action="store_true", help="re-evaluate every policy instead of reading its card")
    args = ap.parse_args()
    seeds = json.loads(args.seeds.read_text()) if args.seeds.is_file() else None
    table = build(args.scenario, args.cards, args.policies, args.evaluate, seeds)
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "table.json").write_text(json.dumps(table, indent=2) + "\n")
    md = markdown(table)
    extra = seeds_markdown(table)
    md += f"\n{extra}" if extra else ""
    (args.out / "table.md").write_text(md)
    print(md)
    drawn = figure(table, args.out / "table.png")
    print(f"wrote {args.out / 'table.md'}, {args.out / 'table.json'} and {drawn}")


if __name__ == "__main__":
    main()
