"""Several training runs side by side, one process each: an ensemble of training seeds in one command.

Why: the tables' meta-policy is two training runs of one recipe averaged (:mod:`marl_amod.ensemble`),
and the issue's 60-minute budget is their wall time together on a 2-core machine, one core each.
By hand that is two background ``marl-amod train`` commands, a wait, and ``marl-amod ensemble``;
``marl-amod train-ensemble`` runs the members here, at most ``jobs`` at once, and then writes the
ensemble, so the time it reports is what a user pays.

Each member is ``marl-amod train --config C`` in a process of its own (its output in
``<run_dir>/train.log``): processes, not threads, because each run sets its own torch threads
(``threads``, 1 by default) and owns its simulator. The children get a session of their own, so a
Ctrl-C reaches them once, from here, and each saves its training state as ``marl-amod train`` does;
``resume`` then picks every member up where it stopped.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

from marl_amod.errors import ConfigError

POLL_S = 2.0  # how often the children are checked and the progress read


@dataclass(frozen=True)
class Member:
    """One training config of the ensemble, validated, with where its run writes."""

    config: Path
    algo: str
    run_dir: Path
    policy_out: Path
    total: int
    """the updates (or episodes) the run is set to reach: what its progress counts to"""

    @property
    def state(self) -> Path:
        return self.run_dir / "state.pt"

    @property
    def log(self) -> Path:
        return self.run_dir / "train.log"

    def trained_by_this_config(self) -> bool:
        """Whether its policy exists and its card names this very config (what ``resume`` keeps)."""
        from marl_amod.data import read_json

        card = self.policy_out.with_suffix(".json")
        if not (self.policy_out.is_file() and card.is_file()):
            return False
        made_by = read_json(card).get("config")
        return made_by is not None and Path(made_by).resolve() == self.config.resolve()

    def progress(self, since: float) -> int:
        """The last update (or episode) its ``log.csv`` holds, 0 before the run has written one after ``since``
        (a log of an earlier run in the same folder is not this run's progress)."""
        path = self.run_dir / "log.csv"
        try:
            if path.stat().st_mtime < since:
                return 0
            with path.open("rb") as fh:
                fh.seek(max(fh.seek(0, os.SEEK_END) - 4096, 0))
                text = fh.read().decode("utf-8", "replace")
        except OSError:
            return 0
        lines = text.split("\n")[1:-1]  # whole lines only: the chunk's first may be cut, its last still being written
        for line in reversed(lines):
            head = line.split(",", 1)[0]
            if head.isdigit():
                return int(head)
        return 0


@dataclass(frozen=True)
class Outcome:
    member: Member
    returncode: int
    wall_s: float
    kept: bool = False
    """trained before by this config and kept (``resume``): nothing ran"""

    @property
    def ok(self) -> bool:
        return self.returncode == 0


def plan(configs: Sequence[str | Path]) -> list[Member]:
    """The members, every config validated before any run starts: each must write a policy
    (``policy_out``), and no two may share a path they write to (``RunArgs.outputs``: the run
    folder, the policy file, meta-bc's demonstrations folder), or one run would overwrite the other's."""
    from marl_amod.algos.common import check_separate_outputs
    from marl_amod.algos.registry import load_train_config
    from marl_amod.files import check_destination
    from marl_amod.scenario import load_spec
    from marl_amod.scenario.variants import base_city

    if len(configs) < 2:
        raise ConfigError(f"an ensemble takes two or more training configs, got {len(configs)}")
    loaded = [(config, *load_train_config(config)) for config in map(Path, configs)]
    for config, _, args in loaded:
        for scenario in (args.scenario, *getattr(args, "cities", [])):  # here, not in a member's process
            try:
                load_spec(base_city(scenario))
            except ConfigError as exc:
                raise ConfigError(f"{config}: {exc}") from None
        if not args.policy_out:
            raise ConfigError(f"{config}: policy_out is empty, so the run would write no policy to put in the ensemble")
        check_destination(args.policy_out, what=f"{config}: policy_out")  # now, not when that member's run ends
    check_separate_outputs((str(config), args) for config, _, args in loaded)
    return [Member(config, algo, Path(args.run_dir), Path(args.policy_out), args.run_length()) for config, algo, args in loaded]


def train_side_by_side(
    members: Sequence[Member], jobs: int, resume: bool = False, on_tick: Callable[[dict[Member, tuple[str, int]]], None] | None = None
) -> list[Outcome]:
    """Train every member, at most ``jobs`` at once; returns their outcomes in the members' order.

    ``resume``: a member whose policy this config already made is kept, one with a training state
    resumes from it, the rest start afresh. ``on_tick`` gets, every few seconds, each member's
    status (waiting, running, done, failed, kept) and its progress in updates (or episodes).
    On KeyboardInterrupt every running child is asked to stop (SIGINT: it saves its state) and
    waited for, and the interrupt is raised again."""
    if jobs < 1:
        raise ConfigError(f"jobs must be at least 1, got {jobs}")
    outcomes: dict[Member, Outcome] = {}
    if resume:
        outcomes |= {m: Outcome(m, 0, 0.0, kept=True) for m in members if m.trained_by_this_config()}
    waiting = [m for m in members if m not in outcomes]
    running: dict[Member, tuple[subprocess.Popen, float]] = {}

    def status() -> dict[Member, tuple[str, int]]:
        out = {}
        for m in members:
            if m in running:
                out[m] = ("running", m.progress(running[m][1]))
            elif m in outcomes:
                o = outcomes[m]
                out[m] = ("kept" if o.kept else "done" if o.ok else "failed", m.total if o.ok else 0)
            else:
                out[m] = ("waiting", 0)
        return out

    def stop(signum: int, frame: object) -> None:  # a kill (SIGTERM) stops the children as a Ctrl-C does, not orphans them
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, stop) if threading.current_thread() is threading.main_thread() else None
    try:
        while waiting or running:
            while waiting and len(running) < jobs:
                m = waiting.pop(0)
                running[m] = (_start(m, resume and m.state.is_file()), time.time())
            for m, (child, started) in list(running.items()):
                if (code := child.poll()) is not None:
                    outcomes[m] = Outcome(m, code, time.time() - started)
                    del running[m]
            if on_tick is not None:
                on_tick(status())
            if running:
                time.sleep(POLL_S)
    except KeyboardInterrupt:
        for child, _ in running.values():
            child.send_signal(signal.SIGINT)
        for child, _ in running.values():
            child.wait()
        raise
    finally:
        if previous is not None:
            signal.signal(signal.SIGTERM, previous)
    return [outcomes[m] for m in members]


def _start(member: Member, from_state: bool) -> subprocess.Popen:
    """``marl-amod train`` for ``member`` in a process and session of its own, its output to its log."""
    member.run_dir.mkdir(parents=True, exist_ok=True)
    command = [sys.executable, "-m", "marl_amod", "train", "--config", str(member.config)]
    if from_state:
        command += ["--resume", str(member.state)]
    with member.log.open("a" if from_state else "w") as log:  # resumed: after the stopped run's lines; the child holds its own handle
        return subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, start_new_session=True)
