"""LPs with 0 <= z <= ub, as scipy's ``linprog(method="highs-ds")`` solves them, handed to HiGHS
without linprog's wrapping: MPC's plan and the behaviour policies' (INF, DTV) moves.

Why a module of its own: MPC solves one such LP per control step, and in the meta-imitation
recipe (demonstrations and DAgger labels) those LPs are about a third of the wall time. scipy's
``linprog`` spends some 40% of each call outside HiGHS, most of it in a per-column Python loop that
builds bound marginals MPC never reads. :func:`solve_lp` passes the same model, with the
options ``linprog`` sets for ``highs-ds``, to the HiGHS build scipy bundles
(``scipy.optimize._highspy``, in recent scipy: 1.17 here). Same build, same model, same options: HiGHS takes
the same pivots and returns the same vertex. That matters because these LPs are degenerate: another
HiGHS build (``highspy`` 1.16) or a trimmed model lands on other optimal vertices, and every MPC
row of every table would move. ``tests/test_highs.py`` checks the two paths agree bit for bit.
Where scipy has no such core (older releases), ``linprog`` does the solve.
"""

from __future__ import annotations

import warnings
from typing import TYPE_CHECKING

import numpy as np

from marl_amod.errors import SolverError

if TYPE_CHECKING:
    import scipy.sparse as sp

    Matrix = np.ndarray | sp.spmatrix | sp.sparray

try:  # a private module: used only when it has every name this file reads
    import scipy.optimize._highspy._core as _core

    for _name in ("_Highs", "HighsOptions", "HighsModelStatus", "HighsStatus", "kHighsInf"):
        getattr(_core, _name)
except (ImportError, AttributeError):  # pragma: no cover - the lower-bound stage runs this path
    _core = None

HAS_BUNDLED_HIGHS = _core is not None

# what scipy's _linprog_highs sets for method="highs-ds" (every option it leaves at None is HiGHS's default)
LINPROG_HIGHS_DS_OPTIONS = {
    "presolve": "on",
    "solver": "simplex",
    "simplex_strategy": 1,  # kSimplexStrategyDual
    "highs_debug_level": 0,
    "output_flag": False,
    "log_to_console": False,
}
_COLWISE, _MINIMIZE = 1, 1  # HiGHS's MatrixFormat.kColwise and ObjSense.kMinimize


def solve_lp(
    cost: np.ndarray, what: str, *, a_ub: Matrix | None = None, b_ub: np.ndarray | None = None,
    a_eq: Matrix | None = None, b_eq: np.ndarray | None = None, ub: np.ndarray | None = None, direct: bool = True,
) -> tuple[np.ndarray, float]:
    """min cost @ z s.t. a_ub z <= b_ub, a_eq z = b_eq, 0 <= z <= ub (None: no upper bounds): (z, cost @ z)
    at the vertex HiGHS's dual simplex finds; raises :class:`SolverError` naming ``what``.

    ``direct=False`` forces scipy's ``linprog`` (the reference the direct path is tested against).
    """
    global HAS_BUNDLED_HIGHS
    n = cost.size
    ub = np.full(n, np.inf) if ub is None else np.asarray(ub, dtype=np.float64)
    if direct and HAS_BUNDLED_HIGHS:
        try:
            return _solve_bundled(cost, what, a_ub, b_ub, a_eq, b_eq, ub)
        except (TypeError, AttributeError) as exc:  # a scipy whose private core changed its calls
            HAS_BUNDLED_HIGHS = False
            warnings.warn(f"scipy's bundled HiGHS core took no model ({exc}); LPs are solved through linprog (slower, same vertex)", stacklevel=2)
    from scipy.optimize import linprog

    res = linprog(cost, A_ub=a_ub, b_ub=b_ub, A_eq=a_eq, b_eq=b_eq, bounds=np.column_stack([np.zeros(n), ub]), method="highs-ds")
    if res.status != 0 or res.x is None:
        raise SolverError(f"{what} (scipy/HiGHS) failed: status {res.status}: {res.message}")
    return res.x, float(res.fun)


def _rows(a_ub: Matrix | None, b_ub, a_eq: Matrix | None, b_eq, n: int) -> tuple[sp.csc_array, np.ndarray, np.ndarray]:
    """(A, lhs, rhs) of lhs <= A z <= rhs, stacked as ``linprog`` stacks them: the inequalities (lhs
    -inf) over the equalities (lhs = rhs), sparse if either block is, one CSC matrix."""
    import scipy.sparse as sp

    a_ub = np.zeros((0, n)) if a_ub is None else a_ub
    a_eq = np.zeros((0, n)) if a_eq is None else a_eq
    b_ub = np.zeros(0) if b_ub is None else np.asarray(b_ub, dtype=np.float64).ravel()
    b_eq = np.zeros(0) if b_eq is None else np.asarray(b_eq, dtype=np.float64).ravel()
    stacked = sp.vstack((a_ub, a_eq)) if sp.issparse(a_ub) or sp.issparse(a_eq) else np.vstack((a_ub, a_eq))
    return sp.csc_array(stacked), np.concatenate([np.full(b_ub.size, -np.inf), b_eq]), np.concatenate([b_ub, b_eq])


def _solve_bundled(cost: np.ndarray, what: str, a_ub, b_ub, a_eq, b_eq, ub: np.ndarray) -> tuple[np.ndarray, float]:
    """The model and options as scipy's ``_linprog_highs`` builds them for ``highs-ds``, passed as
    arrays (HiGHS's array overload of ``passModel``: no element-by-element copy into a ``HighsLp``)."""
    n_col = cost.size
    a, lhs, rhs = _rows(a_ub, b_ub, a_eq, b_eq, n_col)
    inf = _core.kHighsInf
    highs = _core._Highs()
    options = _core.HighsOptions()
    for key, value in LINPROG_HIGHS_DS_OPTIONS.items():
        setattr(options, key, value)
    highs.passOptions(options)
    passed = highs.passModel(
        n_col, rhs.size, a.nnz, _COLWISE, _MINIMIZE, 0.0,
        np.asarray(cost, dtype=np.float64), np.zeros(n_col), np.minimum(ub, inf),
        np.clip(lhs, -inf, inf), np.clip(rhs, -inf, inf),  # HiGHS's infinity, as linprog maps np.inf
        a.indptr.astype(np.int32), a.indices.astype(np.int32), a.data.astype(np.float64),
        np.zeros(n_col, dtype=np.int32),  # every column continuous (with an empty array HiGHS refused the model)
    )  # fmt: skip
    if passed == _core.HighsStatus.kError:
        raise SolverError(f"{what}: HiGHS refused the model ({rhs.size} rows, {n_col} columns)")
    highs.run()
    status = highs.getModelStatus()
    if status != _core.HighsModelStatus.kOptimal:
        raise SolverError(f"{what} (HiGHS) failed: {highs.modelStatusToString(status)}")
    return np.array(highs.getSolution().col_value), float(highs.getInfo().objective_function_value)
