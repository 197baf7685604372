"""Env throughput with random actions: the single ParallelEnv, FleetSystem and the batched env.

Prints a markdown table per scenario, in env steps per second (one env step = one control step
of one episode, every region acting; a batch of B episodes stepping once counts B):

* ``parallel``: a plain loop over the PettingZoo ParallelEnv with actions from its spaces;
* ``aec``: ``pettingzoo.test.performance_benchmark``'s loop over the AEC env (cycles per second);
* ``system``: FleetSystem alone (Dirichlet targets, no observations);
* ``batch B``: ``marl_amod.vector_env(num_envs=B)`` with uniform random actions (B, N);
* ``stay B``: the batched env at the largest B with all-zero actions ("stay": no rebalancing to
  solve), i.e. the batched machinery without the per-episode min-cost flows;
* ``step ms``: median milliseconds of one ParallelEnv.step.

Run on one core:  python benchmarks/env_speed.py [--seconds 2] [--scenarios nyc_brooklyn synthetic]
(sets OMP/MKL/OpenBLAS threads and torch threads to 1 before numpy loads).
"""

from __future__ import annotations

import argparse
import os
import statistics
import time
from collections.abc import Callable

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ.setdefault(_var, "1")

import numpy as np  # noqa: E402

import marl_amod  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402

BATCHES = (1, 16, 64, 256)
MEMORY_LIMIT = 2e9  # bytes of drawn demand a batch may hold; larger batches are skipped


def rate(step: Callable[[], int], seconds: float) -> float:
    """Env steps per second of ``step`` (which returns how many env steps it made), after a warm-up."""
    end = time.perf_counter() + seconds / 4
    while time.perf_counter() < end:  # warm-up: fills per-step caches, as any run does
        step()
    count, start = 0, time.perf_counter()
    while time.perf_counter() - start < seconds:
        count += step()
    return count / (time.perf_counter() - start)


def parallel_loop(scenario: str, seconds: float) -> tuple[float, float]:
    """Steps/s of a plain ParallelEnv loop and the median ms of one step."""
    env = marl_amod.parallel_env(scenario)
    env.reset(seed=0)
    times: list[float] = []

    def step() -> int:
        if not env.agents:
            env.reset()
        actions = {a: env.action_space(a).sample() for a in env.agents}
        t0 = time.perf_counter()
        env.step(actions)
        times.append(time.perf_counter() - t0)
        return 1

    steps = rate(step, seconds)
    return steps, statistics.median(times) * 1e3


def aec_loop(scenario: str, seconds: float) -> float:
    """pettingzoo.test.performance_benchmark's loop (one cycle = every agent acts once), timed here."""
    env = marl_amod.env(scenario)
    env.reset(seed=0)

    def cycle() -> int:
        for agent in env.agent_iter(env.num_agents):
            obs, reward, termination, truncation, info = env.last()
            env.step(None if termination or truncation else env.action_space(agent).sample())
            if all(env.terminations.values()) or all(env.truncations.values()):
                env.reset()
        return 1

    return rate(cycle, seconds)


def system_loop(scenario: str, seconds: float) -> float:
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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenarios", nargs="+", default=["nyc_brooklyn", "synthetic", "synthetic_large"])
    parser.add_argument("--seconds", type=float, default=2.0, help="timed seconds per cell")
    args = parser.parse_args()
    try:
        import torch

        torch.set_num_threads(1)
    except ImportError:  # pragma: no cover - torch is a core dependency today
        pass
    batch_cols = " | ".join(f"batch {b}" for b in BATCHES)
    print(f"| scenario | regions | parallel | aec | system | {batch_cols} | stay B | step ms |")
    print("|---|---:|---:|---:|---:|" + "---:|" * len(BATCHES) + "---:|---:|")
    for scenario in args.scenarios:
        city = load_city(scenario)
        per_episode = city.demand_rate[: city.horizon].size * 8  # the batch keeps each episode's drawn demand
        parallel, step_ms = parallel_loop(scenario, args.seconds)
        aec = aec_loop(scenario, args.seconds)
        system = system_loop(scenario, args.seconds)
        cells = []
        for b in BATCHES:
            if b * per_episode > MEMORY_LIMIT:
                cells.append("-")
            else:
                cells.append(f"{batch_loop(scenario, b, args.seconds):,.0f}")
        largest = max(b for b in BATCHES if b == 1 or b * per_episode <= MEMORY_LIMIT)
        cells.append(f"{batch_loop(scenario, largest, args.seconds, stay=True):,.0f} (B={largest})")
        print(
            f"| {scenario} | {city.n_regions} | {parallel:,.0f} | {aec:,.0f} | {system:,.0f} | "
            + " | ".join(cells)
            + f" | {step_ms:.3f} |",
            flush=True,
        )


if __name__ == "__main__":
    main()
