"""The dispatch and rebalancing LPs written literally in cvxpy: the slow path that checks the fast one.

HiGHS is used because it returns vertex (hence integral) solutions of these totally unimodular
LPs; interior-point solvers such as Clarabel return fractional flows. The N^2-variable problems
are rebuilt per call rather than parameterised: cvxpy's compile of a parameterised version of
the dispatch LP grows much faster than a rebuild.
"""

from __future__ import annotations

import numpy as np

from marl_amod.errors import SolverError


def _solve(problem, what: str) -> None:
    import cvxpy as cp

    problem.solve(solver=cp.HIGHS, warm_start=False)
    if problem.status not in ("optimal", "optimal_inaccurate"):
        raise SolverError(f"cvxpy/HiGHS could not solve the {what} LP: status {problem.status}")


def lp_dispatch(idle: np.ndarray, demand: np.ndarray, margin: np.ndarray) -> np.ndarray:
    """Passenger flows (N, N) maximising sum x * margin under demand and idle-vehicle limits."""
    import cvxpy as cp

    n = idle.shape[0]
    x = cp.Variable((n, n), nonneg=True)
    constraints = [x <= demand, cp.sum(x, axis=1) <= idle]
    problem = cp.Problem(cp.Maximize(cp.sum(cp.multiply(margin, x))), constraints)
    _solve(problem, "dispatch")
    return np.rint(x.value).astype(np.int64)


def lp_rebalance(idle: np.ndarray, target: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """Rebalancing flows (N, N) of minimum cost that meet every target (the paper's Step 3)."""
    import cvxpy as cp

    n = idle.shape[0]
    off = ~np.eye(n, dtype=bool)
    y = cp.Variable((n, n), nonneg=True)
    inflow = cp.sum(cp.multiply(off, y), axis=0)
    outflow = cp.sum(cp.multiply(off, y), axis=1)
    constraints = [inflow - outflow + idle >= np.maximum(target, 0), outflow <= idle, cp.diag(y) == 0]
    problem = cp.Problem(cp.Minimize(cp.sum(cp.multiply(cost * off, y))), constraints)
    _solve(problem, "rebalancing")
    return np.rint(y.value).astype(np.int64)
