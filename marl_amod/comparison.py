"""``marl-amod compare``: trained policies against baselines and ablations on the same seeds.

A compare config (configs/compare/<city>.yaml) names the scenario, the evaluation seeds, the
baselines, and the learned runs. Each run either points at an existing policy file or is trained
from its algorithm Args (with the same budget as its siblings). Everything is then evaluated on
the same demand streams and written as a markdown table, a JSON file and three plots.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from marl_amod.config import problems, read_config
from marl_amod.errors import ConfigError
from marl_amod.files import atomic_write, write_json


class RunSpec(BaseModel):
    """One learned policy in the comparison: a training config (plus overrides) or an algorithm and its args."""

    model_config = ConfigDict(extra="forbid")
    label: str = Field(description="row name in the table and plots")
    config: str | None = Field(None, description="a training config, relative to this file; args override its args")
    algo: str | None = Field(None, description="a name in marl_amod.algos.registry.ALGOS (default: the config's)")
    args: dict[str, Any] = Field(default_factory=dict, description="the algorithm's Args (checked strictly)")
    retrain: bool = Field(False, description="train even if args.policy_out already exists")


class CompareConfig(BaseModel):
    """configs/compare/<city>.yaml."""

    model_config = ConfigDict(extra="forbid")
    scenario: str
    episodes: int = Field(10, ge=1, description="evaluation episodes per policy (demand streams (seed, k))")
    seed: int = 0
    baselines: list[str] = Field(default_factory=lambda: ["equal-distribution", "plus-one", "no-rebalancing"], min_length=1,
                                 description="at least one: every row's gap is to the best of them")  # fmt: skip
    runs: list[RunSpec] = Field(default_factory=list)
    output: str = Field("results/compare", description="folder for compare.md, compare.json and plots")


def _resolve_run(path: Path, run: RunSpec) -> RunSpec:
    """The run with its training config (if any) folded in: algo set, args complete."""
    if run.config is None:
        if run.algo is None:
            raise ConfigError(f"{path} run {run.label!r}: give a training config or an algo")
        return run
    base = read_config(path.parent / run.config)
    algo = run.algo or base.get("algo")
    if base.get("algo") != algo:
        raise ConfigError(f"{path} run {run.label!r}: algo {run.algo} differs from {run.config}'s {base.get('algo')}")
    return run.model_copy(update={"algo": algo, "args": {**(base.get("args") or {}), **run.args}})


def load_compare_config(path: str | Path) -> CompareConfig:
    from marl_amod.algos.common import check_separate_outputs
    from marl_amod.algos.registry import args_for

    path = Path(path)
    raw = read_config(path)
    try:
        cfg = CompareConfig.model_validate(raw)
    except ValidationError as exc:
        raise problems(str(path), exc) from None
    cfg.runs = [_resolve_run(path, run) for run in cfg.runs]
    validated = []
    for run in cfg.runs:  # fail on a typo or a scenario mismatch before any training starts
        if run.args.get("scenario", cfg.scenario) != cfg.scenario:
            raise ConfigError(f"{path} run {run.label!r}: args.scenario: {run.args['scenario']} is not the comparison's {cfg.scenario}")
        args = args_for(run.algo, {**run.args, "scenario": cfg.scenario}, f"{path} run {run.label!r}")
        if not args.policy_out:
            raise ConfigError(f"{path} run {run.label!r}: args.policy_out is required (where the trained policy lives)")
        validated.append((f"{path} run {run.label!r}", args))
    check_separate_outputs(validated)  # two runs writing one policy would show one policy twice
    return cfg


Tracker = Callable[[str], Callable[[int, int], None]]
"""Starts a progress line for a description; the returned callback takes (done, total)."""


def _no_tracker(_description: str) -> Callable[[int, int], None]:
    return lambda _done, _total: None


def missing_runs(cfg: CompareConfig) -> list[tuple[RunSpec, Any]]:
    """The runs ``compare`` would train (their policy file is missing, or ``retrain`` is set), with their args."""
    from marl_amod.algos.registry import args_for

    planned = []
    for run in cfg.runs:
        args = args_for(run.algo, {**run.args, "scenario": cfg.scenario})
        if run.retrain or not Path(args.policy_out).is_file():
            planned.append((run, args))
    return planned


def run_compare(
    cfg: CompareConfig,
    log: Callable[[str], None] = print,
    config_path: str | None = None,
    *,
    train: bool = True,
    tracker: Tracker = _no_tracker,
) -> dict[str, Any]:
    """Train what is missing (or skip it when ``train`` is False), evaluate everything on the same seeds, write table + plots.

    What will be trained is said before anything runs, since one missing policy can cost many minutes.
    """
    from marl_amod.algos.registry import args_for, run_training
    from marl_amod.checkpoints import read_card
    from marl_amod.evaluation import evaluate
    from marl_amod.files import check_folder
    from marl_amod.scenario import load_city

    out = check_folder(cfg.output, what=f"{config_path or 'compare'}: output")  # before any training, not after it
    planned = missing_runs(cfg)
    skipped = {run.label for run, _ in planned} if not train else set()
    for run, args in planned:
        why = "retrain: true" if run.retrain else f"{args.policy_out} not found" + (
            f" (from {Path.cwd()}: a config's policy_out and run_dir are relative to the working folder)" if not Path(args.policy_out).is_absolute() else "")
        if train:
            log(f"will train {run.label!r} ({run.algo}, {args.mode}, {_budget(args)}): {why}")
        else:
            log(f"skipping {run.label!r}: {why} (--no-train)")
    if planned and train:
        log("to skip training and compare only the policies that exist: --no-train")
    city = load_city(cfg.scenario)
    rows: list[dict[str, Any]] = []
    for name in cfg.baselines:
        done = tracker(f"evaluating {name}")
        rows.append({"label": name, "kind": "baseline",
                     "result": evaluate(name, city, cfg.episodes, cfg.seed, progress=lambda k, done=done: done(k + 1, cfg.episodes))})
    to_train = {run.label for run, _ in planned} - skipped
    for run in cfg.runs:
        if run.label in skipped:
            continue
        args = args_for(run.algo, {**run.args, "scenario": cfg.scenario})
        if run.label in to_train:
            done = tracker(f"training {run.label} ({run.algo}, {args.mode})")
            run_training(run.algo, args, config_path=config_path, progress=lambda ep, total, _stats, done=done: done(ep, total))
        card = read_card(args.policy_out)
        done = tracker(f"evaluating {run.label}")
        result = evaluate(args.policy_out, city, cfg.episodes, cfg.seed, progress=lambda k, done=done: done(k + 1, cfg.episodes))
        rows.append({"label": run.label, "kind": "learned", "result": result, "card": card, "run_dir": args.run_dir})

    best = max((r for r in rows if r["kind"] == "baseline"), key=lambda r: r["result"]["metrics"]["profit"]["mean"], default=None)
    best_profit = best["result"]["metrics"]["profit"]["mean"] if best else float("nan")
    for r in rows:
        r["gap_to_best_baseline"] = r["result"]["metrics"]["profit"]["mean"] / best_profit - 1.0
    payload = {
        "scenario": city.name, "episodes": cfg.episodes, "seed": cfg.seed,
        "best_baseline": best["label"] if best else None,
        "rows": [{k: v for k, v in r.items() if k != "result"} | {"metrics": r["result"]["metrics"],
                  "per_region": r["result"]["per_region"]} for r in rows],
    }
    write_json(out / "compare.json", payload)
    atomic_write(out / "compare.md", markdown_table(rows, city.name, cfg.episodes, cfg.seed, best["label"] if best else "-"))
    plot_all(rows, out, city.name)
    log(f"wrote {out}/compare.md, compare.json, learning_curves.png, profit.png, served_by_region.png")
    return payload


def _budget(args: Any) -> str:
    """A run's training budget in words, from the fields its Args have."""
    keys = ("updates",) if hasattr(args, "updates") else ("episodes", "iterations")  # an offline run counts updates, not episodes
    parts = [f"{getattr(args, key)} {key}" for key in keys if hasattr(args, key)]
    if getattr(args, "time_limit_s", None):
        parts.append(f"at most {args.time_limit_s / 60:g} min")
    return ", ".join(parts) or "its configured budget"


def architecture(card: dict[str, Any]) -> str:
    """The actor as trained: the message passing is named only for GNN actors (an MLP or CNN has none)."""
    actor = card.get("actor", "?")
    if actor == "gnn":
        readout = f", {card['readout']} readout" if card.get("readout") else ""
        region_id = ", region id" if card.get("agent_id") else ""
        return f"GNN, {card.get('conv', 'gcn')}{readout}{region_id}"
    if actor == "local":
        return "local GNN layer, sage"  # LocalActor is a GNN actor with conv="sage" on local observations
    return actor.upper()


def markdown_table(rows: list[dict], scenario: str, episodes: int, seed: int, best: str) -> str:
    lines = [
        f"### {scenario}: {episodes} evaluation episodes (demand streams seed {seed}, k = 0..{episodes - 1})",
        "",
        f"| policy | algorithm / mode | profit (mean ± std) | served demand | rebalancing cost | gap to best baseline ({best}) | training wall time |",
        "|---|---|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        m = r["result"]["metrics"]
        card = r.get("card")
        algo = f"{card['algorithm'].upper()} / {card['mode']} ({architecture(card)})" if card else "baseline"
        wall = f"{card['training_wall_s'] / 60:.1f} min ({card['episodes_trained']} ep.)" if card else "-"
        lines.append(
            f"| {r['label']} | {algo} | {m['profit']['mean']:,.0f} ± {m['profit']['std']:,.0f} | {m['served_demand']['mean']:,.0f} "
            f"| {m['rebalancing_cost']['mean']:,.0f} | {100 * r['gap_to_best_baseline']:+.1f}% | {wall} |"
        )
    return "\n".join(lines) + "\n"


def plot_all(rows: list[dict], out: Path, scenario: str) -> None:
    """Learning curves, profit bars with std, per-region served demand (matplotlib Agg)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    for name, fig in (
        ("learning_curves.png", learning_curves_figure(rows, scenario)),
        ("profit.png", profit_figure(rows, scenario)),
        ("served_by_region.png", served_figure(rows, scenario)),
    ):
        fig.savefig(out / name, dpi=120, bbox_inches="tight")  # "tight" keeps the legends beside the axes
        plt.close(fig)


def _legend_beside(ax: Any) -> None:
    """Legend to the right of the axes, never over curves or bars."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)


def learning_curves_figure(rows: list[dict], scenario: str) -> Any:
    """Validation profit of each learned run; baselines as dashed lines named in the legend, not on the plot."""
    import matplotlib.pyplot as plt

    from marl_amod.algos.common import read_curve

    fig, ax = plt.subplots(figsize=(8, 4))
    baseline_styles = iter(["--", ":", "-.", (0, (5, 1)), (0, (1, 3))] * 4)
    no_log, offline = [], False
    for r in rows:
        if r["kind"] == "learned":
            xs, ys = read_curve(r["run_dir"], "eval/profit")
            if xs:
                by_updates = "updates" in r.get("card", {}) and not r["card"].get("episodes_trained")  # BC, IQL, CQL
                offline |= by_updates
                ax.plot(xs, ys, marker=".", label=r["label"] + (" (updates)" if by_updates else ""))
            else:
                no_log.append(r["label"])
        else:
            profit = r["result"]["metrics"]["profit"]["mean"]
            ax.axhline(profit, ls=next(baseline_styles), lw=1, color="grey", label=f"{r['label']} (baseline, report seeds)")
    xlabel = "training episodes" + (" (offline runs: updates)" if offline else "")
    if no_log:  # a policy trained elsewhere (or its run folder cleaned): said under the axis, not silently left out
        import textwrap

        xlabel += "\n" + "\n".join(textwrap.wrap("no training log (run_dir) for: " + ", ".join(no_log), 90))
    ax.set(xlabel=xlabel, ylabel="validation profit per episode", title=f"{scenario}: learning curves (validation seeds)")
    _legend_beside(ax)
    fig.tight_layout()
    return fig


def profit_figure(rows: list[dict], scenario: str) -> Any:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    means = [r["result"]["metrics"]["profit"]["mean"] for r in rows]
    stds = [r["result"]["metrics"]["profit"]["std"] for r in rows]
    colors = ["tab:grey" if r["kind"] == "baseline" else "tab:blue" for r in rows]
    ax.bar(range(len(rows)), means, yerr=stds, color=colors, capsize=4)
    ax.set_xticks(range(len(rows)), [r["label"] for r in rows], rotation=30, ha="right", fontsize=8)
    ax.set(ylabel="profit per episode (mean ± std)", title=f"{scenario}: profit")
    fig.tight_layout()
    return fig


def served_figure(rows: list[dict], scenario: str) -> Any:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4))
    n = len(rows[0]["result"]["per_region"]["served_demand"])
    width = 0.8 / len(rows)
    for k, r in enumerate(rows):
        ax.bar(np.arange(n) + k * width, r["result"]["per_region"]["served_demand"], width, label=r["label"])
    ax.set_xticks(np.arange(n) + 0.4 - width / 2, [str(i) for i in range(n)], fontsize=7)
    ax.set(xlabel="region", ylabel="served demand per episode", title=f"{scenario}: served demand by region")
    _legend_beside(ax)
    fig.tight_layout()
    return fig
