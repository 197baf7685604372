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

import math

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


def desired_targets(weights: np.ndarray, total_idle: int | np.ndarray) -> np.ndarray:
    """The paper's target u_i = floor(w_i / sum(w) * M); all-zero weights mean 'stay' (-1s).

    Leading axes of ``weights`` (..., N) are independent instances with ``total_idle`` (...,).
    Weights are a policy's output: a NaN, infinite or negative one raises
    :class:`~marl_amod.errors.ActionError` naming the region (cast to an integer it would
    silently mean 'stay' and give the no-rebalancing result).
    """
    weights = check_array(weights, "rebalancing weights", minimum=0, error=ActionError, lead=max(np.ndim(weights) - 1, 0))
    if weights.ndim < 1:
        raise ActionError(f"rebalancing weights must be one number per region (N,), got shape {weights.shape}")
    return floor_targets(weights, total_idle)


def floor_targets(weights: np.ndarray, total_idle: int | np.ndarray) -> np.ndarray:
    """:func:`desired_targets` of weights (..., N) already known to be finite and >= 0 (the env's
    clipped actions): the arithmetic alone. One episode's weights (N,) take one sum and the same
    float64 operations on a scalar sum, not a (1,) array: the same numbers in fewer numpy calls."""
    if weights.ndim == 1:
        s = weights.sum()
        if math.isfinite(s):
            if s > 0:
                return np.floor(weights / s * total_idle + 1e-9).astype(np.int64)
            return np.full(weights.shape, -1, dtype=np.int64)
    s = weights.sum(axis=-1, keepdims=True)
    big = ~np.isfinite(s)
    if big.any():  # weights near the float maximum overflow their sum: rescale those rows
        weights = np.where(big, weights / np.where(big, weights.max(axis=-1, keepdims=True), 1.0), weights)
        s = weights.sum(axis=-1, keepdims=True)
    positive = s > 0
    total = np.asarray(total_idle)[..., None]
    u = np.floor(weights / np.where(positive, s, 1.0) * total + 1e-9).astype(np.int64)
    return np.where(positive, u, -1)


def check_rebalance_inputs(idle: np.ndarray, target: np.ndarray, n: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(idle, target) as int64 (..., N) arrays, or an error naming the argument and the region:
    idle counts must be whole and >= 0; a target whole and >= -1 (-1: no wish). Leading axes are
    a batch of independent instances, checked in one pass."""
    lead = max(np.ndim(idle) - 1, 0)
    idle = check_array(idle, "idle vehicles", minimum=0, integer=True, lead=lead)
    if idle.ndim < 1 or (n is not None and idle.shape[-1] != n):
        want = "(N,)" if n is None else f"({n},)"
        raise DataError(f"idle vehicles must have shape {want} (one count per region, leading batch axes allowed), got {idle.shape}")
    return idle, check_target(target, idle.shape)


def check_target(target: np.ndarray, shape: tuple[int, ...]) -> np.ndarray:
    """A target of ``shape`` (..., N) as int64: whole and >= -1 (-1: no wish), else an ActionError
    naming the region (and the episode, for leading batch axes)."""
    if type(target) is np.ndarray and target.dtype == np.int64 and target.shape == shape and not (target < -1).any():
        return target  # the usual case (a coordinator's own targets), in one comparison
    lead = len(shape) - 1
    return check_array(target, "rebalancing target", shape=shape, minimum=-1, integer=True, error=ActionError, lead=lead)


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
    idle, target = check_rebalance_inputs(idle, target)
    if idle.ndim != 1 or np.shape(cost) != (idle.shape[0],) * 2:
        raise DataError(f"min_cost_rebalance takes idle (N,) and cost (N, N), got {idle.shape} and {np.shape(cost)}")
    return Rebalancer(cost, metric)(idle, target)


class Rebalancer:
    """:func:`min_cost_rebalance` for one cost matrix, called every step.

    Without the triangle inequality the network is the same every call (all N x N arcs), so it is
    built once and only capacities and supplies change between solves: the same network handed
    to the same solver, hence the same flows, without rebuilding it (tested against a fresh build).
    When staying is free and every move between distinct regions costs something, an instance
    where no region is short of its target has one optimum, no move, and is answered without the
    solver (on both networks, one instance or a batch). The OR-Tools object is not picklable; a copy rebuilds it on first use.
    """

    def __init__(self, cost: np.ndarray, metric: bool = False) -> None:
        cost = check_array(cost, "rebalancing cost", minimum=0)
        if cost.ndim != 2 or cost.shape[0] != cost.shape[1]:
            raise DataError(f"rebalancing cost must be a square (N, N) matrix, got shape {cost.shape}")
        self.cost = integer_costs(cost)
        self.metric = metric
        n = cost.shape[0]
        # staying free and every move paid: an instance where no region is short has one optimum, no move
        self._moves_cost = bool((np.diagonal(self.cost) == 0).all() and (self.cost[~np.eye(n, dtype=bool)] > 0).all())
        self._full: tuple | None = None  # (solver, arc ids, node ids) of the full network

    def __call__(self, idle: np.ndarray, target: np.ndarray) -> np.ndarray:
        idle = np.asarray(idle, dtype=np.int64)
        need = np.maximum(np.asarray(target, dtype=np.int64), 0)
        n = idle.shape[0]
        total_need, total_idle = need.sum(), idle.sum()
        if total_need > total_idle:
            raise SolverError(f"rebalancing targets sum to {total_need} but only {total_idle} vehicles are idle")
        if self._moves_cost and not (need > idle).any():
            return np.zeros((n, n), dtype=np.int64)
        if self.metric:
            return self._solve_reduced(idle[None], need[None])[0]
        supplies = np.empty(2 * n + 1, dtype=np.int64)
        supplies[:n], supplies[n : 2 * n], supplies[2 * n] = idle, -need, total_need - total_idle
        return self._solve_full(idle[self._full_network()[3]], supplies)

    def many(self, idle: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Flows (B, N, N) for B independent instances idle (B, N), target (B, N): each solved alone
        (the same flows as B calls), with the array bookkeeping of the full network done once."""
        idle = np.asarray(idle, dtype=np.int64)
        need = np.maximum(np.asarray(target, dtype=np.int64), 0)
        b, n = idle.shape
        flows = np.zeros((b, n, n), dtype=np.int64)
        if self._moves_cost:  # elsewhere no move is the unique optimum
            short = np.flatnonzero((need > idle).any(axis=-1))
        else:
            short = np.arange(b)
        over = need[short].sum(axis=-1) > idle[short].sum(axis=-1)
        if over.any():
            k = short[np.argmax(over)]
            raise SolverError(f"rebalancing targets sum to {need[k].sum()} but only {idle[k].sum()} vehicles are idle")
        if self.metric:
            flows[short] = self._solve_reduced(idle[short], need[short])
            return flows
        supply, demand = idle[short], need[short]
        smcf, arcs, nodes, capacity_index = self._full_network()
        caps = supply[:, capacity_index]
        supplies = np.concatenate([supply, -demand, (demand.sum(1) - supply.sum(1))[:, None]], axis=1)
        pairs = arcs[: n * n]
        out = flows.reshape(b, n * n)
        for row, k in enumerate(short.tolist()):  # _solve_full, inlined: B calls per step
            smcf.set_arc_capacities(arcs, caps[row])
            smcf.set_nodes_supplies(nodes, supplies[row])
            _check(smcf.solve(), smcf)
            out[k] = smcf.flows(pairs)
        flows[:, np.arange(n), np.arange(n)] = 0  # a region 'sending' to itself keeps its vehicles
        return flows

    def _full_network(self) -> tuple:
        """(solver, arc ids, node ids, capacity index) of the full network, built on first use;
        ``idle[capacity index]`` are the arc capacities (each arc may carry its sender's vehicles)."""
        if self._full is None:
            n = self.cost.shape[0]
            rows = np.arange(n)
            self._full = (*_network(self.cost), np.concatenate([np.repeat(rows, n), rows]))
        return self._full

    def _solve_full(self, capacities: np.ndarray, supplies: np.ndarray) -> np.ndarray:
        """(N, N) flows of the full network for one instance's arc capacities and node supplies."""
        smcf, arcs, nodes, _ = self._full_network()
        n = self.cost.shape[0]
        smcf.set_arc_capacities(arcs, capacities)
        smcf.set_nodes_supplies(nodes, supplies)
        _check(smcf.solve(), smcf)
        flows = smcf.flows(arcs)  # a fresh int64 array: ours to edit
        flows[: n * n : n + 1] = 0  # a region 'sending' to itself keeps its vehicles
        return flows[: n * n].reshape(n, n)

    def _solve_reduced(self, idle: np.ndarray, need: np.ndarray) -> np.ndarray:
        """(K, N, N) flows of K instances (K, N) on the metric network: surplus regions (ascending)
        send to shortfall regions (ascending) or to the sink, one OR-Tools network per instance.

        Every instance's arcs, capacities, costs and supplies are laid out for the whole batch in a
        few array operations; the loop only hands each instance's slices to its own solver, so the
        networks are those a one-instance build makes (same nodes, arcs and order), hence the same flows.
        """
        from ortools.graph.python import min_cost_flow

        k, n = idle.shape
        surplus = idle - need
        send, recv = surplus > 0, surplus < 0
        s, r = send.sum(axis=1), recv.sum(axis=1)
        s_rank, r_rank = np.cumsum(send, axis=1) - 1, np.cumsum(recv, axis=1) - 1
        n_arcs, n_nodes = s * r + s, s + r + 1
        arc_start = np.concatenate([[0], np.cumsum(n_arcs)])
        node_start = np.concatenate([[0], np.cumsum(n_nodes)])
        tail, head = np.empty(arc_start[-1], dtype=np.int64), np.empty(arc_start[-1], dtype=np.int64)
        cap, unit = np.empty_like(tail), np.zeros_like(tail)
        # sender x receiver arcs first, senders then receivers ascending (np.nonzero's order)
        pe, pi, pj = np.nonzero(send[:, :, None] & recv[:, None, :])
        first_pair = np.concatenate([[0], np.cumsum(s * r)])[:-1]
        at = arc_start[pe] + np.arange(pe.size) - first_pair[pe]
        tail[at], head[at], cap[at], unit[at] = s_rank[pe, pi], s[pe] + r_rank[pe, pj], surplus[pe, pi], self.cost[pi, pj]
        pair_at = at
        # then each sender's arc to the sink (cost 0)
        se, si = np.nonzero(send)
        first_send = np.concatenate([[0], np.cumsum(s)])[:-1]
        at = arc_start[se] + s[se] * r[se] + np.arange(se.size) - first_send[se]
        tail[at], head[at], cap[at] = s_rank[se, si], s[se] + r[se], surplus[se, si]
        supplies = np.empty(node_start[-1], dtype=np.int64)
        supplies[node_start[se] + s_rank[se, si]] = surplus[se, si]
        re, ri = np.nonzero(recv)
        supplies[node_start[re] + s[re] + r_rank[re, ri]] = surplus[re, ri]  # -(shortfall)
        supplies[node_start[1:] - 1] = -surplus.sum(axis=1)  # the sink absorbs the rest
        nodes = np.arange(n_nodes.max(initial=0))
        moved = np.zeros(arc_start[-1], dtype=np.int64)
        for e in np.flatnonzero(r > 0).tolist():
            a, b = arc_start[e], arc_start[e + 1]
            smcf = min_cost_flow.SimpleMinCostFlow()
            arcs = smcf.add_arcs_with_capacity_and_unit_cost(tail[a:b], head[a:b], cap[a:b], unit[a:b])
            smcf.set_nodes_supplies(nodes[: n_nodes[e]], supplies[node_start[e] : node_start[e + 1]])
            _check(smcf.solve(), smcf)
            moved[a:b] = smcf.flows(arcs)
        flows = np.zeros((k, n, n), dtype=np.int64)
        flows[pe, pi, pj] = moved[pair_at]  # senders and receivers differ: nothing on the diagonal
        return flows

    def __getstate__(self) -> dict:
        return {**self.__dict__, "_full": None}


def _check(status: int, smcf: object) -> None:
    """Raise unless OR-Tools found the optimum (it always should: the inputs were checked)."""
    if status != smcf.OPTIMAL:  # type: ignore[attr-defined]
        raise SolverError(f"min-cost rebalancing flow failed with OR-Tools status {status}")


def _network(cost: np.ndarray) -> tuple:
    """An OR-Tools network for senders x receivers with unit costs ``cost`` (s, r), capacities unset.

    Nodes: senders 0..s-1, receivers s..s+r-1, slack sink s+r (absorbs vehicles that stay anywhere).
    """
    from ortools.graph.python import min_cost_flow

    s, r = cost.shape
    tail = np.concatenate([np.repeat(np.arange(s), r), np.arange(s)])
    head = np.concatenate([np.tile(np.arange(s, s + r), s), np.full(s, s + r)])
    unit = np.concatenate([cost.ravel(), np.zeros(s, dtype=np.int64)]).astype(np.int64)
    smcf = min_cost_flow.SimpleMinCostFlow()
    arcs = smcf.add_arcs_with_capacity_and_unit_cost(tail, head, np.zeros(tail.size, dtype=np.int64), unit)
    return smcf, arcs, np.arange(s + r + 1)
