"""The trained policies of a folder as one table: what each file is, where it trained, what it scored.

``policies/`` holds one checkpoint (``.pt``) per trained policy with its card (``.json``, ``.md``),
ensemble files (``.yaml``) of several, and in ``policies/seeds/`` the training seeds the meta-policy's
record compares. Every fact is on a card; this module gathers the cards so a user can pick a policy
without opening sixty files, and ``marl-amod policies --markdown policies/README.md`` keeps the
folder's index current (a test checks that it is).

Scores are normalised (equal distribution 0, MPC-Oracle 100) only where the results tables hold both
anchors for the very episodes the card was scored on (same scenario, episode count and seed); a card
scored on validation episodes, or on a scenario with no table, shows its profit alone.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from marl_amod.checkpoints import read_card
from marl_amod.ensemble import ENSEMBLE_SUFFIXES, read_spec
from marl_amod.errors import ConfigError, MarlAmodError
from marl_amod.metrics import normalised_score, score_anchors

SEEDS = "seeds"  # the sub-folder of training-seed members


@dataclass(frozen=True)
class Entry:
    """One checkpoint of the folder, as its card describes it."""

    path: Path
    card: dict[str, Any]

    @property
    def name(self) -> str:
        return self.path.stem

    @property
    def trained_in(self) -> str:
        """The scenario it trained in; a meta-policy's training cities instead of the city its card scored it on."""
        if self.is_meta:
            from marl_amod.transfer import meta_used

            return meta_used([self.card])["source_city"]
        return str(self.card["scenario"])

    @property
    def is_meta(self) -> bool:
        return "demonstrations" in self.card or "warm_start" in self.card

    @property
    def on_validation(self) -> bool:
        """Scored on validation episodes (the meta record's members), not on the tables' report episodes."""
        return self.card.get("eval_streams") == "validation"


def trained_on(card: dict[str, Any]) -> str:
    """What a policy card says it was trained on and how long: a meta-imitation counts every
    demonstration (the cities' and each variant kind's) and its DAgger episodes, and names the
    demonstrations' collection time, which its training time leaves out."""
    minutes = f"in {card['training_wall_s'] / 60:.1f} min"
    if "dataset" in card:
        return f"{card['updates']:,} updates on {card['dataset']['transitions']:,} logged transitions {minutes}"
    if "demonstrations" in card:
        from marl_amod.transfer import meta_used

        used, demos = meta_used([card]), card["demonstrations"]
        dagger = f" and {used['dagger_episodes']:,} DAgger episodes" if used.get("dagger_episodes") else ""
        collected = f" (+ {demos['collection_wall_s'] / 60:.1f} min collecting the demonstrations)" if demos.get("collection_wall_s") else ""
        return f"{card['updates']:,} updates on {used.get('demonstrations', 0):,} MPC-Forecast demonstration episodes{dagger} {minutes}{collected}"
    if "iterations" in card:  # RLlib counts iterations and env steps, not episodes
        return f"{card['iterations']} iterations ({card.get('env_steps', 0):,} env steps) {minutes}"
    return f"{card['episodes_trained']:,} episodes {minutes}"


def read_entries(folder: str | Path, *, seeds: bool = False, unreadable: list[tuple[Path, str]] | None = None) -> list[Entry]:
    """Every checkpoint of ``folder`` (and of its ``seeds/`` with ``seeds``), by name, cards checked against their files.

    A file that is not a readable policy with its card raises, unless ``unreadable`` is given: then it
    is left out and noted there as (path, why), so one damaged file does not hide the rest of a listing."""
    folder = Path(folder)
    if folder.is_file():
        raise ConfigError(f"{folder} is a file; give the policy folder that holds it (marl-amod policies {folder.parent})")
    if not folder.is_dir():
        raise ConfigError(f"policy folder {folder} not found")
    paths = sorted(folder.glob("*.pt")) + (sorted((folder / SEEDS).glob("*.pt")) if seeds else [])
    entries = []
    for p in paths:
        try:
            entries.append(Entry(p, read_card(p)))
        except MarlAmodError as exc:
            if unreadable is None:
                raise
            unreadable.append((p, str(exc)))
    return entries


def read_ensembles(folder: str | Path) -> dict[Path, list[str]]:
    """Each ensemble file of ``folder`` and its members (as the file names them, relative to it)."""
    files = sorted(p for p in Path(folder).iterdir() if p.suffix in ENSEMBLE_SUFFIXES)
    return {p: read_spec(p).members for p in files}


def read_anchors(results: str | Path) -> dict[tuple[str, int, int], tuple[float, float]]:
    """(scenario, episodes, seed) -> (equal distribution's, MPC-Oracle's) mean profit, from the results
    tables (``docs/results/*.json``) that hold both; nothing when the folder is not there."""
    anchors: dict[tuple[str, int, int], tuple[float, float]] = {}
    for path in sorted(Path(results).glob("*.json")) if Path(results).is_dir() else []:
        table = json.loads(path.read_text())
        rows = table.get("results", []) if isinstance(table, dict) else []
        profit = {r["policy"]: r["metrics"]["profit"]["mean"] for r in rows if "metrics" in r}
        pair = score_anchors(profit)
        if pair is not None and table.get("episodes") is not None:
            anchors.setdefault((table["scenario"], int(table["episodes"]), int(table["seed"])), pair)
    return anchors


def score(entry: Entry, anchors: dict[tuple[str, int, int], tuple[float, float]]) -> float | None:
    """The card's profit normalised against the anchors of its own evaluation episodes, or None."""
    card = entry.card
    key = (str(card["scenario"]), int(card["eval_episodes"]), int(card["eval_seed"]))
    if entry.on_validation or key not in anchors:
        return None
    return normalised_score(card["profit_mean"], *anchors[key])


def architecture(card: dict[str, Any]) -> str:
    """The actor in a few words (a recurrent meta-policy names its message passing too)."""
    from marl_amod.comparison import architecture as single

    if card.get("actor") == "recurrent":
        return f"recurrent GNN, {card.get('conv', 'sage')}, {card.get('hidden')} units"
    return f"{single(card)}, {card.get('hidden')} units"


def profit_cell(entry: Entry) -> str:
    card = entry.card
    streams = "validation" if entry.on_validation else f"seed {card['eval_seed']}"
    return f"{card['profit_mean']:,.0f} ± {card['profit_std']:,.0f} ({card['scenario']}, {card['eval_episodes']} ep., {streams})"


def cells(entry: Entry, anchors: dict[tuple[str, int, int], tuple[float, float]]) -> dict[str, str]:
    """The entry's row, by column name (:data:`COLUMNS`)."""
    card, value = entry.card, score(entry, anchors)
    return {
        "policy": f"`{entry.name}`",
        "trained in": entry.trained_in,
        "algorithm": f"{card['algorithm']}, {card['mode']}",
        "actor": architecture(card),
        "training": trained_on(card),
        "profit (scored on)": profit_cell(entry),
        "score": "" if value is None else f"{value + 0.0:.0f}",  # + 0.0: no "-0"
        "config": f"`{card['config']}`",
    }


COLUMNS = ("policy", "trained in", "algorithm", "actor", "training", "profit (scored on)", "score", "config")


def _table(rows: list[dict[str, str]], columns: tuple[str, ...]) -> list[str]:
    lines = ["| " + " | ".join(columns) + " |", "|" + "---|" * len(columns)]
    return lines + ["| " + " | ".join(r[c] for c in columns) + " |" for r in rows]


def _place_order(place: str, entries: list[Entry]) -> tuple[bool, bool, str]:
    """The default city first, then the single cities, then the meta-policies' training sets."""
    return (entries[0].is_meta, place != "synthetic", place)


def markdown(folder: str | Path, results: str | Path) -> str:
    """The folder's index: every policy with its card's facts, the ensembles, then the training seeds."""
    folder = Path(folder)
    anchors = read_anchors(results)
    entries, ensembles = read_entries(folder), read_ensembles(folder)
    lines = [
        f"# Trained policies ({len(entries)} checkpoints, {len(ensembles)} ensembles)",
        "",
        "<!-- generated by `marl-amod policies --markdown policies/README.md`; do not edit by hand -->",
        "",
        "Each checkpoint has its card beside it (`<name>.json`, and `<name>.md` with the command that trains it",
        "and the one that scores it). Load one with `marl_amod.load_policy(\"policies/<name>.pt\")` (for its card's city,",
        "or give another), or score it with `marl-amod evaluate --scenario <scenario> --policy policies/<name>.pt`.",
        "Score: the card's profit normalised as in the results tables (equal distribution 0, MPC-Oracle 100), shown",
        "where the tables in `docs/results/` score both anchors on the card's own episodes; the meta-policies'",
        "tables are in [docs/meta](../docs/meta/README.md), the offline ones in [docs/offline](../docs/offline/index.md).",
        "",
    ]
    by_place: dict[str, list[Entry]] = {}
    for e in entries:
        by_place.setdefault(e.trained_in, []).append(e)
    grouped = tuple(c for c in COLUMNS if c != "trained in")  # the section's heading says it
    for place in sorted(by_place, key=lambda p: _place_order(p, by_place[p])):
        lines += [f"## {place}", "", *_table([cells(e, anchors) for e in by_place[place]], grouped), ""]
    if ensembles:
        lines += ["## Ensembles", "", "The mean of their members' desired distributions (`marl_amod.ensemble`); each has its card (`.md`).", ""]
        lines += ["| ensemble | members |", "|---|---|"]
        lines += [f"| `{p.name}` | {', '.join(f'`{m}`' for m in members)} |" for p, members in ensembles.items()]
        lines.append("")
    seeds = read_entries(folder / SEEDS) if (folder / SEEDS).is_dir() else []  # the top level's cards are read once, above
    if seeds:
        lines += [
            f"## Training seeds ({SEEDS}/)",
            "",
            "Members of the meta-policy's record (docs/meta/log.md): its recipes trained from several seeds, each card scored",
            "on validation episodes (seed 1000), not the tables' report episodes; the tables' meta-policy is an ensemble of two.",
            "",
            *_table([cells(e, anchors) for e in seeds], COLUMNS),
            "",
        ]
    return "\n".join(lines)
