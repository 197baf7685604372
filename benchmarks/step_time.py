"""Simulator step time (dispatch + rebalancing + bookkeeping), fast solvers vs the cvxpy path.

Prints a markdown table: per scenario, median milliseconds per control step with the fast path
(greedy dispatch + OR-Tools min-cost flow) and with the cvxpy/HiGHS path, and their ratio.
Targets come from random Dirichlet weights, so every step has real rebalancing to solve.
Run on one core:  OMP_NUM_THREADS=1 python benchmarks/step_time.py [--real] [--output t.json]
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from marl_amod.scenario import City, grid_city, load_city  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402

SYNTHETIC = [(4, 4), (5, 10), (10, 10), (10, 20), (20, 20)]
REAL = ["nyc_brooklyn", "san_francisco", "shenzhen_downtown_west", "washington_dc", "shenzhen_north", "chicago"]


def time_steps(city: City, solver: str, max_steps: int, warmup_episode: bool) -> dict[str, float]:
    """Median ms per step of the whole step and of its two solves."""
    system = FleetSystem(city, solver=solver)
    rng = np.random.default_rng(0)
    if warmup_episode:  # fills the per-step margin-order cache, as in any training run
        system.reset(1)
        while not system.done:
            system.step(system.targets_from_weights(rng.dirichlet(np.ones(city.n_regions))))
    system.reset(0)
    step_ms, reb_ms, disp_ms = [], [], []
    coord = system.coordinator
    while not system.done and len(step_ms) < max_steps:
        target = system.targets_from_weights(rng.dirichlet(np.ones(city.n_regions)))
        idle = system.sim.idle.copy()
        t0 = time.perf_counter()
        coord.rebalance(idle, target)
        t1 = time.perf_counter()
        coord.dispatch(idle, system.sim.requests(), system.t)
        t2 = time.perf_counter()
        system.step(target)
        t3 = time.perf_counter()
        reb_ms.append((t1 - t0) * 1e3)
        disp_ms.append((t2 - t1) * 1e3)
        step_ms.append((t3 - t2) * 1e3)
    med = statistics.median
    return {"step": med(step_ms), "dispatch": med(disp_ms), "rebalance": med(reb_ms), "steps": len(step_ms)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--real", action="store_true", help="also time the real cities (needs MARL_AMOD_DATA)")
    parser.add_argument("--cvxpy-steps", type=int, default=5, help="steps timed on the slow path")
    parser.add_argument("--output", help="write the rows as JSON")
    args = parser.parse_args()
    cities = [grid_city(r, c, seed=0) for r, c in SYNTHETIC]
    if args.real:
        cities += [load_city(name) for name in REAL]
    rows = []
    print("| scenario | regions | fast step ms | dispatch ms | rebalance ms | cvxpy step ms | cvxpy / fast |")
    print("|---|---:|---:|---:|---:|---:|---:|")
    for city in cities:
        fast = time_steps(city, "fast", 10_000, warmup_episode=True)
        slow = time_steps(city, "cvxpy", args.cvxpy_steps, warmup_episode=False)
        ratio = slow["step"] / fast["step"]
        rows.append({"scenario": city.name, "regions": city.n_regions, "fast": fast, "cvxpy": slow, "ratio": ratio})
        print(
            f"| {city.name} | {city.n_regions} | {fast['step']:.2f} | {fast['dispatch']:.2f} | {fast['rebalance']:.2f} "
            f"| {slow['step']:.1f} | {ratio:.0f}x |",
            flush=True,
        )
    if args.output:
        with open(args.output, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
