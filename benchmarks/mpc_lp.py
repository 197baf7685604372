"""MPC's LP per control step: scipy's linprog, the direct call to scipy's bundled HiGHS, and cvxpy.

Records the plans of MPC-Forecast episodes (what MPC solves at each step; the meta-imitation
recipe's demonstrations and DAgger labels are one such LP per step), then solves each one with

* ``linprog``: the sparse LP (:func:`~marl_amod.baselines.mpc.lp_matrices`) through
  ``scipy.optimize.linprog(method="highs-ds")``, what MPC called until the direct path;
* ``direct``: the same LP through :func:`marl_amod.baselines.highs.solve_lp` (MPC's
  ``scipy`` backend now);
* ``cvxpy``: the DPP-parameterised problem (``backend="cvxpy"``; its compile, at the first solve,
  left out),

in turn, the order rotating from one LP to the next so no path always finds the warmer cache.
Prints per city the median milliseconds per step of each (the LP's construction included), the
speed-ups over linprog, and on how many LPs ``direct`` returned linprog's vertex bit for bit (any
other count is a bug: MPC would act differently). Run on one idle core:
    python benchmarks/mpc_lp.py [--cities nyc_brooklyn shenzhen_downtown_west] [--episodes 2] [--no-cvxpy]
(a minute or two; the real cities need MARL_AMOD_DATA).
"""

from __future__ import annotations

import os

for _var in ("OMP_NUM_THREADS", "MKL_NUM_THREADS", "OPENBLAS_NUM_THREADS"):
    os.environ[_var] = "1"

import argparse  # noqa: E402
import statistics  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402

import numpy as np  # noqa: E402

from marl_amod.baselines.highs import HAS_BUNDLED_HIGHS, solve_lp  # noqa: E402
from marl_amod.baselines.mpc import DEFAULT_HORIZON, CvxpyMPC, MPCForecast, PlanData, lp_matrices  # noqa: E402
from marl_amod.evaluation import episode_seeds  # noqa: E402
from marl_amod.scenario import City, load_city  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402


def episode_plans(city: City, episodes: int, seed: int, horizon: int) -> list[PlanData]:
    """What MPC-Forecast solves at every step of ``episodes`` episodes, as it plays them."""
    system, policy = FleetSystem(city), MPCForecast(horizon=horizon)
    plans = []
    for e in range(episodes):
        demand_seed, rng = episode_seeds(seed, e)
        system.reset(demand_seed)
        policy.reset(system, rng)
        while not system.done:
            plans.append(policy.problem(system))
            system.step(policy.target(system))
    return plans


def _solve(plan: PlanData, direct: bool) -> np.ndarray:
    cost, a, b, ub = lp_matrices(plan)
    return solve_lp(cost, "benchmark LP", a_eq=a, b_eq=b, ub=ub, direct=direct)[0]


def solvers(city: City, horizon: int, cvxpy: bool) -> dict[str, Callable[[PlanData], np.ndarray | None]]:
    """Each path as plan -> its flows (None where the vertex is not compared)."""
    paths: dict[str, Callable[[PlanData], np.ndarray | None]] = {
        "linprog": lambda plan: _solve(plan, direct=False),
        "direct": lambda plan: _solve(plan, direct=True),
    }
    if cvxpy:
        problem = CvxpyMPC(city, horizon)

        def with_cvxpy(plan: PlanData) -> None:
            problem.solve(plan)  # another modelling layer: its vertex is not compared

        paths["cvxpy"] = with_cvxpy
    return paths


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cities", nargs="+", default=["nyc_brooklyn", "shenzhen_downtown_west", "chicago", "porto", "synthetic"])
    p.add_argument("--episodes", type=int, default=2)
    p.add_argument("--seed", type=int, default=5)
    p.add_argument("--horizon", type=int, default=DEFAULT_HORIZON)
    p.add_argument("--no-cvxpy", dest="cvxpy", action="store_false", help="leave the cvxpy path out")
    opts = p.parse_args()
    if not HAS_BUNDLED_HIGHS:
        raise SystemExit("this scipy bundles no HiGHS core: MPC uses linprog, nothing to compare")
    names = ["linprog", "direct"] + (["cvxpy"] if opts.cvxpy else [])
    print(f"MPC-Forecast, horizon {opts.horizon}, {opts.episodes} episodes per city; median ms per step, the LP's construction included")
    print("| city | regions | LPs | " + " | ".join(names) + " | linprog / direct |" + (" linprog / cvxpy |" if opts.cvxpy else "") + " same vertex |")
    print("|---|---|---|" + "---|" * len(names) + "---|" + ("---|" if opts.cvxpy else "") + "---|")
    for name in opts.cities:
        city = load_city(name)
        plans = episode_plans(city, opts.episodes, opts.seed, opts.horizon)
        paths = solvers(city, opts.horizon, opts.cvxpy)
        if opts.cvxpy:
            paths["cvxpy"](plans[0])  # the DPP compile happens at the first solve
        times: dict[str, list[float]] = {path: [] for path in names}
        same = 0
        for k, plan in enumerate(plans):
            flows = {}
            for path in names[k % len(names) :] + names[: k % len(names)]:
                start = time.perf_counter()
                flows[path] = paths[path](plan)
                times[path].append(time.perf_counter() - start)
            same += np.array_equal(flows["linprog"], flows["direct"])
        ms = {path: statistics.median(t) * 1e3 for path, t in times.items()}
        cells = " | ".join(f"{ms[path]:.1f}" for path in names)
        ratios = f" {ms['linprog'] / ms['direct']:.2f}x |" + (f" {ms['linprog'] / ms['cvxpy']:.2f}x |" if opts.cvxpy else "")
        print(f"| {name} | {city.n_regions} | {len(plans)} | {cells} |{ratios} {same}/{len(plans)} |", flush=True)


if __name__ == "__main__":
    main()
