"""MPC's LP: scipy's linprog against the direct call to scipy's bundled HiGHS core (same vertex?).

Records the LPs of MPC-Forecast episodes (the meta-imitation recipe's demonstrations and DAgger
labels are one such LP per step), then solves each with both paths of
:func:`marl_amod.baselines.highs.solve_equality_lp`, alternating the order per LP so neither path
gets the warmer cache. Prints per city the median milliseconds of each path, their ratio, and on
how many LPs the two returned the same vertex bit for bit (any other count is a bug: MPC would act
differently). Run:  python benchmarks/mpc_lp.py [--cities chicago porto ...] [--episodes 2]
(about a minute; needs MARL_AMOD_DATA for the real cities).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402

import numpy as np  # noqa: E402

from marl_amod.baselines.highs import HAS_BUNDLED_HIGHS, solve_equality_lp  # noqa: E402
from marl_amod.baselines.mpc import MPCForecast, lp_matrices  # noqa: E402
from marl_amod.evaluation import episode_seeds  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402


def episode_lps(city_name: str, episodes: int, seed: int) -> list[tuple]:
    """Every LP MPC-Forecast solves in ``episodes`` episodes of the city, as it plays them."""
    city = load_city(city_name)
    system, policy = FleetSystem(city), MPCForecast()
    lps = []
    for e in range(episodes):
        demand_seed, rng = episode_seeds(seed, e)
        system.reset(demand_seed)
        policy.reset(system, rng)
        while not system.done:
            lps.append(lp_matrices(policy.problem(system)))
            system.step(policy.target(system))
    return lps


def timed(lp: tuple, direct: bool) -> tuple[float, np.ndarray]:
    start = time.perf_counter()
    z, _ = solve_equality_lp(*lp, "benchmark LP", direct=direct)
    return time.perf_counter() - start, z


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cities", nargs="+", default=["chicago", "nyc_man_south", "porto", "shenzhen_baoan", "synthetic"])
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--seed", type=int, default=5)
    opts = p.parse_args()
    if not HAS_BUNDLED_HIGHS:
        raise SystemExit("this scipy bundles no HiGHS core (scipy < 1.15): MPC uses linprog, nothing to compare")
    print("| city | LPs | columns | linprog (ms) | direct (ms) | linprog / direct | same vertex |")
    print("|---|---|---|---|---|---|---|")
    for name in opts.cities:
        lps = episode_lps(name, opts.episodes, opts.seed)
        slow, fast, same = [], [], 0
        for k, lp in enumerate(lps):
            order = (False, True) if k % 2 == 0 else (True, False)
            results = {direct: timed(lp, direct) for direct in order}
            slow.append(results[False][0])
            fast.append(results[True][0])
            same += np.array_equal(results[False][1], results[True][1])
        s, f = statistics.median(slow) * 1e3, statistics.median(fast) * 1e3
        print(f"| {name} | {len(lps)} | {lps[0][0].size:,} | {s:.1f} | {f:.1f} | {s / f:.2f} | {same}/{len(lps)} |")


if __name__ == "__main__":
    main()
