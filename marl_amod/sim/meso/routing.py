"""Fleet routes on SUMO's own routing costs, without a SUMO routing call per leg.

Every fleet leg needs a route. ``simulation.findRoute`` (SUMO's A*, ~6 ms on Luxembourg) was 79%
of a meso episode, and the legs' (from, to) edge pairs almost never repeat, so caching its
answers does not help. What does: SUMO's default router (the one ``findRoute`` uses) costs a
route by *static* weights, each edge's free-flow time plus a per-connection penalty (junction
and turn costs), unless edge weights are loaded or set. Those weights are read from SUMO once per
network and settings (one cheap ``findRoute`` per edge and per connection), and routes are then
shortest paths over them: one vectorised Dijkstra (scipy) per source edge, whose predecessor row
is kept, so a leg costs a few microseconds of path walking. The route's cost is the one SUMO's
router gives (checked on sampled pairs when the router is built; a mismatch, e.g. from loaded
weight files, falls back to SUMO's router); where two routes tie, the edges may differ.
"""

from __future__ import annotations

from collections import OrderedDict
from typing import Any

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import dijkstra

from marl_amod.scenario.sumo.network import RoadNetwork

CHECK_PAIRS = 20  # sampled (from, to) pairs compared with SUMO's router when weights are read
TOLERANCE_S = 1e-3  # seconds; trees keep costs as float32 (a millisecond at worst on city routes)


class EdgeRouter:
    """Shortest routes between usable edges on SUMO's routing costs (see the module docstring)."""

    def __init__(self, net: RoadNetwork, edge_cost: np.ndarray, arcs: csr_matrix, max_trees: int | None = None) -> None:
        self.net = net
        self.edge_cost = edge_cost  # (E,) seconds SUMO's router charges for the first edge
        self.arcs = arcs  # (E, E) cost of moving onto edge b from edge a (b's time + the connection's)
        # trees kept (LRU), by default all: 6 bytes per edge each (200 MB for Luxembourg's 5.7k
        # edges at most), so training computes each source's tree once per process
        self.max_trees = net.n_edges if max_trees is None else max_trees
        self._index_type = np.int16 if net.n_edges < np.iinfo(np.int16).max else np.int32
        self._trees: OrderedDict[int, tuple[np.ndarray, np.ndarray]] = OrderedDict()

    @classmethod
    def from_sumo(cls, api: Any, net: RoadNetwork, check_seed: int = 0) -> EdgeRouter | None:
        """Read SUMO's routing costs of ``net`` from a running simulation; None when routes
        computed on them do not cost what SUMO's own router says (then keep calling SUMO)."""
        find = api.simulation.findRoute
        edges = net.edges
        edge_cost = np.array([find(e, e).travelTime for e in edges])
        coo = net.successors.tocoo()
        row, col, cost = [], [], []
        for a, b in zip(coo.row, coo.col, strict=True):
            r = find(edges[a], edges[b])
            if len(r.edges) == 2:  # a direct connection SUMO's vehicles may use (else a detour is cheaper or needed)
                row.append(a), col.append(b), cost.append(r.travelTime - edge_cost[a])
        arcs = csr_matrix((np.maximum(cost, 0.0), (row, col)), shape=(net.n_edges, net.n_edges))
        router = cls(net, edge_cost, arcs)
        rng = np.random.default_rng(check_seed)
        for a, b in rng.integers(net.n_edges, size=(CHECK_PAIRS, 2)):
            if a != b and abs(router.route(a, b)[1] - find(edges[a], edges[b]).travelTime) > TOLERANCE_S:
                return None
        return router

    def _tree(self, source: int) -> tuple[np.ndarray, np.ndarray]:
        """(predecessors (E,), costs (E,)) of the shortest-path tree from ``source``."""
        tree = self._trees.get(source)
        if tree is None:
            dist, pred = dijkstra(self.arcs, directed=True, indices=source, return_predecessors=True)
            tree = self._trees[source] = (pred.astype(self._index_type), dist.astype(np.float32))
            if len(self._trees) > self.max_trees:
                self._trees.popitem(last=False)
        else:
            self._trees.move_to_end(source)
        return tree

    def route(self, source: int, target: int) -> tuple[list[int], float]:
        """(edge indices from ``source`` to ``target``, cost in seconds as SUMO's router counts it)."""
        pred, dist = self._tree(source)
        if not np.isfinite(dist[target]):
            raise RuntimeError(f"no route from {self.net.edges[source]} to {self.net.edges[target]}")
        path = [target]
        while path[-1] != source:
            path.append(int(pred[path[-1]]))
        return path[::-1], float(self.edge_cost[source] + dist[target])


_ROUTERS: dict[tuple[str, ...], EdgeRouter | None] = {}  # per process: SUMO's settings -> router


def router_for(api: Any, net: RoadNetwork, settings: tuple[str, ...]) -> EdgeRouter | None:
    """The router of a network under SUMO ``settings`` (its command line), read once per process:
    the costs are static, so every episode after the first reuses the weights and cached trees."""
    if settings not in _ROUTERS:
        _ROUTERS[settings] = EdgeRouter.from_sumo(api, net)
    return _ROUTERS[settings]
