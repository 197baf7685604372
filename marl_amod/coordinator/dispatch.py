"""Step 1, dispatch: match idle vehicles to requests by the paper's LP, solved exactly by a greedy.

    max  sum_ij x_ij * m_ij    s.t.  0 <= x_ij <= d_ij,   sum_j x_ij <= M_i

The constraints couple only pairs with the same origin, so the LP splits into one fractional
knapsack per origin with unit weights: serving requests in decreasing order of margin m_ij
(skipping non-positive margins) until the idle vehicles run out is optimal, and integral for
integral demand. Vectorised over all origins at once: one sort, one cumulative sum, one clip.
"""

from __future__ import annotations

import numpy as np

from marl_amod.errors import DataError
from marl_amod.validation import check_array


def margin_order(margin: np.ndarray) -> np.ndarray:
    """Per-origin column order by decreasing margin; (..., N, N) int. Cacheable per step."""
    return np.argsort(-margin, axis=-1, kind="stable")


def dispatch_plan(margin: np.ndarray, order: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """What :func:`greedy_dispatch` needs of a margin table: (N, N) bool 'worth serving' (margin > 0)
    and (N, N) flat row-major positions of each origin's entries by decreasing margin. A table of
    the city per step, so the coordinator computes it once per step."""
    if order is None:
        order = margin_order(margin)
    n = margin.shape[-1]
    return margin > 0, order + np.arange(0, n * n, n)[:, None]


def greedy_dispatch(
    idle: np.ndarray, demand: np.ndarray, margin: np.ndarray, order: np.ndarray | None = None
) -> np.ndarray:
    """Optimal integral passenger flows x (..., N, N) for idle (..., N), demand (..., N, N) and margin (N, N).

    ``order`` is :func:`margin_order` of ``margin``; pass it when margins repeat across calls.
    Leading axes are independent instances (a batch of episodes at the same step).
    """
    idle, demand, margin = check_dispatch_inputs(idle, demand, margin)
    return planned_dispatch(idle, demand, dispatch_plan(margin, order))


def planned_dispatch(idle: np.ndarray, demand: np.ndarray, plan: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """:func:`greedy_dispatch` on checked int64 counts and a :func:`dispatch_plan` (no checks here)."""
    positive, flat = plan
    servable = np.where(positive, demand, 0).reshape(*demand.shape[:-2], -1)  # (..., N * N)
    # served so far along each origin's requests by decreasing margin: the cumulative requests,
    # capped by the idle vehicles; its increments are the flows (min(d_k, max(idle - before_k, 0))
    # in integers, exactly; numpy reads the overlapping operand as it was before the subtraction)
    x_sorted = np.minimum(servable[..., flat].cumsum(axis=-1), idle[..., None])
    x_sorted[..., 1:] -= x_sorted[..., :-1]
    x = np.empty(servable.shape, servable.dtype)
    x[..., flat] = x_sorted
    return x.reshape(demand.shape)


def check_dispatch_counts(idle: np.ndarray, demand: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """idle (..., N) and demand (..., N, N) as whole non-negative int64 counts, otherwise a
    :class:`~marl_amod.errors.DataError` naming the argument and the region. Leading axes are a
    batch of episodes, checked in one pass."""
    lead = max(np.ndim(idle) - 1, 0)
    idle = check_array(idle, "idle vehicles", minimum=0, integer=True, lead=lead)
    if idle.ndim < 1:
        raise DataError(f"idle vehicles must be one count per region (N,), got shape {idle.shape}")
    n = idle.shape[-1]
    demand = check_array(demand, "requests", shape=(*idle.shape, n), minimum=0, integer=True, lead=lead)
    return idle, demand


def check_dispatch_inputs(idle: np.ndarray, demand: np.ndarray, margin: np.ndarray) -> tuple[np.ndarray, ...]:
    """:func:`check_dispatch_counts`, and margin (N, N) finite."""
    idle, demand = check_dispatch_counts(idle, demand)
    n = idle.shape[-1]
    margin = check_array(margin, "dispatch margin", shape=(n, n))
    return idle, demand, margin
