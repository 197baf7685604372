"""Step 3, rebalancing: the cheapest moves that bring every region up to its target.

    min  sum_ij c_ij y_ij   s.t.  sum_j (y_ji - y_ij) + M_i >= u_i,   sum_j y_ij <= M_i,  y >= 0

Every y_ij is made of region i's own idle vehicles, so the LP is a transportation problem:
region i supplies M_i vehicles, region j needs u_j of them, keeping a vehicle at home costs 0
and the rest may stay anywhere. We solve it as a min-cost flow with OR-Tools. When travel costs
obey the triangle inequality (checked once per city), only surplus regions need to send and only
shortfall regions need to receive, which shrinks the network from N^2 arcs to |surplus| x
|shortfall|; otherwise the full bipartite network is solved.
"""

from __future__ import annotations

import numpy as np

from marl_amod.errors import ActionError, DataError, SolverError
from marl_amod.validation import check_array


def satisfies_triangle_inequality(cost: np.ndarray, chunk: int | None = None) -> bool:
    """True when c_ij <= c_ik + c_kj for all i, j, k (O(N^3), in chunks to bound memory).

    The default chunk keeps each (chunk, N, N) block near 8 M entries (64 MB of int64), so a
    city of thousands of regions is checked without gigabytes of scratch memory.
    """
    n = cost.shape[0]
    chunk = chunk or max(1, min(64, (1 << 23) // max(n * n, 1)))
    for start in range(0, n, chunk):
        block = cost[start : start + chunk]  # (b, N) = c_ik for i in the block
        via = (block[:, :, None] + cost[None, :, :]).min(axis=1)  # (b, N): min_k c_ik + c_kj
        if np.any(via < block):
            return False
    return True


def desired_targets(weights: np.ndarray, total_idle: int) -> np.ndarray:
    """The paper's target u_i = floor(w_i / sum(w) * M); all-zero weights mean 'stay' (-1s).

    Weights are a policy's output: a NaN, infinite or negative one raises
    :class:`~marl_amod.errors.ActionError` naming the region (cast to an integer it would
    silently mean 'stay' and give the no-rebalancing result).
    """
    weights = check_array(weights, "rebalancing weights", minimum=0, error=ActionError)
    if weights.ndim != 1:
        raise ActionError(f"rebalancing weights must be one number per region (N,), got shape {weights.shape}")
    s = weights.sum()
    if s <= 0:
        return np.full(weights.shape, -1, dtype=np.int64)
    share = weights / s
    if not np.all(np.isfinite(share)):  # weights near the float maximum overflow their sum
        share = (weights / weights.max()) / (weights / weights.max()).sum()
    return np.floor(share * total_idle + 1e-9).astype(np.int64)


def check_rebalance_inputs(idle: np.ndarray, target: np.ndarray, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(idle, target) as int64 (N,) arrays, or an error naming the argument and the region:
    idle counts must be whole and >= 0; a target whole and >= -1 (-1: no wish)."""
    idle = check_array(idle, "idle vehicles", minimum=0, integer=True, shape=None if n is None else (n,))
    if idle.ndim != 1:
        raise DataError(f"idle vehicles must be one count per region (N,), got shape {idle.shape}")
    target = check_array(target, "rebalancing target", shape=idle.shape, minimum=-1, integer=True, error=ActionError)
    return idle, target


# costs scaled to integers with this resolution when they are not whole numbers already
COST_RESOLUTION = 10**9


def integer_costs(cost: np.ndarray) -> np.ndarray:
    """Costs as int64 for OR-Tools: whole numbers up to ``COST_RESOLUTION`` unchanged (exact),
    others scaled so the largest is ``COST_RESOLUTION`` and rounded (never truncated)."""
    top = float(cost.max()) if cost.size else 0.0
    if top <= COST_RESOLUTION and (cost.dtype.kind in "iu" or np.all(cost == np.round(cost))):
        return cost.astype(np.int64, copy=False)
    return np.rint(cost * (COST_RESOLUTION / top)).astype(np.int64)


def min_cost_rebalance(idle: np.ndarray, target: np.ndarray, cost: np.ndarray, metric: bool = False) -> np.ndarray:
    """Optimal integral rebalancing flows y (N, N), zero diagonal.

    ``cost`` (N, N) is non-negative and finite. Whole-number costs (travel steps, as the
    coordinator passes: proportional to the money cost, so the same argmin) are solved exactly;
    other costs are scaled so the largest is 10^9 and rounded (see :func:`integer_costs`), so the
    flows are optimal to within total flow x max cost x 1e-9 of the LP. ``metric`` says the triangle inequality holds (see
    :func:`satisfies_triangle_inequality`). Targets above what the fleet can reach are
    infeasible and raise; targets summing to at most sum(idle) never are.
    """
    from ortools.graph.python import min_cost_flow

    idle, target = check_rebalance_inputs(idle, target)
    need = np.maximum(target, 0)
    n = idle.shape[0]
    cost = integer_costs(check_array(cost, "rebalancing cost", shape=(n, n), minimum=0))
    if need.sum() > idle.sum():
        raise SolverError(f"rebalancing targets sum to {need.sum()} but only {idle.sum()} vehicles are idle")
    flows = np.zeros((n, n), dtype=np.int64)
    if metric:
        senders = np.flatnonzero(idle > need)
        receivers = np.flatnonzero(need > idle)
        if receivers.size == 0:
            return flows
        supply = idle[senders] - need[senders]
        demand = need[receivers] - idle[receivers]
    else:
        senders = receivers = np.arange(n)
        supply, demand = idle, need
    s, r = senders.size, receivers.size
    # nodes: senders 0..s-1, receivers s..s+r-1, slack sink s+r (absorbs vehicles that stay anywhere)
    tail = np.concatenate([np.repeat(np.arange(s), r), np.arange(s)])
    head = np.concatenate([np.tile(np.arange(s, s + r), s), np.full(s, s + r)])
    unit = np.concatenate([cost[np.ix_(senders, receivers)].ravel(), np.zeros(s, dtype=np.int64)])
    cap = np.concatenate([np.repeat(supply, r), supply])
    smcf = min_cost_flow.SimpleMinCostFlow()
    arcs = smcf.add_arcs_with_capacity_and_unit_cost(tail, head, cap, unit)
    supplies = np.concatenate([supply, -demand, [demand.sum() - supply.sum()]])
    smcf.set_nodes_supplies(np.arange(s + r + 1), supplies)
    status = smcf.solve()
    if status != smcf.OPTIMAL:
        raise SolverError(f"min-cost rebalancing flow failed with OR-Tools status {status}")
    f = smcf.flows(arcs)[: s * r].reshape(s, r)
    flows[np.ix_(senders, receivers)] = f
    np.fill_diagonal(flows, 0)  # a region 'sending' to itself keeps its vehicles
    return flows
