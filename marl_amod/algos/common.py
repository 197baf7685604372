"""What every native algorithm shares: run args, logging, validation, the training state, the card.

The algorithm files (:mod:`marl_amod.algos.a2c`, :mod:`marl_amod.algos.sac`) read top to bottom;
everything here is plumbing they would otherwise repeat. The rollout driver is
:mod:`marl_amod.algos.rollout`; the registry of algorithms is :mod:`marl_amod.algos.registry`.

Interrupts: an algorithm wraps its loop in :func:`interruptible` and calls :func:`stop_if_asked`
after each update; a first Ctrl-C stops the run there (a second stops it at once), saves the
training state of that finished update (atomically) and raises :class:`TrainingInterrupted`, which
the CLI prints as one line saying where the state is and how to resume. A resumed run rewrites
``log.csv`` without the rows logged after that state, so no episode appears twice.
"""

from __future__ import annotations

import contextlib
import copy
import csv
import ctypes
import io
import time
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import torch
from pydantic import Field, model_validator

from marl_amod.algos.rollout import BatchRollout, Mode, Rollout
from marl_amod.checkpoints import ActorPolicy, actor_inputs, check_torch_file, make_card, save_policy, with_context
from marl_amod.config import CommonArgs
from marl_amod.env.features import n_features
from marl_amod.errors import ConfigError, DataError, MarlAmodError
from marl_amod.files import atomic_write, file_sha256, torch_save, write_json
from marl_amod.models import LocalActor, build_actor
from marl_amod.models.dense import DenseGraph
from marl_amod.models.gnn import Readout
from marl_amod.scenario import City
from marl_amod.selection import QSelector, Selection

Progress = Callable[[int, int, dict], None]
Precision = Literal["fp32", "bf16"]
Autocast = Callable[[], contextlib.AbstractContextManager]


def autocast(precision: Precision) -> Autocast:
    """The context a gradient update's network passes run in: bfloat16 autocast on the CPU, or nothing.

    A fresh context per pass: autocast caches the bf16 copies of the weights until its outermost
    context exits, and weights that change between the passes of one update (SAC's critic) must be cast again.
    """
    if precision == "fp32":
        return contextlib.nullcontext
    return lambda: torch.autocast("cpu", dtype=torch.bfloat16)


class RunArgs(CommonArgs):
    """What every native training run has, whatever the algorithm; each algorithm's ``Args`` extends it."""

    mode: Mode = "centralised"
    """centralised: one learner on the global graph; decentralised: shared actor on local observations"""
    actor: Literal["gnn", "mlp", "cnn"] = "gnn"
    """centralised actor architecture (decentralised always uses the local GNN actor)"""
    conv: Literal["gcn", "sage"] = "gcn"
    """message passing: gcn (the paper's) or sage (mean aggregation, what the local actor computes)"""
    readout: Readout = "none"
    """centralised GNN actor (and A2C's value critic): append a pooled summary of every region
    (mean and/or max of a learned node map) to each node before the head, so a region's output
    can depend on the whole fleet, not only its neighbours (none: the paper's one-hop GNN)"""
    agent_id: bool = False
    """centralised GNN actor (and A2C's value critic): append a one-hot of the region index to
    every node's input (the agent-ID input of parameter-shared MARL policies), so a region's
    output can depend on where it is; ties the policy to the training city's size and region
    order (the card records it; evaluating it on a city of another size is an error)"""
    standardise_inputs: bool = False
    """centralised MLP actor: standardise every input dimension by the offline dataset's mean and
    std (CORL's state normalisation; offline runs set them from their dataset, a run with
    init_actor takes its start's); the statistics ride in the policy file and the card records it"""
    central_critic: bool = True
    """decentralised mode only: critic on the global graph (env.state()) instead of sum of local values"""
    episodes: int = Field(1000, ge=1)
    """training episodes"""
    max_grad_norm: float = Field(10.0, gt=0)
    """gradient clipping (global L2 norm per network)"""
    threads: int = Field(1, ge=1)
    """torch CPU threads (the machine is shared)"""
    num_envs: int = Field(1, ge=1)
    """episodes run in lockstep on the batched simulator, models on the dense small-graph path
    (1: one episode at a time through torch-geometric, how the shipped policies were trained)"""
    critic_time: bool = False
    """critics also read the time context the local actors see (time of day, step fraction):
    episodes have a fixed horizon, so the value of a state depends on the steps to go"""
    actor_time: bool = False
    """the centralised actor also reads the time context on every node: without it a GNN cannot
    tell the last steps, where a move no longer pays back, from the first (the card records it)"""
    arrivals_now: bool = False
    """every node also reads the vehicles arriving at it in the current step (idle from the next;
    in no default column, yet MPC's plan starts from them: :mod:`marl_amod.env.features`); the card
    records it, so evaluation and warm starts build the same features"""
    init_actor: str = ""
    """a policy .pt whose weights start the actor (offline -> online, macro -> SUMO fine-tuning);
    same actor, hidden, conv; the critic and optimisers start fresh (A2C validates the start first)"""

    @model_validator(mode="after")
    def _gnn_options_apply(self) -> RunArgs:
        why = {"readout": "pools over every region", "agent_id": "sizes a one-hot for the whole city's regions"}
        for key, off in (("readout", "none"), ("agent_id", False)):
            if getattr(self, key) == off:
                continue
            if self.mode == "decentralised":
                raise ValueError(f"{key} {why[key]}, but a decentralised actor reads only its local observation "
                                 f"(use mode: centralised, or {key}: {str(off).lower()})")  # fmt: skip
            if self.actor != "gnn":
                raise ValueError(f"{key} is a GNN actor option; the {self.actor} actor reads every region, each in its place, "
                                 f"already (use actor: gnn, or {key}: {str(off).lower()})")  # fmt: skip
        if self.standardise_inputs and (self.mode == "decentralised" or self.actor != "mlp"):
            raise ValueError("standardise_inputs is an option of the centralised MLP actor (use actor: mlp, or standardise_inputs: false)")
        if self.standardise_inputs and not self.init_actor and "dataset" not in type(self).model_fields:
            raise ValueError("standardise_inputs: an online run takes the statistics from its start; without init_actor they would "
                             "stay mean 0, std 1 (set init_actor to a standardised offline policy, or standardise_inputs: false)")  # fmt: skip
        return self

    def run_length(self) -> int:
        """The updates (offline and imitation runs) or episodes (online ones) the run is set to reach:
        what its progress bar counts to."""
        return getattr(self, "updates", self.episodes)

    def trained_on(self) -> str:
        """Where the run learns, as its progress bar names it."""
        return self.scenario

    def outputs(self) -> dict[str, str]:
        """The paths the run writes to, by key (two runs side by side must not share one)."""
        return {"run_dir": self.run_dir, "policy_out": self.policy_out}

    def ignored_keys(self) -> dict[str, str]:
        if self.mode == "centralised":
            return {"central_critic": "only decentralised runs choose their critic"}
        return {"actor": "decentralised runs always use the local GNN actor", "actor_time": "the local actor reads its own observation"}


def check_separate_outputs(runs: Iterable[tuple[str, Any]]) -> None:
    """Refuse (ConfigError) runs, given as (name, args), that would write to one path: the run folder,
    the policy file, meta-imitation's demonstrations (``outputs()``); one would overwrite the other's."""
    seen: dict[Path, str] = {}  # a path written to -> the run writing it
    for name, args in runs:
        for key, path in args.outputs().items():
            if not path:
                continue
            if (where := Path(path).resolve()) in seen:
                raise ConfigError(f"{seen[where]} and {name} share {key} {path}: each run needs its own")
            seen[where] = name


def make_rollout(city: City, args: RunArgs) -> Rollout | BatchRollout:
    """The rollout driver of a run: one episode at a time, or ``num_envs`` in lockstep."""
    if args.num_envs > 1:
        return BatchRollout(city, args.mode, args.lookahead, args.num_envs, args.arrivals_now)
    return Rollout(city, args.mode, args.lookahead, args.arrivals_now)


def make_graph(city: City, args: RunArgs) -> torch.Tensor | DenseGraph:
    """How the models see the city graph: torch-geometric's edge_index (one episode at a time,
    as before) or the dense operators of the batched path."""
    edge_index = torch.tensor(city.edge_index, dtype=torch.long)  # a copy: the city's arrays are read-only
    return DenseGraph(edge_index, city.n_regions) if args.num_envs > 1 else edge_index


def actor_features(n_features: int, args: RunArgs) -> int:
    """Input columns of a centralised actor: F, plus the time context with ``actor_time``."""
    return actor_inputs(n_features, args.actor_time)


def run_features(args: RunArgs) -> int:
    """F of a run's node features (its lookahead and the opt-in ``arrivals_now`` column): one place,
    so every network of a run (actor, critics, the card) reads the width its rollout or data has."""
    return n_features(args.lookahead, args.arrivals_now)


def make_actor(args: RunArgs, city: City) -> torch.nn.Module:
    """The run's actor: the local (SAGE) GNN on each agent's observation for decentralised runs,
    else ``args.actor`` on the global graph (reading the time context too with ``actor_time``)."""
    f = run_features(args)
    if args.mode == "decentralised":
        return LocalActor(f, args.hidden)
    return build_actor(args.actor, city, actor_features(f, args), args.hidden, args.conv, args.readout, args.agent_id, args.standardise_inputs)


def critic_features(n_features: int, args: RunArgs) -> int:
    """Node features a critic reads: F, plus the time context with ``critic_time``."""
    return actor_inputs(n_features, args.critic_time)


def with_time(x: torch.Tensor, ctx: torch.Tensor | None, use: bool) -> torch.Tensor:
    """x (..., N, F) with the time context (..., 3) appended to every node when ``use``: (..., N, F + 3)."""
    return with_context(x, ctx) if use else x


# --------------------------------------------------------------------------------------------
# Logging
# --------------------------------------------------------------------------------------------
class Logger:
    """TensorBoard scalars plus a long-format CSV (episode, metric, value) under ``run_dir``.

    Long format because validation rows are sparser than training rows; plots pivot it back.
    ``resume_from=k`` drops the rows logged after episode k (they belong to the run being
    replaced), so a resumed run never logs an episode twice.
    """

    def __init__(self, run_dir: str | Path, tensorboard: bool = True, resume_from: int | None = None) -> None:
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        path = self.dir / "log.csv"
        if resume_from is not None and path.exists():
            with open(path, newline="") as fh:
                kept = [row for row in csv.reader(fh) if row and (row[0] == "episode" or int(row[0]) <= resume_from)]
            out = io.StringIO()
            csv.writer(out).writerows(kept)
            atomic_write(path, out.getvalue())
        elif resume_from is None:  # a fresh run starts a fresh log, and TensorBoard curves of its own
            path.unlink(missing_ok=True)
            for old in self.dir.glob("events.out.tfevents.*"):
                old.unlink()
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.dir), purge_step=None if resume_from is None else resume_from + 1)
        new = not path.exists()
        self._csv = open(path, "a", newline="")  # noqa: SIM115 - closed in close()
        self._w = csv.writer(self._csv)
        if new:
            self._w.writerow(["episode", "metric", "value"])

    def log(self, step: int, **scalars: float) -> None:
        for k, v in scalars.items():
            self._w.writerow([step, k, float(v)])
            if self.writer is not None:
                self.writer.add_scalar(k, v, step)
        self._csv.flush()

    def close(self) -> None:
        self._csv.close()
        if self.writer is not None:
            self.writer.close()


def read_curve(run_dir: str | Path, metric: str) -> tuple[list[int], list[float]]:
    """(episodes, values) of one metric from a run's log.csv."""
    xs, ys = [], []
    path = Path(run_dir) / "log.csv"
    if path.exists():
        with open(path, newline="") as fh:
            for row in csv.DictReader(fh):
                if row["metric"] == metric:
                    xs.append(int(row["episode"]))
                    ys.append(float(row["value"]))
    return xs, ys


class Timer:
    """Wall seconds since construction, plus what earlier (resumed) sessions already spent."""

    def __init__(self, prior: float = 0.0) -> None:
        self.start, self.prior = time.perf_counter(), prior

    def __call__(self) -> float:
        return self.prior + time.perf_counter() - self.start


# --------------------------------------------------------------------------------------------
# Validation and the best actor
# --------------------------------------------------------------------------------------------
def evaluate_actor(
    actor: torch.nn.Module, city: City, episodes: int, seed: int, lookahead: int = 6, time_context: bool = False,
    selector: QSelector | None = None, arrivals_now: bool = False,
) -> dict[str, Any]:
    """Deterministic (Dirichlet mean, or Q-guided with ``selector``) evaluation with the same loop
    and JSON as the baselines."""
    from marl_amod.evaluation import evaluate

    was_training = actor.training
    actor.eval()
    try:
        policy = ActorPolicy(actor, city, lookahead, time_context=time_context, selector=selector, arrivals_now=arrivals_now)
        return evaluate(policy, city, episodes, seed)
    finally:
        actor.train(was_training)


class ValidationArgs(Protocol):
    """What validation reads from a run's args (native RunArgs and RLlib's args both have it)."""

    eval_episodes: int
    eval_seed: int
    lookahead: int


@dataclass
class BestActor:
    """The actor with the best validation profit so far: what a run keeps and ships, not the last one."""

    value: float
    state: dict[str, torch.Tensor]

    @classmethod
    def of(cls, actor: torch.nn.Module) -> BestActor:
        """Start from the untrained actor (kept if no validation ever beats -inf)."""
        return cls(-np.inf, copy.deepcopy(actor.state_dict()))

    def validate(self, actor: torch.nn.Module, city: City, args: ValidationArgs) -> float:
        """Mean profit of the deterministic actor on the validation seeds; kept when it is the best yet."""
        time, arrivals = getattr(args, "actor_time", False), getattr(args, "arrivals_now", False)  # RLlib's actors: neither
        val = evaluate_actor(actor, city, args.eval_episodes, args.eval_seed, args.lookahead, time, None, arrivals)["metrics"]["profit"]["mean"]
        if val > self.value:
            self.value, self.state = val, copy.deepcopy(actor.state_dict())
        return val


def crossed(ep: int, step: int, every: int) -> bool:
    """True when going from episode ep - step to ep passed a multiple of ``every``."""
    return ep // every != (ep - step) // every


@dataclass
class EpisodeBook:
    """What A2C and SAC do after each batch of episodes and at the end of the run, in one place:
    validate every ``eval_every`` episodes and at the last one (keeping the best actor and saving
    the resumable state), log, report progress, stop at the time limit; then close the log and
    finish with the best actor's evaluation and card."""

    args: RunArgs
    algorithm: str
    actor: torch.nn.Module
    city: City
    rollout: Rollout | BatchRollout
    log: Logger
    timer: Timer
    best: BestActor
    save: Callable[[], tuple[Path, int]]
    progress: Progress | None = None

    def close(self, ep: int, step: int, stats: dict[str, float]) -> bool:
        """After ``step`` more episodes (``ep`` done): validate if due, log; True when time is up.
        A Ctrl-C pressed during the batch stops the run here, once it is logged (:func:`stop_if_asked`)."""
        args = self.args
        # the batch that runs out of time is validated (and saved) too: the last actor competes, and a run stopped
        # before its first validation does not ship the untrained start
        out_of_time = bool(args.time_limit_s) and self.timer() > args.time_limit_s
        if crossed(ep, step, args.eval_every) or ep >= args.episodes or out_of_time:
            stats["eval/profit"] = self.best.validate(self.actor, self.city, args)
            self.save()
        wall_s = self.timer()
        stats["time/wall_s"] = wall_s
        if self.rollout.env is not None:
            stats["env/clipped_actions"] = self.rollout.clipped  # cumulative; should stay 0
        self.log.log(ep, **stats)
        if self.progress is not None:
            self.progress(ep, args.episodes, stats)
        stop_if_asked()
        return bool(args.time_limit_s) and wall_s > args.time_limit_s

    def finish(self, episodes_done: int, config_path: str | None) -> dict[str, Any]:
        """Close the log and finish the run with the best validation actor (see :func:`finish_run`)."""
        self.log.close()
        self.actor.load_state_dict(self.best.state)
        return finish_run(self.args, self.algorithm, self.actor, self.city, self.timer(), episodes_done, config_path)


def warm_start(actor: torch.nn.Module, args: RunArgs, city: City) -> None:
    """Load ``args.init_actor``'s weights into ``actor`` (a fresh run only; resume restores its own)."""
    if not args.init_actor:
        return
    from marl_amod.checkpoints import load_actor

    source, card = load_actor(args.init_actor, city)
    features = (card["lookahead"], bool(card.get("arrivals_now")))
    if features != (args.lookahead, args.arrivals_now):  # other columns: the weights would read the wrong ones, if they fit at all
        raise DataError(
            f"init_actor {args.init_actor} reads the features of lookahead {features[0]}, arrivals_now {features[1]}; this run's are "
            f"lookahead {args.lookahead}, arrivals_now {args.arrivals_now} (set both to match)"
        )
    theirs, ours = source.state_dict(), actor.state_dict()
    if set(theirs) != set(ours) or any(theirs[k].shape != ours[k].shape for k in ours):
        raise DataError(
            f"init_actor {args.init_actor} is a {card['actor']}/{card['conv']} actor with hidden {card['hidden']}, "
            f"readout {card.get('readout') or 'none'}, agent_id {bool(card.get('agent_id'))}, "
            f"standardise_inputs {bool(card.get('standardise_inputs'))}; this run's actor differs "
            "(set actor, conv, hidden, readout, agent_id and standardise_inputs to match)"
        )
    actor.load_state_dict(theirs)


# --------------------------------------------------------------------------------------------
# Training state (resume) and interrupts
# --------------------------------------------------------------------------------------------
STATE_FORMAT = "marl_amod.train_state/1"


_M_TOP_PAD, _M_MMAP_THRESHOLD = -2, -3  # glibc mallopt parameters (malloc.h)


def retain_freed_memory(pad_bytes: int = 64 << 20, mmap_threshold: int = 32 << 20) -> bool:
    """Ask glibc to keep freed heap memory for reuse instead of returning it to the OS.

    A gradient update on the batched path allocates and frees megabytes of activations; by
    default glibc gives some of them back and the next update faults the pages in again (about
    2,000 minor page faults per SAC update at 256 hidden units, 10-15% of its time here). Blocks
    under ``mmap_threshold`` then come from the heap, and ``pad_bytes`` of free heap are kept.
    A process-wide setting, so only trainers call it (a training process owns its memory);
    returns False where the C library is not glibc (nothing changes).
    """
    try:
        mallopt = ctypes.CDLL(None).mallopt  # the C library the interpreter runs on
    except (OSError, AttributeError):  # not glibc (macOS, Windows, musl has no mallopt)
        return False
    # the threshold first: setting either fixes it, and glibc's default (128 KiB) would put every
    # large activation in its own freshly faulted mapping
    return bool(mallopt(_M_MMAP_THRESHOLD, mmap_threshold)) and bool(mallopt(_M_TOP_PAD, pad_bytes))


def seed_everything(seed: int) -> None:
    np.random.seed(seed)
    torch.manual_seed(seed)


def state_path(args: CommonArgs) -> Path:
    return Path(args.run_dir) / "state.pt"


# what a resumed run may change: how long it runs, how and where it validates, reports and writes; any other
# key would make the resumed run another run than the one its state began (another scenario, seed, rate, ...)
RESUMABLE_CHANGES = frozenset({
    "episodes", "updates", "stop_after", "time_limit_s", "eval_every", "eval_episodes", "eval_seed", "final_eval_episodes",
    "final_eval_seed", "keep", "threads", "run_dir", "policy_out", "demos",
})  # fmt: skip


def save_state(path: str | Path, args: RunArgs, **state: Any) -> Path:
    """Full training state (networks, optimisers, buffers, RNGs, and the run's args) for ``--resume``, written atomically."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    rng = {"torch": torch.get_rng_state(), "numpy": np.random.get_state()}
    return torch_save(path, {"format": STATE_FORMAT, "rng": rng, "args": args.model_dump(mode="json"), **state})


def check_same_run(path: str | Path, saved: dict[str, Any] | None, args: RunArgs) -> None:
    """Refuse to resume a state under args that make it another run (:data:`RESUMABLE_CHANGES` may differ)."""
    if not saved:  # states of before the args were saved
        return
    now = args.model_dump(mode="json")
    changed = [k for k in sorted(set(saved) | set(now)) if k not in RESUMABLE_CHANGES and saved.get(k) != now.get(k)]
    if changed:
        said = "; ".join(f"{k}: {saved.get(k)!r} -> {now.get(k)!r}" for k in changed)
        raise DataError(f"{path} was saved by a run with other settings ({said}): resume it with the config that began it "
                        f"(only {', '.join(sorted(RESUMABLE_CHANGES))} may change), or start a fresh run")  # fmt: skip


def load_state(path: str | Path, algorithm: str, args: RunArgs) -> dict[str, Any]:
    """A training state written by :func:`save_state` for ``algorithm`` and, as far as the run goes, these
    ``args`` (:func:`check_same_run`); global RNGs restored."""
    path = Path(path)
    check_torch_file(path, "training state")
    try:
        state = torch.load(path, map_location="cpu", weights_only=False)
    except Exception as exc:  # noqa: BLE001 - every unreadable file means the same to the user
        raise DataError(f"{path} cannot be read as a training state (empty, truncated or damaged?): {str(exc).splitlines()[0] if str(exc) else type(exc).__name__}") from None
    if not isinstance(state, dict) or "episode" not in state:
        raise DataError(f"{path} is not a marl_amod training state (a policy file? resume takes runs/<run>/state.pt)")
    if state.get("algorithm", algorithm) != algorithm:
        raise DataError(f"{path} is a {state['algorithm']} training state; this config trains {algorithm}")
    check_same_run(path, state.get("args"), args)
    if "rng" in state:
        torch.set_rng_state(state["rng"]["torch"])
        np.random.set_state(state["rng"]["numpy"])
    return state


def load_error(exc: Exception) -> str:
    """What a failed ``load_state_dict`` says, on one line: its first mismatches, without torch's header line
    ("Error(s) in loading state_dict for X:", which names only the class)."""
    lines = [line.strip() for line in str(exc).strip().splitlines()]
    return " ".join(lines[1:3]) or (lines[0] if lines else type(exc).__name__)


def restore(path: str | Path, state: dict[str, Any], **parts: Any) -> None:
    """Load each network or optimiser of ``parts`` from ``state[name]``. A state saved by a run of another
    architecture (conv, width, actor kind) is a DataError naming the file, not torch's key listing."""
    for name, part in parts.items():
        try:
            part.load_state_dict(state[name])
        except (RuntimeError, ValueError, KeyError) as exc:  # missing or unexpected keys, shapes, parameter groups
            raise DataError(f"{path} was saved by a run whose {name} differs from this config's (another conv, width or actor?): "
                            f"{load_error(exc)}; resume with the config that made it") from None  # fmt: skip


INTERRUPTED = "INTERRUPTED"  # in a run folder: the episode a Ctrl-C saved the state at, until a run resumes it


def check_not_interrupted(run_dir: str | Path, resume: str | None) -> None:
    """A run folder holding an interrupted run is resumed (its marker cleared) or refused: a fresh run
    there would overwrite the saved state and the log without a word."""
    marker = Path(run_dir) / INTERRUPTED
    if not marker.is_file():
        return
    if resume is None:
        episode = marker.read_text().strip()
        raise ConfigError(f"{run_dir} holds a run interrupted at episode {episode}: continue it with --resume "
                          f"{Path(run_dir) / 'state.pt'}, or remove {run_dir} (or give another run_dir) to start over")  # fmt: skip
    marker.unlink()


class TrainingInterrupted(MarlAmodError):
    """Ctrl-C during training; the state of the last finished update is saved at ``path``."""

    def __init__(self, path: Path, episode: int) -> None:
        self.path, self.episode = path, episode
        super().__init__(f"interrupted: training state of episode {episode} saved to {path}; resume with --resume {path}")


_STOP_ASKED = False  # a Ctrl-C arrived during an update; the loop stops after it (stop_if_asked)


def stop_if_asked() -> None:
    """Where an update has finished: stop here if Ctrl-C was pressed during it. Why: a state saved in the
    middle of an episode holds that episode's transitions, updates and random draws, and the resumed run,
    which replays the episode from its start, would not be the uninterrupted run."""
    global _STOP_ASKED
    if _STOP_ASKED:
        _STOP_ASKED = False
        raise KeyboardInterrupt


@contextlib.contextmanager
def _stop_after_the_update() -> Iterator[None]:
    """SIGINT marks the stop instead of raising (in the main thread; a second Ctrl-C raises at once)."""
    import signal
    import threading

    global _STOP_ASKED
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def ask(signum: int, frame: Any) -> None:
        global _STOP_ASKED
        if _STOP_ASKED:
            raise KeyboardInterrupt
        _STOP_ASKED = True

    _STOP_ASKED = False
    previous = signal.signal(signal.SIGINT, ask)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)
        _STOP_ASKED = False


@contextlib.contextmanager
def interruptible(save: Callable[[], tuple[Path, int]]) -> Iterator[None]:
    """Turn Ctrl-C inside the block into a saved state and :class:`TrainingInterrupted`.

    ``save`` writes the state of the last finished update and returns (path, episode); the loop
    calls :func:`stop_if_asked` after each update, so that is where a first Ctrl-C stops it.
    """
    try:
        with _stop_after_the_update():
            yield
    except KeyboardInterrupt:
        path, episode = save()
        atomic_write(path.parent / INTERRUPTED, f"{episode}\n")  # a later fresh run in this folder would erase the state: refused
        raise TrainingInterrupted(path, episode) from None


# --------------------------------------------------------------------------------------------
# The end of a run: final evaluation and the policy card
# --------------------------------------------------------------------------------------------
@dataclass
class CriticSpec:
    """A twin Q critic that ships in the policy file beside the actor (IQL, CQL): its weights,
    what rebuilds it (n_features, hidden, conv: the card's ``critic``), and the ``selection`` the
    policy plays with (None: the Dirichlet mean), applied to the final evaluation too."""

    critic: torch.nn.Module
    card: dict[str, Any]
    selection: Selection | None = None


def finish_run(
    args: RunArgs, algorithm: str, actor: torch.nn.Module, city: City, wall_s: float, episodes_done: int, config_path: str | None = None,
    extra: dict[str, Any] | None = None, critic: CriticSpec | None = None,
) -> dict[str, Any]:
    """Final evaluation on the report seeds, then the policy file and its card (written once);
    ``extra`` adds algorithm-specific card fields (an offline run's dataset); ``critic`` ships a
    Q critic in the file (and its selection, which the final evaluation then plays)."""
    selector = None
    if critic is not None and critic.selection is not None and critic.selection.candidates:
        selector = QSelector(critic.critic, city, critic.selection)
    result = evaluate_actor(actor, city, args.final_eval_episodes, args.final_eval_seed, args.lookahead, args.actor_time, selector, args.arrivals_now)
    profit = result["metrics"]["profit"]
    card = make_card(
        scenario=city.name, n_regions=city.n_regions, algorithm=algorithm, mode=args.mode,
        actor="local" if args.mode == "decentralised" else args.actor,
        conv="sage" if args.mode == "decentralised" else args.conv, readout=None if args.readout == "none" else args.readout,
        agent_id=args.agent_id or None, standardise_inputs=args.standardise_inputs or None,
        hidden=args.hidden, n_features=run_features(args), lookahead=args.lookahead, seed=args.seed, time_context=args.actor_time,
        arrivals_now=args.arrivals_now or None,
        episodes_trained=episodes_done, eval_episodes=args.final_eval_episodes, eval_seed=args.final_eval_seed,
        profit_mean=profit["mean"], profit_std=profit["std"], served_demand_mean=result["metrics"]["served_demand"]["mean"],
        training_wall_s=round(wall_s, 1), torch_threads=torch.get_num_threads(),
        config=config_path, args=args.model_dump(mode="json"), **(extra or {}),
        # which start it was trained from, by content (a retrained start makes this policy stale)
        **({"start_sha256": file_sha256(args.init_actor)} if args.init_actor and Path(args.init_actor).is_file() else {}),
        **({} if critic is None else {"critic": critic.card, "selection": critic.selection}),
    ).to_dict()
    summary: dict[str, Any] = {"card": card, "result": result}
    if args.policy_out:
        summary["policy"] = str(save_policy(args.policy_out, actor, card, None if critic is None else critic.critic))
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    write_json(run_dir / "final_eval.json", result)
    return summary
