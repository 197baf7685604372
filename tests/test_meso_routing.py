"""The fleet's routing table (marl_amod.sim.meso.routing) against SUMO's own router: every route
is a connected chain of edges and costs exactly what ``findRoute`` says; when SUMO's costs are not
what the table holds, the simulator keeps calling SUMO."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

pytest.importorskip("libsumo")

from marl_amod.scenario import load_city  # noqa: E402
from marl_amod.scenario.simspec import SimSpec  # noqa: E402
from marl_amod.sim.meso.routing import EdgeRouter  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402


def _grid_sim(**options):
    city = load_city("sumo_grid")
    if options:
        city = dataclasses.replace(city, simulator=SimSpec("meso", dataclasses.replace(city.simulator.sumo, **options)))
    system = FleetSystem(city)
    system.reset(0)
    return system


def test_routes_are_connected_and_cost_what_sumo_router_says():
    system = _grid_sim()
    sim = system.sim
    router, net, find = sim._router, sim.net, sim.sumo.simulation.findRoute
    assert router is not None
    succ = net.successors.tocsr()
    rng = np.random.default_rng(3)
    for a, b in rng.choice(net.n_edges, size=(100, 2)):
        if a == b:
            continue
        path, cost = router.route(a, b)
        assert path[0] == a and path[-1] == b
        assert all(succ[u, v] for u, v in zip(path[:-1], path[1:], strict=True))  # SUMO can drive it
        assert cost == pytest.approx(find(net.edges[a], net.edges[b]).travelTime, abs=1e-3)  # costs kept as float32
    sim.close()


def test_sumo_router_option_routes_every_leg_with_sumo_and_serves_alike():
    def episode(**options):  # one after the other: libsumo runs one simulation per process
        system = _grid_sim(**options)
        assert (system.sim._router is None) == bool(options)
        while not system.done:
            system.step(system.targets_from_weights(np.ones(system.city.n_regions)))
        system.sim.close()
        return system

    fast, slow = episode(), episode(sumo_router=True)
    # same demand; routes differ at most where two cost the same, so service is near-identical
    assert fast.sim.totals.demand.sum() == slow.sim.totals.demand.sum()
    assert fast.sim.totals.served.sum() == pytest.approx(slow.sim.totals.served.sum(), rel=0.05)


class _WrongCosts:
    """A SUMO stand-in whose router charges 1 s more than the sum of its edge and turn costs."""

    def __init__(self, net):
        self.simulation = self
        self.net = net

    def findRoute(self, a, b):  # noqa: N802 - SUMO's name
        edges = [a] if a == b else [a, b]
        extra = 0.0 if len(edges) < 2 or self.net.successors[self.net.index[a], self.net.index[b]] else 1.0
        return type("Stage", (), {"edges": edges, "travelTime": 10.0 * len(edges) + extra})()


def test_router_refuses_when_routes_do_not_cost_what_sumo_says():
    net = _grid_sim().sim.net
    assert EdgeRouter.from_sumo(_WrongCosts(net), net) is None
