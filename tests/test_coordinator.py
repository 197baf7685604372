"""The fast solvers reach the cvxpy reference objective, satisfy every constraint and return integers."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from marl_amod.coordinator import (
    Coordinator,
    desired_targets,
    greedy_dispatch,
    min_cost_rebalance,
)
from marl_amod.coordinator.rebalance import satisfies_triangle_inequality
from marl_amod.coordinator.reference import lp_dispatch, lp_rebalance
from marl_amod.errors import SolverError


def random_dispatch_instance(rng: np.random.Generator, n: int):
    idle = rng.integers(0, 12, size=n)
    demand = rng.poisson(rng.uniform(0, 3), size=(n, n))
    margin = rng.normal(5, 6, size=(n, n))  # some negative margins: never worth serving
    return idle, demand, margin


def random_rebalance_instance(rng: np.random.Generator, n: int, metric: bool):
    idle = rng.integers(0, 15, size=n)
    if metric:  # travel times from points on a grid obey the triangle inequality
        pts = rng.integers(0, 6, size=(n, 2))
        cost = np.abs(pts[:, None, :] - pts[None, :, :]).sum(-1) + 1
    else:
        cost = rng.integers(1, 20, size=(n, n))
    np.fill_diagonal(cost, 0)
    weights = rng.dirichlet(np.full(n, 0.5))
    target = desired_targets(weights, int(idle.sum()))
    return idle, target, cost


def check_dispatch_feasible(x, idle, demand):
    assert x.dtype.kind == "i"
    assert np.all(x >= 0) and np.all(x <= demand)
    assert np.all(x.sum(axis=1) <= idle)


def check_rebalance_feasible(y, idle, target):
    assert y.dtype.kind == "i"
    assert np.all(y >= 0) and np.all(np.diag(y) == 0)
    assert np.all(y.sum(axis=1) <= idle)
    after = idle - y.sum(axis=1) + y.sum(axis=0)
    assert np.all(after >= np.maximum(target, 0))
    assert after.sum() == idle.sum()


@pytest.mark.parametrize("seed", range(25))
def test_greedy_dispatch_matches_cvxpy_objective(seed):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 12))
    idle, demand, margin = random_dispatch_instance(rng, n)
    fast = greedy_dispatch(idle, demand, margin)
    ref = lp_dispatch(idle, demand, margin)
    check_dispatch_feasible(fast, idle, demand)
    check_dispatch_feasible(ref, idle, demand)
    assert (fast * margin).sum() == pytest.approx((ref * margin).sum(), rel=1e-9, abs=1e-6)


@pytest.mark.parametrize("seed", range(25))
@pytest.mark.parametrize("metric", [True, False])
def test_min_cost_rebalance_matches_cvxpy_objective(seed, metric):
    rng = np.random.default_rng(seed)
    n = int(rng.integers(2, 12))
    idle, target, cost = random_rebalance_instance(rng, n, metric)
    assert satisfies_triangle_inequality(cost) or not metric
    fast = min_cost_rebalance(idle, target, cost, metric=satisfies_triangle_inequality(cost))
    full = min_cost_rebalance(idle, target, cost, metric=False)
    ref = lp_rebalance(idle, target, cost)
    for y in (fast, full, ref):
        check_rebalance_feasible(y, idle, target)
    assert (fast * cost).sum() == (ref * cost).sum() == (full * cost).sum()


def test_triangle_violation_is_exploited_by_the_full_network():
    # going 0->2 directly costs 10, but 0->1 and 1->2 cost 1 each: the exact LP chains moves
    cost = np.array([[0, 1, 10], [1, 0, 1], [10, 1, 0]])
    idle, target = np.array([1, 1, 0]), np.array([0, 1, 1])
    assert not satisfies_triangle_inequality(cost)
    y = min_cost_rebalance(idle, target, cost, metric=False)
    check_rebalance_feasible(y, idle, target)
    assert (y * cost).sum() == 2 == (lp_rebalance(idle, target, cost) * cost).sum()


@settings(max_examples=60, deadline=None)
@given(
    idle=st.lists(st.integers(0, 30), min_size=2, max_size=9),
    data=st.data(),
)
def test_rebalance_feasible_for_any_targets_within_the_fleet(idle, data):
    idle = np.array(idle)
    n = len(idle)
    weights = np.array(data.draw(st.lists(st.floats(0, 1), min_size=n, max_size=n)))
    target = desired_targets(weights, int(idle.sum()))
    cost = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :])
    y = min_cost_rebalance(idle, target, cost, metric=True)
    if weights.sum() <= 0:
        assert np.all(target == -1) and not y.any()
    check_rebalance_feasible(y, idle, target)
    assert target.sum() <= idle.sum()


def test_desired_targets_floor_the_share_of_the_fleet():
    t = desired_targets(np.array([1.0, 1.0, 2.0]), 10)
    assert t.tolist() == [2, 2, 5]
    assert desired_targets(np.zeros(3), 10).tolist() == [-1, -1, -1]


def test_infeasible_targets_raise():
    with pytest.raises(SolverError, match="only 3 vehicles"):
        min_cost_rebalance(np.array([1, 2]), np.array([3, 3]), np.array([[0, 1], [1, 0]]))


def test_coordinator_backends_agree_on_a_city_step(small_city):
    rng = np.random.default_rng(0)
    fast = Coordinator(small_city, solver="fast")
    slow = Coordinator(small_city, solver="cvxpy")
    idle = small_city.initial_vehicles
    demand = rng.poisson(small_city.demand_rate[3])
    x_fast, x_slow = fast.dispatch(idle, demand, 3), slow.dispatch(idle, demand, 3)
    margin = fast.margin(3)
    assert (x_fast * margin).sum() == pytest.approx((x_slow * margin).sum())
    target = fast.targets(rng.dirichlet(np.ones(small_city.n_regions)), idle)
    y_fast, y_slow = fast.rebalance(idle, target), slow.rebalance(idle, target)
    cost = small_city.reb_cost
    assert (y_fast * cost).sum() == pytest.approx((y_slow * cost).sum())


def test_revenue_objective_ignores_trip_cost(small_city):
    c = Coordinator(small_city, objective="revenue")
    assert np.array_equal(c.margin(0), small_city.price[0])
    profit = Coordinator(small_city).margin(0)  # the fare minus beta x step length x trip time, by hand
    np.testing.assert_allclose(profit, small_city.price[0] - small_city.beta * small_city.tstep * small_city.trip_time[0])
    off_diagonal = ~np.eye(small_city.n_regions, dtype=bool)
    assert np.all(profit[off_diagonal] < small_city.price[0][off_diagonal])  # every trip off the diagonal costs something


def test_rebalancing_with_a_paid_stay_still_solves_when_nobody_is_short() -> None:
    """Plus-one prices 'a region replaces its own departures' above any move: with such a diagonal
    no shortfall does not mean no move, so the solver must run (the free-stay shortcut must not)."""
    cost = np.array([[10, 1], [1, 10]])
    flows = min_cost_rebalance(np.array([3, 3]), np.array([1, 1]), cost)
    np.testing.assert_array_equal(flows, [[0, 1], [1, 0]])  # each region is refilled by the other
