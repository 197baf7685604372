"""The results tables of README.md and docs/results.md, generated from committed JSON.

    python benchmarks/results_tables.py                 # rewrite the tables (and docs/results/<table>.png) from docs/results/*.json
    python benchmarks/results_tables.py --check         # exit 1 if a committed table is stale
    python benchmarks/results_tables.py --add eval.json # merge `marl-amod evaluate --output` records

Numbers are never copied into markdown by hand: each ``docs/results/<table>.json`` holds one city's
results in the evaluation JSON schema (``policy``, ``metrics: {name: {mean, std}}``, plus ``kind``,
``label``, ``training``, ``ms_per_step`` where known), and the markdown between marker comments

    <!-- results:full nyc_brooklyn -->  ...  <!-- /results -->      (docs/results.md: every column)
    <!-- results:summary nyc_brooklyn -->  ...  <!-- /results -->   (README.md: profit and score)

is rewritten from it. The normalised score puts equal distribution at 0 and MPC-Oracle at 100
(D4RL style): 100 * (profit - ED) / (MPC-Oracle - ED). Each table with both anchors is also drawn,
its policies ranked by that score (``docs/results/<table>.png``, shown in docs/results.md).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from pathlib import Path
from typing import Any

from marl_amod.metrics import normalised_score, score_anchors, score_points

ROOT = Path(__file__).resolve().parent.parent
RESULTS = ROOT / "docs" / "results"
DOCUMENTS = (ROOT / "README.md", ROOT / "docs" / "results.md")
BLOCK = re.compile(r"(<!-- results:(full|summary) (\w+) -->\n)(.*?)(<!-- /results -->)", re.DOTALL)


def load(folder: Path = RESULTS) -> dict[str, dict[str, Any]]:
    """Every results file by table name (the file stem)."""
    return {p.stem: json.loads(p.read_text()) for p in sorted(folder.glob("*.json"))}


def anchors(table: dict[str, Any]) -> tuple[float, float] | None:
    """The table's (equal distribution, MPC-Oracle) mean profits; None without both, or where they coincide."""
    pair = score_anchors({r["policy"]: r["metrics"]["profit"]["mean"] for r in table["results"]})
    return pair if pair is not None and pair[0] != pair[1] else None


def score(profit: float, table: dict[str, Any]) -> float | None:
    """Normalised score: equal distribution 0, MPC-Oracle 100; None without both anchors."""
    pair = anchors(table)
    return None if pair is None else normalised_score(profit, *pair)


def _mean_std(metric: dict[str, float] | None, digits: int = 0, percent: bool = False) -> str:
    if metric is None:
        return "–"
    scale, suffix = (100.0, "%") if percent else (1.0, "")
    text = f"{scale * metric['mean']:,.{digits}f}{suffix}"
    if "std" in metric:
        text += f" ± {scale * metric['std']:,.{digits}f}{suffix}"
    return text


def _policy(r: dict[str, Any], full: bool) -> str:
    if r.get("kind") != "trained":
        return r["policy"]
    mode = f", {r['mode']}" if full and r.get("mode") else ""
    return f"`{r['policy']}`: {r['label']}{mode}" if r.get("label") else f"`{r['policy']}`"


def table_markdown(table: dict[str, Any], full: bool) -> str:
    """One city's table; columns nobody reported (and waits that are zero in every row) are left out; the best mean profit in bold."""
    rows = table["results"]
    best = max(r["metrics"]["profit"]["mean"] for r in rows)
    columns: list[tuple[str, str, Any]] = [
        ("policy", "---", lambda r: _policy(r, full)),
        ("profit (mean ± std)", "---:", lambda r: _mean_std(r["metrics"]["profit"])),
        ("score (ED 0, MPC-Oracle 100)", "---:", lambda r: "–" if (s := score(r["metrics"]["profit"]["mean"], table)) is None else f"{s:.0f}"),
    ]
    if full:
        has = lambda key: any(key in r["metrics"] for r in rows)  # noqa: E731
        if has("served_demand"):
            columns.append(("served" + (" / demand" if has("demand") else ""), "---:", lambda r: _served(r["metrics"])))
        if has("rebalancing_cost"):
            columns.append(("rebalancing cost", "---:", lambda r: _mean_std(r["metrics"].get("rebalancing_cost"))))
        if any(r["metrics"].get("wait_time", {}).get("mean") for r in rows):  # zero everywhere: the model has no waiting
            columns.append(("wait (min)", "---:", lambda r: _mean_std(r["metrics"].get("wait_time"), 2)))
        if has("utilization"):
            columns.append(("utilisation", "---:", lambda r: _mean_std(r["metrics"].get("utilization"), percent=True)))
        if any("ms_per_step" in r for r in rows):
            columns.append(("ms / step", "---:", lambda r: f"{r['ms_per_step']:.1f}" if "ms_per_step" in r else "–"))
        if any("training" in r for r in rows):
            columns.append(("training", "---:", lambda r: r.get("training", "")))
    lines = ["| " + " | ".join(c[0] for c in columns) + " |", "|" + "|".join(c[1] for c in columns) + "|"]
    for r in rows:
        cells = [c[2](r) for c in columns]
        if r["metrics"]["profit"]["mean"] == best:
            cells[1] = f"**{cells[1]}**"
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def figure(name: str, table: dict[str, Any], folder: Path = RESULTS) -> Path | None:
    """``<folder>/<name>.png``: the table's policies ranked by normalised score (None without both
    anchors). Written with the tables, not checked by ``--check`` (image bytes vary with matplotlib)."""
    from marl_amod.plots import score_ranking

    pair = anchors(table)
    if pair is None:
        return None
    rows = [(r["policy"], score(r["metrics"]["profit"]["mean"], table), score_points(r["metrics"]["profit"].get("std", 0.0), *pair),
             r.get("kind") or "baseline") for r in table["results"]]  # fmt: skip
    episodes = f", {table['episodes']} episodes" if table.get("episodes") else ""
    return score_ranking(rows, folder / f"{name}.png", f"{table.get('title', name)}{episodes}")


def _served(metrics: dict[str, Any]) -> str:
    served = _mean_std({"mean": metrics["served_demand"]["mean"]}) if "served_demand" in metrics else "–"
    return f"{served} / {metrics['demand']['mean']:,.0f}" if "demand" in metrics else served


def render(text: str, tables: dict[str, dict[str, Any]]) -> str:
    """``text`` with every marker block rewritten from ``tables``; an unknown table is an error."""

    def fill(match: re.Match[str]) -> str:
        kind, name = match.group(2), match.group(3)
        if name not in tables:
            raise KeyError(f"results block names {name!r}, but there is no docs/results/{name}.json")
        return match.group(1) + table_markdown(tables[name], full=kind == "full") + match.group(5)

    return BLOCK.sub(fill, text)


def merge(records: list[dict[str, Any]], name: str, folder: Path = RESULTS) -> Path:
    """Put evaluation records into ``<folder>/<name>.json``, replacing a policy's old entry but
    keeping what only a person can say about it (label, kind, training, config)."""
    path = folder / f"{name}.json"
    doc = json.loads(path.read_text()) if path.is_file() else {"table": name, "scenario": name, "title": name, "results": []}
    by_policy = {r["policy"]: r for r in doc["results"]}
    for rec in records:
        policy = Path(rec["policy"]).stem if rec["policy"].endswith(".pt") else rec["policy"]
        keep = {k: v for k, v in by_policy.get(policy, {}).items() if k in ("kind", "label", "mode", "training", "checkpoint", "config")}
        entry = {**keep, "policy": policy, "scenario": rec["scenario"], "episodes": rec["episodes"], "seed": rec["seed"],
                 "metrics": rec["metrics"], **{k: rec[k] for k in ("kind", "ms_per_step", "max_wait") if k in rec}}  # fmt: skip
        if policy in by_policy:
            doc["results"][doc["results"].index(by_policy[policy])] = entry
        else:
            doc["results"].append(entry)
        by_policy[policy] = entry
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(doc, indent=2, ensure_ascii=False) + "\n")
    return path


def add(records_file: Path, folder: Path = RESULTS, table: str | None = None) -> str:
    """Merge the output of ``marl-amod evaluate --output`` (one record, or ``{"results": [...]}``);
    the table defaults to the scenario's name."""
    payload = json.loads(records_file.read_text())
    records = payload["results"] if "results" in payload else [payload]
    name = table or records[0]["scenario"]
    merge(records, name, folder)
    return name


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--check", action="store_true", help="only report whether the committed tables are current")
    parser.add_argument("--add", type=Path, nargs="*", default=[], help="evaluate JSON files to merge first")
    parser.add_argument("--table", default=None, help="results file for --add (default: the scenario name)")
    args = parser.parse_args(argv)
    for records in args.add:
        print(f"merged {records} into docs/results/{add(records, table=args.table)}.json")
    tables = load()
    stale = []
    for doc in DOCUMENTS:
        text = doc.read_text()
        new = render(text, tables)
        if new != text:
            stale.append(doc.name)
            if not args.check:
                doc.write_text(new)
    if not args.check:
        drawn = [path.name for name, table in tables.items() if "results" in table and (path := figure(name, table))]
        print(f"figures: {', '.join(drawn)}")
    if args.check and stale:
        print(f"stale results tables in {', '.join(stale)}: run python benchmarks/results_tables.py", file=sys.stderr)
        return 1
    print("results tables " + ("are current" if not stale else f"rewritten in {', '.join(stale)}"))
    return 0


if __name__ == "__main__":
    sys.exit(main())
