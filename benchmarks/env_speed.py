"""Env throughput with random actions: the single ParallelEnv, FleetSystem and the batched env.

Prints a markdown table per scenario, in env steps per second (one env step = one control step
of one episode, every region acting; a batch of B episodes stepping once counts B):

* ``parallel``: a plain loop over the PettingZoo ParallelEnv with actions from its spaces;
* ``aec``: ``pettingzoo.test.performance_benchmark`` itself on the AEC env (its own 5-second
  loop; the cycles per second it prints, one cycle = every agent acts once = one env step);
* ``system``: FleetSystem alone (Dirichlet targets, no observations);
* ``batch B``: ``marl_amod.vector_env(num_envs=B)`` with uniform random actions (B, N);
* ``stay B``: the batched env at the largest B with all-zero actions ("stay": no rebalancing to
  solve), i.e. the batched machinery without the per-episode min-cost flows;
* ``step ms``: median milliseconds of one ParallelEnv.step.

Times are this process's CPU time by default (``--clock cpu``): on a shared machine the time other
jobs hold the core does not count, so the numbers are those of one core; ``--clock wall`` measures
elapsed time. ``performance_benchmark`` keeps its own wall clock.

With ``--ref <git ref> [<git ref> ...]`` every scenario is measured side by side: with each ref's
``marl_amod`` (``git archive`` into a temporary folder) and with this tree's, each in a fresh
subprocess, one after another, so a change of machine load affects all alike; a second table gives
this tree's numbers as ratios to each ref's (steps/s: new / ref, higher is faster; step ms:
new / ref, lower is faster), the comparison that holds on a loaded machine. ``--json`` writes
every number, the tables, the load average before and after, and the CPU model.

Run on one core:  python benchmarks/env_speed.py [--seconds 2] [--scenarios nyc_brooklyn synthetic]
    [--ref 2c22f5a main] [--json docs/results/env_speed.json]
(sets OMP/MKL/OpenBLAS threads and torch threads to 1 before numpy loads).
"""

from __future__ import annotations

import argparse
import contextlib
import io
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

BATCHES = (1, 16, 64, 256)
MEMORY_LIMIT = 2e9  # bytes of drawn demand a batch may hold; larger batches are skipped
ROOT = Path(__file__).resolve().parents[1]
CLOCKS = {"cpu": time.process_time, "wall": time.perf_counter}
clock = CLOCKS["cpu"]  # this process's CPU seconds: on a shared machine, time taken by others does not count


def rate(step: Callable[[], int], seconds: float) -> float:
    """Env steps per second of ``step`` (which returns how many env steps it made), after a warm-up."""
    end = clock() + seconds / 4
    while clock() < end:  # warm-up: fills per-step caches, as any run does
        step()
    count, start = 0, clock()
    while clock() - start < seconds:
        count += step()
    return count / (clock() - start)


def parallel_loop(scenario: str, seconds: float) -> tuple[float, float]:
    """Steps/s of a plain ParallelEnv loop and the median ms of one step."""
    import marl_amod

    env = marl_amod.parallel_env(scenario)
    env.reset(seed=0)
    times: list[float] = []

    def step() -> int:
        if not env.agents:
            env.reset()
        actions = {a: env.action_space(a).sample() for a in env.agents}
        t0 = clock()
        env.step(actions)
        times.append(clock() - t0)
        return 1

    steps = rate(step, seconds)
    return steps, statistics.median(times) * 1e3


def aec_benchmark(scenario: str) -> float:
    """Cycles per second printed by ``pettingzoo.test.performance_benchmark`` on the AEC env."""
    from pettingzoo.test import performance_benchmark

    import marl_amod

    env = marl_amod.env(scenario)
    env.reset(seed=0)
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        performance_benchmark(env)
    found = re.search(r"([0-9.eE+-]+) cycles per second", out.getvalue())
    if found is None:
        raise RuntimeError(f"performance_benchmark printed no cycle rate:\n{out.getvalue()}")
    return float(found.group(1))


def system_loop(scenario: str, seconds: float) -> float:
    from marl_amod.scenario import load_city
    from marl_amod.system import FleetSystem

    city = load_city(scenario)
    system = FleetSystem(city)
    rng = np.random.default_rng(0)
    system.reset(0)

    def step() -> int:
        if system.done:
            system.reset()
        system.step(system.targets_from_weights(rng.dirichlet(np.ones(city.n_regions))))
        return 1

    return rate(step, seconds)


def batch_loop(scenario: str, b: int, seconds: float, stay: bool = False) -> float:
    import marl_amod

    venv = marl_amod.vector_env(scenario, num_envs=b)
    rng = np.random.default_rng(0)
    venv.reset(seed=0)

    def step() -> int:
        actions = rng.random((b, venv.num_agents), dtype=np.float32) * (not stay)
        *_, trunc, _ = venv.step(actions)
        if trunc.all():
            venv.reset()
        return b

    return rate(step, seconds)


def measure(scenario: str, seconds: float) -> dict[str, Any]:
    """Every column of one scenario's row, with the ``marl_amod`` this process imports."""
    import torch

    from marl_amod.scenario import load_city

    torch.set_num_threads(1)
    city = load_city(scenario)
    per_episode = city.demand_rate[: city.horizon].size * 8  # the batch keeps each episode's drawn demand
    fits = [b for b in BATCHES if b == 1 or b * per_episode <= MEMORY_LIMIT]
    parallel, step_ms = parallel_loop(scenario, seconds)
    row: dict[str, Any] = {"regions": city.n_regions, "parallel": parallel, "aec": aec_benchmark(scenario)}
    row["system"] = system_loop(scenario, seconds)
    row["batch"] = {str(b): batch_loop(scenario, b, seconds) if b in fits else None for b in BATCHES}
    row["stay_b"] = max(fits)
    row["stay"] = batch_loop(scenario, row["stay_b"], seconds, stay=True)
    row["step_ms"] = step_ms
    return row


def measure_in(tree: Path, scenario: str, seconds: float, clock_name: str) -> dict[str, Any]:
    """:func:`measure` in a fresh subprocess that imports ``marl_amod`` from ``tree``."""
    env = {**os.environ, "PYTHONPATH": str(tree)}
    spec = json.dumps({"scenario": scenario, "seconds": seconds, "clock": clock_name})
    out = subprocess.run(
        [sys.executable, str(Path(__file__).resolve()), "--worker", spec],
        env=env, capture_output=True, text=True, cwd=tree, check=False,
    )
    if out.returncode != 0:
        raise RuntimeError(f"worker failed in {tree} for {scenario}:\n{out.stderr[-3000:]}")
    return json.loads(out.stdout.strip().splitlines()[-1])


def header() -> str:
    batch_cols = " | ".join(f"batch {b}" for b in BATCHES)
    return (
        f"| scenario | regions | tree | parallel | aec | system | {batch_cols} | stay B | step ms |\n"
        "|---|---:|---|---:|---:|---:|" + "---:|" * len(BATCHES) + "---:|---:|"
    )


def table_row(scenario: str, tree: str, row: dict[str, Any]) -> str:
    batches = " | ".join("–" if row["batch"][str(b)] is None else f"{row['batch'][str(b)]:,.0f}" for b in BATCHES)
    return (
        f"| {scenario} | {row['regions']} | {tree} | {row['parallel']:,.0f} | {row['aec']:,.0f} | {row['system']:,.0f} | "
        f"{batches} | {row['stay']:,.0f} (B={row['stay_b']}) | {row['step_ms']:.3f} |"
    )


def cpu_model() -> str:
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["nyc_brooklyn", "synthetic", "synthetic_large"])
    parser.add_argument("--seconds", type=float, default=2.0, help="timed seconds per cell")
    parser.add_argument("--ref", nargs="+", default=[], help="git refs to measure side by side with this tree")
    parser.add_argument("--json", type=Path, default=None, help="write the measurements and table here")
    parser.add_argument("--clock", choices=list(CLOCKS), default="cpu", help="cpu: this process's CPU time (default); wall: elapsed time")
    parser.add_argument("--worker", help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.worker:
        spec = json.loads(args.worker)
        global clock
        clock = CLOCKS[spec["clock"]]
        print(json.dumps(measure(spec["scenario"], spec["seconds"])))
        return

    load_before = os.getloadavg()
    lines, rows = [header()], []
    print(lines[0], flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        trees: list[tuple[str, Path]] = []
        commits: dict[str, str] = {}
        if args.ref:
            sys.path.insert(0, str(ROOT / "benchmarks"))
            from train_speed import export_ref

            for k, ref in enumerate(args.ref):
                (Path(tmp) / str(k)).mkdir()
                commits[ref] = export_ref(ref, Path(tmp) / str(k))
                trees.append((ref, Path(tmp) / str(k) / "tree"))
        trees.append(("new" if args.ref else "this", ROOT))
        for scenario in args.scenarios:
            for name, tree in trees:
                row = measure_in(tree, scenario, args.seconds, args.clock)
                rows.append({"scenario": scenario, "tree": name, **row})
                lines.append(table_row(scenario, name, row))
                print(lines[-1], flush=True)
            if args.json:  # after every scenario, so an interrupted run keeps what it measured
                write_json(args, commits, load_before, rows, lines)
    if args.ref:
        print("\n" + ratio_table(rows, args.ref), flush=True)


RATIO_COLUMNS = ("parallel", "aec", "system", "stay", "step_ms")


def ratio_table(rows: list[dict[str, Any]], refs: list[str]) -> str:
    """This tree's numbers divided by each ref's, per scenario (step ms: below 1 is faster)."""
    batch_cols = " | ".join(f"batch {b}" for b in BATCHES)
    lines = [
        f"| scenario | new / ref | parallel | aec | system | {batch_cols} | no rebalancing | step ms |",
        "|---|---|" + "---:|" * (len(RATIO_COLUMNS) + len(BATCHES)),
    ]
    by = {(r["scenario"], r["tree"]): r for r in rows}
    for scenario in dict.fromkeys(r["scenario"] for r in rows):
        new = by.get((scenario, "new"))
        for ref in refs:
            old = by.get((scenario, ref))
            if new is None or old is None:
                continue
            ratio = {key: new[key] / old[key] for key in RATIO_COLUMNS}
            batches = " | ".join(
                "–" if old["batch"][str(b)] is None or new["batch"][str(b)] is None
                else f"{new['batch'][str(b)] / old['batch'][str(b)]:.2f}" for b in BATCHES
            )
            lines.append(
                f"| {scenario} | new / {ref} | {ratio['parallel']:.2f} | {ratio['aec']:.2f} | {ratio['system']:.2f} | {batches} "
                f"| {ratio['stay']:.2f} | {ratio['step_ms']:.2f} |"
            )
    return "\n".join(lines)


def write_json(args: argparse.Namespace, commits: dict[str, str], load_before: tuple, rows: list, lines: list[str]) -> None:
    """Every measurement so far, the table, the machine and its load, written atomically."""
    head = subprocess.run(["git", "-C", str(ROOT), "rev-parse", "HEAD"], capture_output=True, text=True).stdout.strip()
    status = ["git", "-C", str(ROOT), "status", "--porcelain", "--untracked-files=no", "--", ".", f":(exclude){args.json.resolve()}"]
    dirty = bool(subprocess.run(status, capture_output=True, text=True).stdout.strip())  # the output file itself does not count
    result = {
        "refs": commits, "commit": head, "dirty": dirty, "seconds": args.seconds,
        "clock": args.clock, "threads": 1, "cpu": cpu_model(), "python": platform.python_version(), "numpy": np.__version__,
        "load_average_before": load_before, "load_average_after": os.getloadavg(), "rows": rows, "markdown": "\n".join(lines),
        "ratios_markdown": ratio_table(rows, args.ref) if args.ref else None,
    }
    args.json.parent.mkdir(parents=True, exist_ok=True)
    part = args.json.with_suffix(".part")
    part.write_text(json.dumps(result, indent=2) + "\n")
    os.replace(part, args.json)


if __name__ == "__main__":
    main()
