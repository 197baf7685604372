"""The ``marl-amod`` command line: every subcommand (``marl-amod --help`` lists them), built with typer."""

from __future__ import annotations

import os
import shutil
import time
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any

import typer
from rich.console import Console
from rich.markup import escape
from rich.progress import (
    BarColumn,
    MofNCompleteColumn,
    Progress,
    TextColumn,
    TimeElapsedColumn,
)
from rich.table import Table

from marl_amod.data import ENV_VAR
from marl_amod.errors import ConfigError, DataError, MarlAmodError
from marl_amod.files import atomic_write, check_destination, check_folder, save_or_fallback, write_json
from marl_amod.policies import policy_names

if TYPE_CHECKING:
    from marl_amod.baselines import Policy
    from marl_amod.scenario.types import City

app = typer.Typer(add_completion=False, no_args_is_help=True, help="Robo-taxi fleet coordination as a multi-agent RL benchmark.")
# wide enough for the metrics table when output is piped (rich would assume 80 columns)
console = Console(width=shutil.get_terminal_size((150, 24)).columns)

DataDir = Annotated[
    Path | None, typer.Option("--data-dir", help=f"data root (macro/, lux/); default: ${ENV_VAR}", show_default=False)
]


# the report's evaluation: episode k draws its demand from (seed, k), the same draws for every policy
Episodes = Annotated[int, typer.Option(min=1, help="evaluation episodes per policy")]
EvalSeed = Annotated[int, typer.Option(min=0, help="episode k draws demand from (seed, k); the results tables use 0")]
# a dataset's card scores its behaviour policy and the references on evaluation episodes
CardEpisodes = Annotated[int, typer.Option(min=0, help="card: evaluation episodes of the behaviour and reference scores (0: no card)")]
CardSeed = Annotated[int, typer.Option(min=0, help="card: evaluation seed (as marl-amod evaluate --seed)")]

PolicyOptions = Annotated[
    list[str] | None,
    typer.Option(
        "--policy-option",
        help="KEY=VALUE for the policy, e.g. demand_scale=1.2 or horizon=10 for mpc-forecast; repeat for more",
        show_default=False,
    ),
]


def parse_policy_options(items: list[str] | None, ctx: typer.Context | None = None) -> dict[str, object]:
    """``["demand_scale=1.2", "horizon=10"]`` -> ``{"demand_scale": 1.2, "horizon": 10}`` (see :func:`_option_value`).

    A key the command sets itself (``seed``, ``episodes``, ``max_wait``, ...) is refused with the
    flag of ``ctx``'s command to use: passed on, it would collide with the run's own argument."""
    import inspect

    from marl_amod.evaluation import SYSTEM_OPTIONS
    from marl_amod.evaluation import evaluate as run_eval

    flags = {opt for param in ctx.command.params for opt in getattr(param, "opts", ())} if ctx is not None else set()
    run_keys = {name for name, p in inspect.signature(run_eval).parameters.items() if p.kind is not p.VAR_KEYWORD}
    options: dict[str, object] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        key = key.strip()
        if not sep or not key.isidentifier():
            raise ConfigError(f"--policy-option takes KEY=VALUE, got {item!r}")
        if key in SYSTEM_OPTIONS or key in run_keys:
            flag = f"--{key.replace('_', '-')}"
            raise ConfigError(f"{key} is the run's, not the policy's" + (f": use {flag}" if flag in flags else ""))
        options[key] = _option_value(key, value)
    return options


def _option_value(key: str, value: str) -> object:
    """A number as Python writes it, else a YAML scalar: PyYAML reads YAML 1.1, where ``5e-2`` is
    a string (and then "not a finite number") and ``010`` is octal 8."""
    import yaml

    for number in (int, float):
        try:
            return number(value)
        except ValueError:
            pass
    try:
        return yaml.safe_load(value)
    except yaml.YAMLError as exc:
        first = str(exc).splitlines()[0]
        raise ConfigError(f"--policy-option {key}: {value!r} is not a YAML value ({first})") from None


def _use_data_dir(data_dir: Path | None) -> None:
    if data_dir is not None:
        os.environ[ENV_VAR] = str(data_dir)


class LoggedProgress(Progress):
    """A progress bar that, off a terminal (output sent to a log file, a background job, CI), also
    prints a plain line at every tenth of a task: there rich draws the bar only when it ends, so a
    half-hour collection would say nothing until it is done."""

    def __init__(self, *columns: Any, **kwargs: Any) -> None:
        super().__init__(*columns, **kwargs)
        self._tenths: dict[Any, int] = {}

    def update(self, task_id: Any, **kwargs: Any) -> None:  # type: ignore[override]
        super().update(task_id, **kwargs)
        self._log(task_id)

    def advance(self, task_id: Any, advance: float = 1) -> None:
        super().advance(task_id, advance)
        self._log(task_id)

    def _log(self, task_id: Any) -> None:
        if self.console.is_terminal:
            return
        task = self._tasks[task_id]
        tenth = int(10 * task.completed / task.total) if task.total else 0
        if 0 < tenth < 10 and tenth > self._tenths.get(task_id, 0):
            self._tenths[task_id] = tenth
            minutes = (task.elapsed or 0.0) / 60
            self.console.print(f"{task.description}: {task.completed:,.0f}/{task.total:,.0f} ({10 * tenth}%) in {minutes:.1f} min", markup=False)


def progress_bar() -> Progress:
    """The progress bar every long-running command shows (with a line a tenth when not on a terminal)."""
    return LoggedProgress(
        TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), console=console
    )


@app.command()
def scenarios(data_dir: DataDir = None) -> None:
    """List the bundled scenarios from their YAML files (no city is built)."""
    from importlib.util import find_spec

    from marl_amod.data import data_dir as data_root
    from marl_amod.scenario import catalogue

    _use_data_dir(data_dir)
    missing: dict[str, str] = {}
    try:
        root = data_root()
        if not any((root / sub).is_dir() for sub in ("macro", "lux")):  # the folder exists but is not the data folder
            missing["data"] = f"the data directory {root} holds neither macro/ nor lux/: point --data-dir (or MARL_AMOD_DATA) at the folder that does"
    except DataError as exc:
        missing["data"] = str(exc)
    if find_spec("sumo") is None:
        from marl_amod.sim.meso.engine import INSTALL_HINT

        missing["sumo"] = f"SUMO scenarios need the SUMO extra: {INSTALL_HINT}"
    table = Table(title="marl_amod scenarios")
    for col in ("name", "source", "regions", "fleet", "horizon", "step (min)", "needs", "description"):
        table.add_column(col, justify="right" if col in ("regions", "fleet", "horizon", "step (min)") else "left")
    broken = 0
    for info in catalogue():
        if info.error is not None:
            broken += 1
            table.add_row(escape(info.name), "[red]broken[/red]", "-", "-", "-", "-", "-", f"[red]{escape(info.error)}[/red]")
            continue
        needs = ", ".join(f"[yellow]{n}[/yellow]" if n in missing else n for n in info.needs) or "-"
        cells = ["-" if v is None else f"{v:g}" for v in (info.regions, info.fleet, info.horizon, info.tstep)]
        table.add_row(escape(info.name), info.source, *cells, needs, escape(info.description))  # a name may hold [brackets]
    console.print(table)
    for need, hint in missing.items():
        console.print(f"[yellow]{need}[/yellow]: {escape(hint)}")
    if broken:
        console.print(f"[red]{broken} scenario file(s) could not be read[/red]; the others are listed.")


@app.command("policies")
def policies_(
    folder: Annotated[Path, typer.Argument(help="the policy folder")] = Path("policies"),
    scenario: Annotated[list[str] | None, typer.Option(help="only policies trained in this scenario, or scored on it (a meta-policy: its card's city; repeat for more)", show_default=False)] = None,
    algorithm: Annotated[list[str] | None, typer.Option(help="only this algorithm, e.g. a2c, sac, iql, meta-bc (repeat for more)", show_default=False)] = None,
    seeds: Annotated[bool, typer.Option("--seeds", help="also the training-seed members in FOLDER/seeds/")] = False,
    results: Annotated[Path, typer.Option(help="results tables whose equal-distribution and MPC-Oracle rows normalise the scores")] = Path("docs/results"),
    markdown: Annotated[Path | None, typer.Option(help="write the folder's whole index here (e.g. policies/README.md) instead", show_default=False)] = None,
) -> None:
    """List the trained policies of a folder from their cards: where each trained, how, and what it scored."""
    from marl_amod import policy_catalogue as pc

    if markdown is not None:
        atomic_write(check_destination(markdown, what="policy index"), pc.markdown(folder, results) + "\n")
        console.print(f"wrote {markdown}")
        return
    unreadable: list[tuple[Path, str]] = []
    entries = pc.read_entries(folder, seeds=seeds, unreadable=unreadable)
    for path, why in unreadable:
        console.print(f"[yellow]left out {escape(str(path))}[/yellow]: {escape(why)}", soft_wrap=True)
    for asked, what, known in ((algorithm, "trained with", {e.card["algorithm"] for e in entries}),
                               (scenario, "trained in", {e.trained_in for e in entries} | {e.card["scenario"] for e in entries})):
        for name in asked or []:
            if name not in known:
                raise ConfigError(f"no policy in {folder} was {what} {name!r}; there are: {', '.join(sorted(known))}")
    shown = [e for e in entries if (not scenario or e.trained_in in scenario or e.card["scenario"] in scenario)
             and (not algorithm or e.card["algorithm"] in algorithm)]  # fmt: skip
    table = Table(title=f"policies in {folder} ({len(shown)} of {len(entries)})")
    for col in pc.COLUMNS:
        table.add_column(col, justify="right" if col == "score" else "left", no_wrap=col == "policy", overflow="fold")
    anchors = pc.read_anchors(results)
    for e in shown:
        table.add_row(*(escape(v.strip("`")) for v in pc.cells(e, anchors).values()))
    console.print(table)
    if not anchors:
        console.print(f"[yellow]no scores[/yellow]: {results} holds no results table with equal distribution and MPC-Oracle")


NO_WAIT_NOTE = (
    "wait min and wait Gini are 0 because requests do not wait at --max-wait 0 (the default): each is served in the step it "
    "appears or lost; give --max-wait N to let requests wait N steps"
)


def metrics_table(results: list[dict], title: str) -> Table:
    """Policies as rows, metrics as 'mean ± std' columns."""
    from marl_amod.metrics import DISPLAY_DIGITS, DISPLAY_NAMES, METRICS

    table = Table(title=title)
    table.add_column("policy", no_wrap=True)
    for key in METRICS:
        table.add_column(DISPLAY_NAMES.get(key, key), justify="right", no_wrap=True)
    for r in results:
        cells = []
        for key in METRICS:
            m = r["metrics"][key]
            digits = DISPLAY_DIGITS.get(key, 0)
            cells.append(f"{m['mean']:,.{digits}f} ± {m['std']:,.{digits}f}")
        table.add_row(r["policy"], *cells)
    return table


@app.command()
def evaluate(
    ctx: typer.Context,
    scenario: Annotated[str, typer.Option(help="scenario name or YAML path")] = "synthetic",
    policy: Annotated[
        list[str], typer.Option(help=f"{', '.join(policy_names())} or a checkpoint .pt; repeat to compare")
    ] = ["equal-distribution"],  # noqa: B006
    episodes: Episodes = 10,
    seed: EvalSeed = 0,
    output: Annotated[Path | None, typer.Option(help="write the results JSON here")] = None,
    max_wait: Annotated[int, typer.Option(min=0, help="steps a request waits before leaving")] = 0,
    objective: Annotated[str, typer.Option(help="dispatch objective: profit or revenue")] = "profit",
    solver: Annotated[str, typer.Option(help="fast (greedy + OR-Tools) or cvxpy")] = "fast",
    policy_option: PolicyOptions = None,
    data_dir: DataDir = None,
) -> None:
    """Run policies for whole episodes and print (and save) their metrics."""
    from marl_amod.evaluation import evaluate as run_eval
    from marl_amod.evaluation import results_payload
    from marl_amod.scenario import load_city

    _use_data_dir(data_dir)
    options = parse_policy_options(policy_option, ctx)
    if output is not None:
        output = check_destination(output, what="--output")  # before the run, not after it
    city = load_city(scenario)
    policies = _make_policies(policy, city, options)
    results = []
    with progress_bar() as bar:
        for name, pol in zip(policy, policies, strict=True):
            task = bar.add_task(f"{name} on {city.name}", total=episodes)
            results.append(
                run_eval(
                    pol, city, episodes, seed, max_wait=max_wait, objective=objective, solver=solver,
                    progress=lambda _k, task=task: bar.advance(task),
                )
            )
    console.print(metrics_table(results, f"{city.name}: {episodes} episodes, seed {seed}"))
    if max_wait == 0 and all(r["metrics"].get("wait_time", {}).get("mean", 0.0) == 0.0 for r in results):  # SUMO cities: waits anyway
        console.print(NO_WAIT_NOTE)
    if output is not None:
        payload = results_payload(results)
        save_or_fallback(output, lambda path: write_json(path, payload), what="the results")
        console.print(f"wrote {output}")


def _make_policies(names: list[str], city: City, options: dict[str, object]) -> list[Policy]:
    """Every ``--policy`` built before the first episode runs, so a typo in the last name (or a
    missing checkpoint) fails at once instead of after the others' evaluations."""
    from marl_amod.policies import make_policy

    return [make_policy(name, city, **options) for name in names]


@app.command()
def collect(
    ctx: typer.Context,
    scenario: Annotated[str, typer.Option(help="scenario name or YAML path")] = "synthetic",
    policy: Annotated[str, typer.Option(help="behaviour policy: inf, dtv, prop, mpc-forecast, ... or a checkpoint")] = "inf",
    episodes: Annotated[int, typer.Option(min=1, help="episodes to collect")] = 10,
    seed: Annotated[int, typer.Option(min=0, help="collection seed (demand streams disjoint from evaluation's)")] = 0,
    output: Annotated[Path, typer.Option(help="dataset file to write (.npz, format in marl_amod.datasets); card beside it")] = Path("data.npz"),
    max_wait: Annotated[int, typer.Option(min=0, help="steps a request waits before leaving")] = 0,
    eval_episodes: CardEpisodes = 10,
    eval_seed: CardSeed = 0,
    noise: Annotated[float, typer.Option(min=0, help="exploratory actions: Dirichlet around the policy's, concentration 1/noise")] = 0.0,
    lookahead: Annotated[int, typer.Option(min=1, help="look-ahead steps T of the logged features (train with the same)")] = 6,
    first_episode: Annotated[int, typer.Option(min=0, help="resume: start at the seed's episode k (merge-datasets joins the pieces)")] = 0,
    arrivals_now: Annotated[bool, typer.Option(help="log the node column of the vehicles arriving now (train with arrivals_now: true)")] = False,
    policy_option: PolicyOptions = None,
    data_dir: DataDir = None,
) -> None:
    """Roll a behaviour policy through the env and write an offline dataset (format 2) and its card."""
    _use_data_dir(data_dir)
    options = parse_policy_options(policy_option, ctx)
    _collect_one(
        scenario, policy, episodes, seed, output, max_wait, eval_episodes, eval_seed, {}, noise, lookahead, options, first_episode, arrivals_now
    )


@app.command()
def fqe(
    dataset: Annotated[Path, typer.Option(help="the offline dataset (.npz) to score the policies on")],
    policy: Annotated[list[str] | None, typer.Option(help="a policy file (.pt) to score (repeat); none: the logged behaviour only")] = None,
    scenario: Annotated[str | None, typer.Option(help="the dataset's city (a name or YAML path; default: its scenario by name)")] = None,
    updates: Annotated[int, typer.Option(min=1, help="critic regression steps per policy")] = 3000,
    seed: Annotated[int, typer.Option(min=0, help="seed of the critic's initialisation and minibatches")] = 0,
    output: Annotated[Path | None, typer.Option(help="also write the estimates as JSON")] = None,
    data_dir: DataDir = None,
) -> None:
    """Score policies from a dataset alone (fitted Q evaluation): each one's episode profit, estimated with no env episode, beside the logged behaviour's estimate and its logged return."""
    from marl_amod import fqe as F
    from marl_amod.checkpoints import read_card
    from marl_amod.datasets import OfflineDataset

    _use_data_dir(data_dir)
    if output is not None:
        output = check_destination(output, what="--output")  # before the fits, not after them
        if output.resolve() == dataset.with_suffix(".json").resolve():
            raise ConfigError(f"--output {output} is the dataset's own card; write the estimates elsewhere")
    for p in policy or []:  # every policy file read before the first fit, so a typo in the last does not wait for the others
        read_card(p)
    settings, loaded = F.FQESettings(updates=updates, seed=seed), OfflineDataset.load(dataset)
    logged = F.logged_returns(loaded)
    rows = {"logged behaviour": F.estimate(None, dataset, scenario, settings, loaded).to_dict() | {"logged_return": float(logged.mean())}}
    for p in policy or []:
        rows[p] = F.estimate(p, dataset, scenario, settings, loaded).to_dict()
    table = Table(title=f"FQE on {dataset} ({len(logged)} episodes; the decisions' profit, the first dispatch left out)")
    for col in ("policy", "FQE estimate", "logged return"):
        table.add_column(col, justify="left" if col == "policy" else "right")
    for name, r in rows.items():
        table.add_row(name, f"{r['profit']:,.0f}", f"{r['logged_return']:,.0f}" if "logged_return" in r else "-")
    console.print(table)
    behaviour = rows["logged behaviour"]
    if abs(behaviour["profit"] - behaviour["logged_return"]) > F.CONVERGED_WITHIN * abs(behaviour["logged_return"]):
        console.print(f"[yellow]warning:[/yellow] the logged behaviour's estimate is {behaviour['profit']:,.0f} against its logged return "
                      f"{behaviour['logged_return']:,.0f}: the fits have not converged; raise --updates (default 3000)")  # fmt: skip
    if output is not None:
        save_or_fallback(output, lambda path: write_json(path, {"dataset": str(dataset), "updates": updates, "seed": seed, "policies": rows}),
                         what="the estimates")  # fmt: skip
        console.print(f"wrote {output}")


@app.command()
def merge_datasets(
    pieces: Annotated[list[Path], typer.Argument(help="dataset pieces of one collection (collect outputs, cards beside them)")],
    output: Annotated[Path, typer.Option(help="merged dataset file (.npz); its card beside it")] = Path("data.npz"),
) -> None:
    """Join pieces of one collection (collected in parallel or across sessions) into one dataset and card.

    Refuses pieces of different collections (city, behaviour policy and its options, logging) or that hold an episode twice; pieces with different --seed, or one resumed with --first-episode where another stopped, never do.
    """  # one line per paragraph: --help prints a docstring's line breaks as they are
    from marl_amod.datasets import OfflineDataset, card_path, dataset_destination, merge, merge_cards

    output = dataset_destination(output)
    if output.resolve() in {p.resolve() for p in pieces}:
        raise ConfigError(f"--output {output} is one of the pieces: write the merged dataset to a new file")
    data = merge([OfflineDataset.load(p) for p in pieces], names=[str(p) for p in pieces])
    path = save_or_fallback(output, data.save, what="the dataset")
    card = merge_cards(path, data, pieces)
    held = ", ".join(f"seed {s} episodes {k}..{k + n - 1}" for s, k, n in data.meta["streams"])
    console.print(f"wrote {data.meta['episodes']} episodes, {len(data)} transitions ({held}) to {path}")
    console.print(f"card {card_path(path)}" if card else "no card (the pieces have none)")


@app.command()
def mix_datasets(
    parts: Annotated[list[Path], typer.Argument(help="datasets of one city logged by different behaviours (cards beside them)")],
    output: Annotated[Path, typer.Option(help="the mixture's dataset file (.npz); its card beside it")] = Path("data.npz"),
) -> None:
    """Join collections of different behaviours on one city into one dataset (D4RL's medium-expert kind), e.g. MPC-Forecast's episodes beside its noisy ones.

    The card keeps each part's behaviour score and the references they share. Refuses one behaviour's episode twice, a file given twice, and parts of other cities or logging; to join pieces of one collection use merge-datasets.
    """  # one line per paragraph: --help prints a docstring's line breaks as they are
    from marl_amod.datasets import OfflineDataset, card_path, dataset_destination, mix, mix_cards
    from marl_amod.files import file_sha256

    output = dataset_destination(output)
    if output.resolve() in {p.resolve() for p in parts}:
        raise ConfigError(f"--output {output} is one of the parts: write the mixture to a new file")
    seen: dict[str, Path] = {}
    for part in parts:
        if not part.is_file():
            raise ConfigError(f"no dataset at {part}")
        first = seen.setdefault(file_sha256(part), part)
        if first is not part:
            raise ConfigError(f"{first} and {part} are the same data: each would weigh twice")
    data = mix([OfflineDataset.load(p) for p in parts], names=[str(p) for p in parts])
    path = save_or_fallback(output, data.save, what="the dataset")
    card = mix_cards(path, data, parts)
    held = ", ".join(f"{meta['episodes']} of {meta['policy']}" for meta in data.meta["parts"])
    console.print(f"wrote {data.meta['episodes']} episodes ({held}), {len(data)} transitions to {path}")
    console.print(f"card {card_path(path)}" if card else "no card (the parts have none)")


def _collect_one(
    scenario: str, policy: str, episodes: int, seed: int, output: Path, max_wait: int, eval_episodes: int, eval_seed: int,
    cache: dict, noise: float = 0.0, lookahead: int = 6, policy_options: dict | None = None, first_episode: int = 0,
    arrivals_now: bool = False,
) -> None:
    from marl_amod.datasets import collect as collect_dataset
    from marl_amod.datasets import dataset_destination, write_card
    from marl_amod.policies import make_policy
    from marl_amod.scenario import load_city

    output = dataset_destination(output)  # before the run, not after it
    city = load_city(scenario)
    pol = make_policy(policy, city, **(policy_options or {}))
    with progress_bar() as bar:
        task = bar.add_task(f"{pol.name} on {city.name}", total=episodes)
        data = collect_dataset(
            city, pol, episodes=episodes, seed=seed, lookahead=lookahead, max_wait=max_wait, noise=noise,
            progress=lambda _k: bar.advance(task), first_episode=first_episode, arrivals_now=arrivals_now,
        )
    data.meta["policy_options"] = dict(policy_options or {})  # the name alone does not say e.g. the horizon
    path = save_or_fallback(output, data.save, what="the dataset")
    console.print(f"wrote {len(data)} transitions ({city.n_regions} agents) to {path}")
    if eval_episodes:
        card = write_card(path, data, city, pol, eval_episodes=eval_episodes, eval_seed=eval_seed, cache=cache)
        b = card["behaviour_score"]
        console.print(f"card {path.with_suffix('.json')}: behaviour {b['mean']:,.0f} (normalised {b['normalised']:.1f})")
    elif (stale := path.with_suffix(".json")).is_file():  # an earlier dataset's card would describe this one
        stale.unlink()
        console.print(f"removed {stale}: the card of the dataset this one replaced (--eval-episodes 0 writes none)")


@app.command()
def datasets(
    scenario: Annotated[str, typer.Option(help="scenario name or YAML path")] = "nyc_brooklyn",
    policies: Annotated[str, typer.Option(help="comma-separated behaviour policies")] = "inf,dtv,prop,mpc-forecast",
    episodes: Annotated[int, typer.Option(min=1, help="episodes per dataset")] = 200,
    seed: Annotated[int, typer.Option(min=0, help="collection seed (disjoint from evaluation's)")] = 0,
    out_dir: Annotated[Path, typer.Option(help="folder of <scenario>_<policy>.npz and cards")] = Path("runs/datasets"),
    eval_episodes: CardEpisodes = 10,
    eval_seed: CardSeed = 0,
    noise: Annotated[float, typer.Option(min=0, help="exploratory actions (see collect); names get _noise<x>")] = 0.0,
    data_dir: DataDir = None,
) -> None:
    """The benchmark's offline datasets: one per behaviour policy, each with its card."""
    from marl_amod.scenario import load_city

    _use_data_dir(data_dir)
    names = [p.strip() for p in policies.split(",") if p.strip()]
    if not names:
        raise ConfigError(f"--policies names no policy: {policies!r}")
    if len(set(names)) < len(names):
        raise ConfigError(f"--policies names a policy twice: {policies!r} (each dataset is one file)")
    _make_policies(names, load_city(scenario), {})  # a typo in the last name fails before the first dataset
    check_folder(out_dir, what="--out-dir")
    suffix = f"_noise{noise:g}" if noise else ""
    # a checkpoint's dataset is named by its file's stem, not its path
    outs = {name: out_dir / f"{Path(scenario).stem}_{Path(name).stem.replace('-', '_')}{suffix}.npz" for name in names}
    if len(set(outs.values())) < len(outs):
        raise ConfigError(f"--policies {policies!r}: two of them would write one dataset ({', '.join(map(str, outs.values()))})")
    cache: dict = {}
    for name, out in outs.items():
        _collect_one(scenario, name, episodes, seed, out, 0, eval_episodes, eval_seed, cache, noise)


@app.command()
def train(
    config: Annotated[Path, typer.Option(help="training config YAML (configs/<algo>/<city>.yaml)")],
    resume: Annotated[Path | None, typer.Option(help="resume from a training state (runs/<run>/state.pt)")] = None,
    backend: Annotated[str, typer.Option(help="native (every registered algorithm, in-process) or rllib (PPO on Ray RLlib)")] = "native",
    num_env_runners: Annotated[
        int | None, typer.Option(min=0, help="rllib: remote env runners (default: the config's)", show_default=False)
    ] = None,
    address: Annotated[
        str | None, typer.Option(help="rllib: join a Ray cluster (auto or ray://host:10001) instead of a local one", show_default=False)
    ] = None,
    data_dir: DataDir = None,
) -> None:
    """Train any registered algorithm (A2C, SAC, BC, IQL, CQL, meta-RL; or PPO on RLlib) from its config; logs under runs/, policy + card to policies/."""
    _use_data_dir(data_dir)
    if backend == "rllib":
        if resume is not None:
            raise ConfigError("--resume is for the native backend; RLlib runs keep their checkpoint under runs/")
        _train_rllib(config, num_env_runners, address)
        return
    if backend != "native":
        raise ConfigError(f"--backend must be native or rllib, got {backend!r}")
    if num_env_runners is not None or address is not None:
        raise ConfigError("--num-env-runners and --address need --backend rllib")
    from marl_amod.algos.common import TrainingInterrupted
    from marl_amod.algos.registry import load_train_config, run_training
    from marl_amod.config import read_config

    if read_config(config).get("algo") == "ppo":  # the reverse of load_rllib_config's hint
        raise ConfigError(f"{config}: algo: ppo trains on Ray RLlib; add --backend rllib")
    algo, args = load_train_config(config)
    last_eval: dict[str, float] = {}
    try:
        with progress_bar() as bar:
            where, last = args.trained_on(), args.run_length()
            task = bar.add_task(f"{algo} {args.mode} on {where}", total=last)

            def progress(ep: int, total: int, stats: dict) -> None:
                if "eval/profit" in stats:
                    last_eval["profit"] = stats["eval/profit"]
                desc = f"{algo} {args.mode} on {where}"
                if last_eval:
                    desc += f" | val profit {last_eval['profit']:,.0f}"
                if stats.get("status"):  # what a run does between updates (collecting demonstrations, a DAgger round)
                    desc += f" | {stats['status']}"
                    if not console.is_terminal:  # a log file gets each as a line (the bar there prints only its tenths)
                        console.print(f"{algo} at {ep:,}/{last:,}: {stats['status']}", markup=False)
                bar.update(task, completed=ep, description=desc)

            summary = run_training(algo, args, resume=str(resume) if resume else None, progress=progress, config_path=str(config))
    except TrainingInterrupted as stop:
        console.print(
            f"interrupted at episode {stop.episode}: training state in {stop.path}; "
            f"resume with: marl-amod train --config {config} --resume {stop.path}",
            soft_wrap=True,  # one line, however long the paths
        )
        raise typer.Exit(130) from None
    except KeyboardInterrupt:  # outside the training loop: setting up, or the final evaluation and the card
        state = Path(args.run_dir) / "state.pt"
        said = (f"interrupted outside the training loop (the final evaluation?); the last training state is {state}: "
                f"finish with: marl-amod train --config {config} --resume {state}") if state.is_file() else "interrupted before training began"
        console.print(said, soft_wrap=True)
        raise typer.Exit(130) from None
    from marl_amod.policy_catalogue import trained_on

    card = summary["card"]
    console.print(
        f"{card['scenario']}: profit {card['profit_mean']:,.1f} ± {card['profit_std']:,.1f} over {card['eval_episodes']} episodes "
        f"(seed {card['eval_seed']}), trained {trained_on(card)}"
    )
    if "policy" in summary:
        console.print(f"wrote {summary['policy']} (+ .json, .md); logs in {args.run_dir}")


@app.command()
def dagger(
    config: Annotated[Path, typer.Option(help="the BC config each round retrains (its dataset is the expert's own episodes)")],
    start: Annotated[Path, typer.Option(help="the policy rolled out in round 1 (usually the config's own clone)")],
    expert: Annotated[str, typer.Option(help="the policy whose actions label the visited states")] = "mpc-forecast",
    rounds: Annotated[int, typer.Option(min=1, help="DAgger rounds (done rounds are skipped: rerun to resume)")] = 3,
    episodes: Annotated[int, typer.Option(min=1, help="learner episodes collected per round")] = 20,
    seed: Annotated[int, typer.Option(min=0, help="collection seed of round 1 (round k: seed + k - 1)")] = 1,
    run_root: Annotated[Path, typer.Option(help="each round's dataset, BC run and policy; dagger.json")] = Path("runs/dagger"),
    data_dir: DataDir = None,
) -> None:
    """DAgger: roll the clone out, label its states with the expert's actions, retrain BC on the aggregate."""
    from marl_amod.dagger import dagger as run_dagger

    _use_data_dir(data_dir)
    summary = run_dagger(config, start=str(start), expert=expert, rounds=rounds, episodes=episodes, seed=seed, run_root=run_root,
                         progress=lambda msg: console.print(msg, soft_wrap=True))  # fmt: skip
    for r in summary["rounds"]:
        console.print(f"round {r['round']}: {r['transitions']:,} transitions, validation profit {r['validation_profit']:,.0f} -> {r['policy']}")
    console.print(f"kept round {summary['kept']}" + (f" as {summary['policy_out']}" if summary["policy_out"] else ""))


@app.command("finetune-curve")
def finetune_curve(
    policy: Annotated[Path, typer.Option(help="the offline policy to fine-tune (a bc/iql/cql .pt with its dataset on the card)")] = Path(
        "policies/iql_gnn_nyc_brooklyn_prop.pt"
    ),
    episodes: Annotated[int, typer.Option(min=1, help="online episodes of each run (fine-tuned and scratch)")] = 6000,
    num_envs: Annotated[int, typer.Option(min=1, help="episodes in lockstep, one A2C update each")] = 4,
    eval_every: Annotated[int, typer.Option(min=1, help="episodes between validations")] = 200,
    eval_episodes: Annotated[int, typer.Option(min=1, help="validation episodes at each validation")] = 10,
    critic_warmup: Annotated[int, typer.Option(min=0, help="first fine-tuning updates that train the critic only")] = 0,
    finetune_lr: Annotated[float, typer.Option(min=0, help="actor learning rate when fine-tuning")] = 3e-4,
    concentration_cap: Annotated[
        float | None, typer.Option(min=0, help="cap on the fine-tuned actor's total Dirichlet concentration when sampling")
    ] = None,
    critic_dataset: Annotated[Path | None, typer.Option(help="pre-train the fine-tuned run's critic on this dataset (default: the policy's own training dataset)")] = None,
    fresh_critic: Annotated[bool, typer.Option(help="start the fine-tuned run's critic fresh instead (train it alone for --critic-warmup updates)")] = False,
    out: Annotated[Path, typer.Option(help="folder for finetune.json and finetune.png")] = Path("docs/offline"),
    run_root: Annotated[Path, typer.Option(help="the two runs' logs")] = Path("runs/finetune"),
    seed: Annotated[int, typer.Option(min=0, help="training seed of both runs (torch, numpy, training demand)")] = 0,
    data_dir: DataDir = None,
) -> None:
    """Offline -> online: fine-tune an offline policy with A2C next to A2C from scratch; plot and numbers."""
    from marl_amod import finetune

    if fresh_critic and critic_dataset is not None:
        raise ConfigError(f"--fresh-critic starts the critic untrained; --critic-dataset {critic_dataset} would pre-train it: give one of them")
    _use_data_dir(data_dir)
    check_folder(out, what="--out")  # before both runs, not after them
    check_folder(run_root, what="--run-root")
    with progress_bar() as bar:
        task = bar.add_task("A2C", total=episodes)
        study = finetune.finetune_curve(
            str(policy), episodes=episodes, num_envs=num_envs, eval_every=eval_every, eval_episodes=eval_episodes, seed=seed,
            finetune_lr_actor=finetune_lr, critic_warmup=critic_warmup, concentration_cap=concentration_cap, critic_dataset=None if fresh_critic else (critic_dataset or finetune.OWN_DATASET),
            run_root=run_root, progress=lambda ep, total, stats: bar.update(task, completed=ep),
        )  # fmt: skip
    paths = finetune.write(study, out)
    console.print(finetune.describe(study), soft_wrap=True)
    console.print(f"wrote {paths[0]} and {paths[1]}")


def _train_rllib(config: Path, num_env_runners: int | None, address: str | None) -> None:
    """PPO with one shared GNN module on Ray RLlib; a log line per iteration, the policy in the native format."""
    from marl_amod.integrations.rllib import load_rllib_config, train_rllib

    args = load_rllib_config(config)
    runners = args.num_env_runners if num_env_runners is None else num_env_runners
    where = address or f"local Ray ({args.num_cpus} CPUs)"
    with progress_bar() as bar:
        task = bar.add_task(f"rllib ppo on {args.scenario}", total=args.iterations)

        def progress(it: int, total: int, stats: dict) -> None:
            line = (
                f"iter {it:4d} | {stats['iter_s']:5.2f} s | {stats['env_steps_iter'] / stats['iter_s']:6.0f} env steps/s"
                f" | train profit {stats['train/profit']:8,.0f}"
            )
            if "eval/profit" in stats:
                line += f" | val profit {stats['eval/profit']:8,.0f}"
            bar.console.print(line)
            bar.update(task, completed=it)

        console.print(f"rllib ppo on {args.scenario}: {runners} env runner(s) on {where}")
        summary = train_rllib(args, runners, address, progress=progress, config_path=str(config))
    card = summary["card"]
    console.print(
        f"{card['scenario']}: profit {card['profit_mean']:,.1f} ± {card['profit_std']:,.1f} over {card['eval_episodes']} episodes "
        f"(seed {card['eval_seed']}), {card['iterations']} iterations, {card['env_steps']:,} env steps in "
        f"{card['training_wall_s'] / 60:.1f} min; RLlib checkpoint {summary['checkpoint']}"
    )
    if "policy" in summary:
        console.print(f"wrote {summary['policy']} (+ .json, .md); logs in {args.run_dir}")


@app.command()
def compare(
    config: Annotated[Path, typer.Option(help="comparison config YAML (configs/compare/<city>.yaml)")],
    no_train: Annotated[
        bool, typer.Option("--no-train", help="skip runs whose policy file is missing instead of training them")
    ] = False,
    data_dir: DataDir = None,
) -> None:
    """Learned policies (centralised, decentralised, ablations) vs baselines on the same seeds: table + plots.

    A run whose policy file is missing is trained first (said before it starts, with progress); --no-train skips it.
    """
    from marl_amod.comparison import load_compare_config, run_compare

    _use_data_dir(data_dir)
    cfg = load_compare_config(config)
    with progress_bar() as bar:

        def tracker(description: str):  # noqa: ANN202 - the comparison's Tracker
            task = bar.add_task(description, total=None)
            return lambda done, total: bar.update(task, completed=done, total=total)

        payload = run_compare(cfg, log=bar.console.print, config_path=str(config), train=not no_train, tracker=tracker)
    console.print((Path(cfg.output) / "compare.md").read_text())
    console.print(f"best baseline: {payload['best_baseline']}")


plot_app = typer.Typer(no_args_is_help=True, help="Study figures from evaluations.")
app.add_typer(plot_app, name="plot")


@plot_app.command("wait-map")
def wait_map(
    scenario: Annotated[str, typer.Option(help="scenario name or YAML path")] = "synthetic",
    policy: Annotated[list[str], typer.Option(help="policy name or checkpoint; repeat: one panel each")] = ["no-rebalancing", "equal-distribution"],  # noqa: B006
    episodes: Episodes = 10,
    seed: EvalSeed = 0,
    max_wait: Annotated[int, typer.Option(min=1, help="steps a request waits before leaving (waits are 0 without waiting)")] = 3,
    output: Annotated[Path, typer.Option(help="figure to write (.png); the results JSON goes beside it")] = Path("wait_map.png"),
    data_dir: DataDir = None,
) -> None:
    """Per-region mean waiting time (and service rate) of each policy on the region map, shared colour scale."""
    from marl_amod.evaluation import evaluate as run_eval
    from marl_amod.files import write_json
    from marl_amod.plots import figure_destination, region_map
    from marl_amod.scenario import load_city

    _use_data_dir(data_dir)
    figure_destination(output, what="--output")  # before the run, not after it
    check_destination(output.with_suffix(".json"), what="--output's JSON")  # the numbers beside the figure, likewise
    city = load_city(scenario)
    policies = _make_policies(policy, city, {})
    results = []
    with progress_bar() as bar:
        for name, pol in zip(policy, policies, strict=True):
            task = bar.add_task(f"{name} on {city.name}", total=episodes)
            results.append(run_eval(pol, city, episodes, seed, max_wait=max_wait,
                                    progress=lambda _k, task=task: bar.advance(task)))
    console.print(metrics_table(results, f"{city.name}: {episodes} episodes, seed {seed}, max wait {max_wait} steps"))
    title = f"{city.name}: {episodes} episode{'s' if episodes != 1 else ''} (seed {seed}), requests wait up to {max_wait} steps ({max_wait * city.tstep:g} min)"
    path = region_map(results, city, output, title=title)
    write_json(output.with_suffix(".json"), {"scenario": city.name, "max_wait": max_wait, "results": results})
    console.print(f"wrote {path} and {output.with_suffix('.json')}")


@app.command()
def transfer(
    strategy: Annotated[str, typer.Option(help="zero-shot, fine-tune, meta-rl, single-city, mpc-forecast or mpc-oracle")],
    scenario: Annotated[str, typer.Option(help="the new city: san_francisco, nyc_brooklyn, shenzhen_downtown_west, nyc_brooklyn_event")],
    policy: Annotated[str | None, typer.Option(help="starting policy .pt, or the meta-policy (default: the study's, see marl_amod.transfer)")] = None,
    adapt_episodes: Annotated[int | None, typer.Option(min=0, help="K online episodes in the new city (fine-tune, meta-rl)")] = None,
    episodes: Episodes = 10,
    seed: EvalSeed = 0,
    output: Annotated[Path | None, typer.Option(help="write the result JSON here")] = None,
    data_dir: DataDir = None,
) -> None:
    """Transfer a policy to a new city with one strategy, then evaluate it on the report seeds."""
    from marl_amod.transfer import run_strategy

    _use_data_dir(data_dir)
    if output is not None:
        output = check_destination(output, what="--output")
    result = run_strategy(strategy, scenario, episodes=episodes, seed=seed, policy=policy, adapt_episodes=adapt_episodes)
    used = result["transfer"]
    console.print(metrics_table([result], f"{strategy} on {result['scenario']}: {episodes} episodes, seed {seed}"))
    console.print(f"episodes in {result['scenario']} before evaluation: {used['target_episodes']}; source: {used.get('source', '-')}")
    if output is not None:
        save_or_fallback(output, lambda path: write_json(path, result), what="the result")
        console.print(f"wrote {output}")


@app.command()
def ensemble(
    members: Annotated[list[Path], typer.Argument(help="two or more policy checkpoints (.pt)")],
    out: Annotated[Path, typer.Option(help="the ensemble file (.yaml); its card goes beside it (.md)")],
    adaptation: Annotated[str | None, typer.Option(help="meta-policies only: how they act in their adaptation episodes: "
                                                        "sampled (as trained), mean, prior-concentration (marl_amod.algos.meta.adapt)")] = None,
    together: Annotated[bool, typer.Option(help="meta-policies only: adapt as the ensemble, K adaptation episodes in all instead of K each "
                                                "(marl_amod.algos.meta.adapt_together)")] = False,
) -> None:
    """Write an ensemble of policies (their desired distributions averaged) and its card; it then loads wherever a checkpoint does, e.g. ``marl-amod evaluate --policy X.yaml``."""
    from marl_amod.ensemble import write_ensemble

    path = write_ensemble(out, list(members), adaptation, together)  # type: ignore[arg-type]  # checked there
    console.print(f"wrote {path} ({len(members)} members) and {path.with_suffix('.md')}")


@app.command("train-ensemble")
def train_ensemble(
    configs: Annotated[list[Path], typer.Argument(help="two or more training configs, one member each (e.g. two training seeds of a recipe)")],
    out: Annotated[Path, typer.Option(help="the ensemble file (.yaml) written from the members' policies; its card goes beside it (.md)")],
    jobs: Annotated[int | None, typer.Option(min=1, help="members trained at once, one process each (default: as many as there are "
                                                       "members, at most the machine's cores)", show_default=False)] = None,
    resume: Annotated[bool, typer.Option(help="keep the members whose policy this config already made, resume those with a training "
                                              "state (after a Ctrl-C), start the rest")] = False,
    data_dir: DataDir = None,
) -> None:
    """Train several configs side by side, one process each, then write their ensemble: the tables' meta-policy in one command."""
    from marl_amod.ensemble import is_ensemble, write_ensemble
    from marl_amod.side_by_side import plan, train_side_by_side

    _use_data_dir(data_dir)
    if not is_ensemble(out):  # write_ensemble would refuse it too, but only after the training
        raise ConfigError(f"--out {out}: the ensemble file is named .yaml")
    check_destination(out, what="--out")
    members = plan([str(c) for c in configs])
    jobs = jobs or min(len(members), os.cpu_count() or 1)
    console.print(f"{len(members)} members, {jobs} at a time; each run's output in its run_dir/train.log")
    started = time.time()
    try:
        with progress_bar() as bar:
            tasks = {m: bar.add_task(f"{m.config.stem}: waiting", total=m.total) for m in members}

            def tick(status: dict) -> None:
                for m, (state, done) in status.items():
                    bar.update(tasks[m], completed=done, description=f"{m.config.stem}: {state}")

            outcomes = train_side_by_side(members, jobs, resume, tick)
    except KeyboardInterrupt:
        console.print("interrupted: each running member saved its training state; rerun the same command with --resume", soft_wrap=True)
        raise typer.Exit(130) from None
    wall = time.time() - started
    table = Table("member", "policy", "wall time", "status")
    for o in outcomes:
        table.add_row(str(o.member.config), str(o.member.policy_out), "-" if o.kept else f"{o.wall_s / 60:.1f} min",
                      "kept (--resume)" if o.kept else "done" if o.ok else f"failed (exit {o.returncode})")  # fmt: skip
    console.print(table)
    failed = [o for o in outcomes if not o.ok]
    for o in failed:
        lines = o.member.log.read_text(errors="replace").strip().splitlines() if o.member.log.is_file() else []
        console.print(f"{o.member.config} failed; its log {o.member.log} ends: {escape(lines[-1]) if lines else '(empty)'}", soft_wrap=True)
    if failed:
        console.print(f"[red]{len(failed)} member(s) failed[/red]; no ensemble written. Fix and rerun with --resume to keep the others.", soft_wrap=True)
        raise typer.Exit(1)
    path = write_ensemble(out, [o.member.policy_out for o in outcomes])
    console.print(f"wrote {path} ({len(outcomes)} members) and {path.with_suffix('.md')}; {wall / 60:.1f} min of wall time side by side")


@app.command("transfer-table")
def transfer_table(
    study: Annotated[str, typer.Option(help="intercity (3 held-out cities) or event (Brooklyn special event)")],
    out: Annotated[Path, typer.Option(help="folder for <study>.md, <study>.json and <study>.png")] = Path("docs/meta"),
    episodes: Episodes = 10,
    seed: EvalSeed = 0,
    strategy: Annotated[
        list[str] | None, typer.Option(help="rerun only these rows (repeat); the others come from <out>/<study>.json")
    ] = None,
    meta_policy: Annotated[str | None, typer.Option(help="the meta-policy (.pt) or ensemble (.yaml) of the meta-rl row (default: marl_amod.transfer.META_POLICY)")] = None,
    redraw: Annotated[bool, typer.Option(help="evaluate nothing: rewrite <study>.md and <study>.png from <out>/<study>.json")] = False,
    data_dir: DataDir = None,
) -> None:
    """Every transfer strategy on a study's cities: the tables of docs/meta (markdown, JSON) and their figure (<study>.png)."""
    from marl_amod.data import read_json
    from marl_amod.plots import score_bars
    from marl_amod.transfer import META_POLICY, STRATEGIES, check_study, run_study, study_markdown, study_scores

    _use_data_dir(data_dir)
    check_study(study, tuple(strategy or ()))  # before --out is made: a typo leaves no empty folder behind
    check_folder(out, what="--out")
    saved = out / f"{study}.json"
    if redraw:
        if strategy or meta_policy:
            raise ConfigError("--redraw evaluates nothing: drop --strategy and --meta-policy, or drop --redraw")
        if not saved.is_file():
            raise DataError(f"--redraw reads {saved}, which does not exist: run the study first (without --redraw)")
        payload = read_json(saved)
    else:
        previous = read_json(saved) if strategy and saved.is_file() else None
        payload = run_study(study, episodes=episodes, seed=seed, strategies=tuple(strategy or STRATEGIES), previous=previous,
                            meta_policy=meta_policy or META_POLICY, progress=lambda city, name, p: console.print(f"{city}: {name} {p:,.0f}"))  # fmt: skip
        payload["meta_policy"] = meta_policy  # None: the default; kept so that --redraw names the command again
        write_json(saved, payload)
    command = f"marl-amod transfer-table --study {study} --episodes {payload['episodes']} --seed {payload['seed']}"
    if payload.get("meta_policy"):  # absent from files of before: those were made with the default
        command += f" --meta-policy {payload['meta_policy']}"
    text = f"<!-- {command} -->\n" + study_markdown(payload)
    (out / f"{study}.md").write_text(text)
    title = f"{study}: normalised score over {payload['episodes']} episode{'s' if payload['episodes'] != 1 else ''}"
    scores = study_scores(payload)
    figure = score_bars(scores, out / f"{study}.png", title) if scores else "no figure (no MPC-Oracle row to score by)"
    console.print(text)
    console.print(f"wrote {out / (study + '.md')}, {figure}" + ("" if redraw else f" and {saved}"))


def main() -> None:
    """Entry point: user errors print one clear line and exit 2, never a traceback."""
    try:
        app()
    except MarlAmodError as exc:
        # soft_wrap: one line however long (rich would cut it at the console width, mid-list)
        console.print(f"[red]error:[/red] {escape(str(exc))}", soft_wrap=True)  # messages name extras like [sumo]
        raise SystemExit(2) from None


if __name__ == "__main__":
    main()
