"""The macro simulator conserves vehicles, times trips like the reference and is reproducible by seed."""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.baselines import EqualDistribution, RandomPolicy
from marl_amod.evaluation import run_episode
from marl_amod.scenario import grid_city
from marl_amod.sim import MacroSim
from marl_amod.system import FleetSystem


def test_vehicles_are_conserved_every_step_under_random_targets(tiny_city):
    system = FleetSystem(tiny_city)
    rng = np.random.default_rng(3)
    system.reset(7)
    fleet = tiny_city.fleet_size
    while not system.done:
        assert system.sim.vehicles() == fleet
        weights = rng.dirichlet(np.full(tiny_city.n_regions, 0.3))
        system.step(system.targets_from_weights(weights))
        assert np.all(system.sim.idle >= 0)
    assert system.sim.vehicles() == fleet


def test_trip_arrives_after_its_duration_and_is_idle_the_step_after():
    city = grid_city(1, 2, horizon=6, vehicles_per_region=1, step_time=2)  # 2 regions, 2 steps apart
    sim = MacroSim(city)
    sim.reset(np.random.default_rng(0))
    sim.backlog[0] = [[0, 1], [0, 0]]  # one request 0 -> 1
    sim.apply_dispatch(np.array([[0, 1], [0, 0]]))
    assert sim.idle.tolist() == [0, 1]
    assert sim.arrivals[2].tolist() == [0, 1]  # departs in step 0, arrives in step 2
    for expected_idle_at_1 in ([0, 1], [0, 1], [0, 2]):  # steps 1, 2, 3
        sim.backlog[:] = 0
        sim.advance()
        sim.backlog[:] = 0
        assert sim.idle.tolist() == expected_idle_at_1
    assert sim.t == 3


def test_two_batches_arriving_together_both_count():
    # the reference overwrites one batch with the other here; we must add them
    city = grid_city(1, 3, horizon=6, vehicles_per_region=2)
    sim = MacroSim(city)
    sim.reset(np.random.default_rng(0))
    sim.backlog[0] = 0
    sim.backlog[0, 0, 2] = 1
    sim.backlog[0, 1, 2] = 1
    duration = city.trip_time[0]
    sim.apply_dispatch(np.array([[0, 0, 1], [0, 0, 1], [0, 0, 0]]))
    y = np.zeros((3, 3), dtype=int)
    y[0, 2] = 1  # a rebalancing vehicle on the same 2-step route as trip 0->2
    sim.apply_rebalance(y)
    assert duration[0, 2] == 2 and duration[1, 2] == 1
    assert sim.arrivals[2, 2] == 2 and sim.arrivals[1, 2] == 1
    assert sim.vehicles() == city.fleet_size


def test_same_seed_same_episode_and_different_seed_different_demand(small_city):
    a, b, c = (FleetSystem(small_city) for _ in range(3))
    m_a, _ = run_episode(a, RandomPolicy(), seed=5)
    m_b, _ = run_episode(b, RandomPolicy(), seed=5)
    m_c, _ = run_episode(c, RandomPolicy(), seed=6)
    assert m_a == m_b
    assert np.array_equal(a.sim.demand, b.sim.demand)
    assert not np.array_equal(a.sim.demand, c.sim.demand)
    assert m_a != m_c


def test_reward_is_dispatch_profit_minus_rebalancing_cost(small_city):
    system = FleetSystem(small_city)
    total = system.reset(0).reward
    policy = EqualDistribution()
    policy.reset(system, np.random.default_rng(0))
    while not system.done:
        out = system.step(policy.target(system))
        assert out.reward == pytest.approx(out.dispatch_profit - out.rebalancing_cost)
        total += out.reward
    assert total == pytest.approx(system.sim.totals.profit.sum())


def test_requests_wait_up_to_max_wait_then_leave():
    city = grid_city(1, 2, horizon=8, vehicles_per_region=0)  # no vehicles: nobody is served
    sim = MacroSim(city, max_wait=2)
    sim.reset(np.random.default_rng(0))
    sim.demand[:] = 0
    sim.backlog[:] = 0
    sim.backlog[0, 0, 1] = 3
    for step in range(1, 4):
        sim.advance()
        open_now = sim.requests()[0, 1]
        assert open_now == (3 if step <= 2 else 0)
    assert sim.totals.lost[0] == 3


def test_waiting_passengers_are_served_oldest_first_and_wait_is_counted():
    city = grid_city(1, 2, horizon=8, vehicles_per_region=1)
    sim = MacroSim(city, max_wait=1)
    sim.reset(np.random.default_rng(0))
    sim.demand[:] = 0
    sim.backlog[:] = 0
    sim.backlog[1, 0, 1] = 1  # waited one step already
    sim.backlog[0, 0, 1] = 1
    sim.apply_dispatch(np.array([[0, 1], [0, 0]]))
    assert sim.backlog[1, 0, 1] == 0 and sim.backlog[0, 0, 1] == 1
    assert sim.totals.wait_minutes[0] == pytest.approx(city.tstep)


@pytest.mark.parametrize(
    "flows, message",
    [
        (np.full((2, 2), np.nan), "NaN"),
        (np.array([[0, -1], [0, 0]]), "non-negative integers"),
        (np.array([[0, 0.5], [0, 0]]), "non-negative integers"),
        (np.zeros((3, 3)), "shape"),
        (np.array([[0, 99], [0, 0]]), "idle"),
    ],
)
def test_invalid_rebalancing_flows_raise(flows, message):
    sim = MacroSim(grid_city(1, 2, horizon=4))
    sim.reset(np.random.default_rng(0))
    with pytest.raises(ValueError, match=message):
        sim.apply_rebalance(flows)


def test_dispatch_cannot_serve_more_than_requested():
    sim = MacroSim(grid_city(1, 2, horizon=4))
    sim.reset(np.random.default_rng(0))
    sim.backlog[:] = 0
    with pytest.raises(ValueError, match="open"):
        sim.apply_dispatch(np.array([[0, 1], [0, 0]]))


def test_episode_has_horizon_dispatches_and_one_fewer_rebalancing(small_city):
    system = FleetSystem(small_city)
    system.reset(0)
    steps = 0
    while not system.done:
        system.step(np.full(small_city.n_regions, -1))
        steps += 1
    assert steps == small_city.horizon - 1
    with pytest.raises(RuntimeError):
        system.sim.advance()
