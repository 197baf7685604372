"""MPC: the LP's solution obeys the simulator's flow model, reduces to the coordinator, and pays off."""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.baselines import EqualDistribution
from marl_amod.baselines.base import round_preserving_sum, target_from_flows
from marl_amod.baselines.mpc import (
    CvxpyMPC,
    MPCForecast,
    MPCOracle,
    MPCScenarios,
    lp_matrices,
    plan_data,
    solve_scenarios,
    solve_scipy,
)
from marl_amod.errors import ConfigError, SolverError
from marl_amod.evaluation import episode_seeds, evaluate
from marl_amod.policies import make_policy
from marl_amod.scenario import City
from marl_amod.system import FleetSystem


def _mid_episode(city: City, steps: int = 2, seed: int = 3) -> FleetSystem:
    """A system a few steps in, so that vehicles are on the road."""
    system = FleetSystem(city)
    system.reset(seed)
    policy = EqualDistribution()
    policy.reset(system, np.random.default_rng(0))
    for _ in range(steps):
        system.step(policy.target(system))
    return system


def _oracle_data(system: FleetSystem, horizon: int):
    sim = system.sim
    steps = sim.t + np.arange(horizon)
    demand = sim.demand[np.minimum(steps, sim.demand.shape[0] - 1)] * (steps < sim.demand.shape[0])[:, None, None]
    return plan_data(system.city, sim.t, sim.idle, sim.arrivals, demand, horizon)


def _replay(data, plan) -> np.ndarray:
    """Idle vehicles per relative step implied by the plan, recomputed with explicit loops."""
    h, n = data.demand.shape[0], data.idle.shape[0]
    avail = np.zeros((h, n))
    avail[0] = data.idle
    for k in range(1, h):
        avail[k] = data.arrivals[k - 1]
    for s in range(h):
        for i in range(n):
            for j in range(n):
                for flows, tau in ((plan.x, data.trip_time[s, i, j]), (plan.y, data.reb_time[i, j])):
                    if s + tau + 1 < h:
                        avail[s + tau + 1, j] += flows[s, i, j]
    return avail


@pytest.mark.parametrize("horizon", [1, 3, 6])
def test_mpc_lp_solution_satisfies_conservation_demand_and_signs(tiny_city, horizon):
    system = _mid_episode(tiny_city)
    data = _oracle_data(system, horizon)
    plan = solve_scipy(data)
    assert np.all(plan.x >= -1e-9) and np.all(plan.y >= -1e-9)
    assert np.all(plan.x <= data.demand + 1e-9)
    assert np.allclose(plan.x[0], 0)  # dispatch at t is already applied
    used = plan.x.sum(axis=2) + plan.y.sum(axis=2)  # every available vehicle is dispatched, moved or stays
    assert np.allclose(used, _replay(data, plan))
    assert np.allclose(plan.y, np.rint(plan.y)) and np.allclose(plan.x, np.rint(plan.x))  # vertex of a network LP
    cost, a, b, _ = lp_matrices(data)
    z = np.concatenate([plan.x.ravel(), plan.y.ravel()])
    assert np.allclose(a @ z, b)
    assert plan.objective == pytest.approx(-cost @ z)


def test_mpc_with_one_step_and_no_future_is_dispatch_plus_min_cost_rebalancing(tiny_city):
    system = FleetSystem(tiny_city)
    sim = system.sim
    sim.reset(np.random.default_rng(5))
    idle_before = sim.idle.copy()
    data = plan_data(tiny_city, 0, idle_before, sim.arrivals, sim.requests()[None], 1, plan_dispatch_now=True)
    plan = solve_scipy(data)
    x = system.coordinator.dispatch(idle_before, sim.requests(), 0)
    margin = system.coordinator.margin(0)
    assert plan.objective == pytest.approx(float((x * margin).sum()))
    # with nothing to gain ahead, the planned rebalancing is the coordinator's for 'no wish': none
    idle_after = idle_before - x.sum(axis=1)
    off = plan.y[0] * (1 - np.eye(tiny_city.n_regions))
    assert np.allclose(off, system.coordinator.rebalance(idle_after, np.full(tiny_city.n_regions, -1)))
    # and the policy's target then makes the coordinator move nothing either
    system.reset(5)
    policy = MPCOracle(horizon=1)
    policy.reset(system, np.random.default_rng(0))
    target = policy.target(system)
    assert np.array_equal(target, system.sim.idle)
    assert not system.coordinator.rebalance(system.sim.idle, target).any()


def test_target_makes_the_coordinator_reproduce_the_planned_distribution(tiny_city):
    system = _mid_episode(tiny_city)
    plan = solve_scipy(_oracle_data(system, 6))
    idle = system.sim.idle
    target = target_from_flows(idle, plan.y[0])
    assert target.sum() == idle.sum() and np.all(target >= 0)
    flows = system.coordinator.rebalance(idle, target)
    assert np.array_equal(idle - flows.sum(axis=1) + flows.sum(axis=0), target)
    planned_cost = float((plan.y[0] * tiny_city.reb_cost).sum())
    assert float((flows * tiny_city.reb_cost).sum()) <= planned_cost + 1e-6


def test_round_preserving_sum_keeps_total_and_stays_close():
    values = np.array([0.4, 1.6, 2.5, 0.5, 0.0])
    r = round_preserving_sum(values, 5)
    assert r.sum() == 5 and np.all(r >= 0) and np.all(np.abs(r - values) < 1)


def test_cvxpy_parameterised_path_matches_scipy(tiny_city):
    system = _mid_episode(tiny_city)
    data = _oracle_data(system, 4)
    cvx = CvxpyMPC(tiny_city, 4)
    assert cvx.solve(data).objective == pytest.approx(solve_scipy(data).objective, rel=1e-6)
    system.step(np.full(tiny_city.n_regions, -1))
    data2 = _oracle_data(system, 4)  # re-solve the same compiled problem with new data
    assert cvx.solve(data2).objective == pytest.approx(solve_scipy(data2).objective, rel=1e-6)


def test_infeasible_lp_raises_solver_error(tiny_city):
    system = _mid_episode(tiny_city)
    data = _oracle_data(system, 3)
    data.idle = data.idle.copy()
    data.idle[0] = -5.0  # no flows can be negative: infeasible
    with pytest.raises(SolverError):
        solve_scipy(data)


def _one_hub_city() -> City:
    """All vehicles start in region 0; every request starts in region 3 and ends in region 0.

    Without rebalancing a vehicle serves one trip and is stranded; equal distribution sends only
    a quarter of the idle fleet to the one region with demand. Rebalancing clearly pays.
    """
    n, steps, horizon = 4, 24, 12
    pos = np.column_stack([np.arange(n), np.zeros(n)]).astype(float)
    reb = np.abs(np.arange(n)[:, None] - np.arange(n)[None, :]).astype(np.int64)
    rate = np.zeros((steps, n, n))
    rate[:, 3, 0] = 8.0
    trip = np.broadcast_to(np.maximum(reb, 1), (steps, n, n)).copy()
    price = 10.0 * trip
    edges = np.array([[0, 1, 1, 2, 2, 3], [1, 0, 2, 1, 3, 2]])
    return City(
        name="one_hub", tstep=3.0, horizon=horizon, beta=0.5, demand_rate=rate, price=price, trip_time=trip,
        reb_time=reb, initial_vehicles=np.array([40, 0, 0, 0]), edge_index=edges, positions=pos,
    )


def test_mpc_oracle_beats_equal_distribution_where_rebalancing_pays():
    city = _one_hub_city()
    ed = evaluate("equal-distribution", city, episodes=3)["metrics"]["profit"]["mean"]
    oracle = evaluate(MPCOracle(horizon=8), city, episodes=3)["metrics"]["profit"]["mean"]
    none = evaluate("no-rebalancing", city, episodes=3)["metrics"]["profit"]["mean"]
    assert oracle > 1.2 * ed and ed > none


def test_mpc_forecast_noise_is_seeded_and_targets_are_feasible(tiny_city):
    results = [evaluate(MPCForecast(horizon=4, noise=0.3), tiny_city, episodes=2, seed=1) for _ in range(2)]
    assert results[0]["per_episode"] == results[1]["per_episode"]
    system = FleetSystem(tiny_city)
    system.reset(0)
    policy = make_policy("mpc-forecast", tiny_city)
    policy.reset(system, np.random.default_rng(0))
    while not system.done:
        target = policy.target(system)
        assert target.dtype.kind == "i" and target.sum() == system.sim.idle.sum() and np.all(target >= 0)
        system.step(target)


def test_mpc_offers_requests_still_waiting_to_the_next_step(tiny_city):
    """With max_wait > 0 the plan sees the backlog left after dispatch, not just new demand."""
    system = FleetSystem(tiny_city, max_wait=2)
    system.reset(0)
    sim = system.sim
    sim.backlog[0] += 5  # more requests than the fleet serves: some stay open
    sim.backlog[1] += 2  # these are one step old and may wait once more
    oracle = MPCOracle(horizon=3)
    oracle.reset(system, np.random.default_rng(0))
    believed = oracle.believed_demand(system)
    forecast = oracle.forecast(system, sim.t + np.arange(3))
    np.testing.assert_array_equal(believed[1] - forecast[1], sim.backlog[:2].sum(axis=0))
    np.testing.assert_array_equal(believed[[0, 2]], forecast[[0, 2]])
    no_wait = FleetSystem(tiny_city)
    no_wait.reset(0)
    np.testing.assert_array_equal(oracle.believed_demand(no_wait), oracle.forecast(no_wait, np.arange(3)))


def _forecast_plan(system: FleetSystem, scale: float, horizon: int = 6):
    """The LP solved by hand on ``scale`` x the expected demand (what demand_scale promises)."""
    city, sim = system.city, system.sim
    steps = sim.t + np.arange(horizon)
    rate = city.forecast_rate[np.minimum(steps, city.forecast_rate.shape[0] - 1)]
    rate = rate * (steps < city.forecast_rate.shape[0])[:, None, None]
    return solve_scipy(plan_data(city, sim.t, sim.idle, sim.arrivals, scale * rate, horizon))


@pytest.mark.parametrize("steps", [0, 2])
def test_mpc_forecast_demand_scale_plans_on_scaled_expected_demand(small_city, steps):
    system = _mid_episode(small_city, steps=steps)
    plans = {}
    for scale in (1.0, 1.5):
        policy = make_policy("mpc-forecast", small_city, horizon=6, **({} if scale == 1.0 else {"demand_scale": scale}))
        policy.reset(system, np.random.default_rng(0))
        plans[scale] = policy.plan(system)
        expected = _forecast_plan(system, scale)
        assert plans[scale].objective == pytest.approx(expected.objective)
        np.testing.assert_allclose(plans[scale].x.sum(axis=(1, 2)), expected.x.sum(axis=(1, 2)), atol=1e-6)
    assert plans[1.5].x.sum() > plans[1.0].x.sum() + 1  # plans to serve more of the (larger) demand


def test_mpc_forecast_demand_scale_moves_more_vehicles_at_the_start_of_the_day(small_city):
    system = FleetSystem(small_city)
    system.reset(3)
    moved = {}
    for scale in (1.0, 1.5):
        policy = MPCForecast(horizon=6, demand_scale=scale)
        policy.reset(system, np.random.default_rng(0))
        y0 = policy.plan(system).y[0]
        moved[scale] = y0.sum() - np.trace(y0)
    assert moved[1.5] > moved[1.0] + 1


def test_mpc_forecast_demand_scale_names_the_policy_and_rejects_bad_values():
    assert MPCForecast().name == "mpc-forecast" and MPCForecast(demand_scale=1.0).name == "mpc-forecast"
    assert MPCForecast(demand_scale=1.25).name == "mpc-forecast+scale1.25"
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="demand_scale"):
            MPCForecast(demand_scale=bad)


class _MeanScenarios(MPCScenarios):
    """Every scenario is the expected demand: the two-stage LP must then plan as MPC-Forecast does."""

    def sample_demand(self, mean: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        return np.broadcast_to(mean, (self.scenarios, *mean.shape)).astype(float)


@pytest.mark.parametrize("steps", [0, 2])
def test_mpc_scenarios_all_equal_to_the_mean_plan_as_mpc_forecast(small_city, steps):
    system = _mid_episode(small_city, steps=steps)
    forecast, scenarios = MPCForecast(horizon=6), _MeanScenarios(horizon=6, scenarios=3)
    for policy in (forecast, scenarios):
        policy.reset(system, np.random.default_rng(0))
    plain, shared = forecast.plan(system), scenarios.plan(system)
    assert shared.objective == pytest.approx(plain.objective, rel=1e-9)
    # the shared first step is an optimal first step of the mean plan: fixing it there loses nothing
    data = plan_data(small_city, system.sim.t, system.sim.idle, system.sim.arrivals, forecast.believed_demand(system), 6)
    cost, a, b, ub = lp_matrices(data)
    n = small_city.n_regions
    lo = np.zeros_like(ub)
    first = slice(6 * n * n, 7 * n * n)
    lo[first] = ub[first] = shared.y[0].ravel()
    from scipy.optimize import linprog

    res = linprog(cost, A_eq=a, b_eq=b, bounds=np.column_stack([lo, ub]), method="highs")
    assert res.status == 0 and -res.fun == pytest.approx(plain.objective, rel=1e-9)


def test_mpc_scenarios_share_the_first_step_and_each_scenario_conserves_vehicles(small_city):
    system = _mid_episode(small_city, steps=2)
    policy = MPCScenarios(horizon=5, scenarios=3)
    policy.reset(system, np.random.default_rng(4))
    demand = policy.scenario_demand(system)
    assert demand.shape == (3, 5, small_city.n_regions, small_city.n_regions)
    assert not np.array_equal(demand[0], demand[1])  # the draws differ
    policy.reset(system, np.random.default_rng(4))
    datas = [plan_data(small_city, system.sim.t, system.sim.idle, system.sim.arrivals, d, 5) for d in demand]
    plan = solve_scenarios(datas)
    # each scenario solved alone, its first step fixed to the shared one, is feasible and its
    # profits average to the joint objective; each is at most its own unconstrained optimum
    from scipy.optimize import linprog

    total = 0.0
    n = small_city.n_regions
    for data in datas:
        cost, a, b, ub = lp_matrices(data)
        lo = np.zeros_like(ub)
        first = slice(5 * n * n, 6 * n * n)
        lo[first] = ub[first] = plan.y[0].ravel()
        res = linprog(cost, A_eq=a, b_eq=b, bounds=np.column_stack([lo, ub]), method="highs")
        assert res.status == 0
        total += -res.fun
        assert -res.fun <= solve_scipy(data).objective + 1e-6
    assert plan.objective == pytest.approx(total / 3, rel=1e-9)
    assert np.allclose(plan.y[0].sum(axis=1), system.sim.idle)  # the whole idle fleet is placed
    assert plan.objective == pytest.approx(policy.plan(system).objective)  # the policy draws the same


def test_mpc_scenarios_targets_are_feasible_and_runs_reproduce_by_seed(tiny_city):
    system = FleetSystem(tiny_city)
    system.reset(0)
    policy = make_policy("mpc-scenarios", tiny_city, horizon=4, scenarios=3)
    policy.reset(system, np.random.default_rng(0))
    while not system.done:
        target = policy.target(system)
        assert target.dtype.kind == "i" and target.sum() == system.sim.idle.sum() and np.all(target >= 0)
        flows = system.coordinator.rebalance(system.sim.idle, target)
        assert np.array_equal(system.sim.idle - flows.sum(axis=1) + flows.sum(axis=0), target)
        system.step(target)
    runs = [evaluate("mpc-scenarios", tiny_city, episodes=2, seed=s, horizon=4, scenarios=3) for s in (1, 1, 2)]
    assert runs[0]["per_episode"] == runs[1]["per_episode"]
    assert runs[0]["per_episode"] != runs[2]["per_episode"]
    assert runs[0]["policy"] == "mpc-scenarios+s3" and MPCScenarios().name == "mpc-scenarios"


def test_mpc_scenarios_common_random_numbers_make_the_plan_a_function_of_the_state(small_city):
    """With ``crn_seed`` two calls in the same state plan the same, whatever the policy rng; without
    it they do not (the clone's labels were the teacher's own sampling noise)."""
    system = _mid_episode(small_city, steps=2)
    crn = MPCScenarios(horizon=5, scenarios=3, crn_seed=7)
    sampling = MPCScenarios(horizon=5, scenarios=3)
    for policy in (crn, sampling):
        policy.reset(system, np.random.default_rng(0))
    same = [crn.scenario_demand(system) for _ in range(2)]
    crn.reset(system, np.random.default_rng(1))  # another episode's policy rng
    same.append(crn.scenario_demand(system))
    assert np.array_equal(same[0], same[1]) and np.array_equal(same[0], same[2])
    assert not np.array_equal(same[0][0], same[0][1])  # still S different scenarios
    assert not np.array_equal(sampling.scenario_demand(system), sampling.scenario_demand(system))
    # the draws depend on the step and the seed, not on the fleet: another state at the same step
    # shares them, the next step and another seed do not
    other = _mid_episode(small_city, steps=2, seed=11)
    assert np.array_equal(crn.scenario_demand(other), same[0])
    assert not np.array_equal(MPCScenarios(horizon=5, scenarios=3, crn_seed=8).scenario_demand(system), same[0])
    later = _mid_episode(small_city, steps=3)
    assert not np.array_equal(crn.scenario_demand(later), same[0])
    targets = [crn.target(system) for _ in range(3)]
    assert all(np.array_equal(targets[0], t) for t in targets[1:])
    assert crn.name == "mpc-scenarios+s3+crn7" and MPCScenarios(crn_seed=0).name == "mpc-scenarios+crn0"


def test_mpc_scenarios_common_random_numbers_are_not_an_episode_demand_stream(small_city):
    """Episode k of seed s draws its demand from (s, k): step t's scenarios from (crn_seed, t) would
    be episode t's own demand stream, so at step 0 of episode 0 of seed crn_seed a scenario would
    be the episode's future demand itself (the forecast rates are the demand rates here)."""
    horizon = 5
    for seed, episode in [(0, 0), (7, 0)]:
        demand_seed, policy_rng = episode_seeds(seed, episode)
        system = FleetSystem(small_city)
        system.reset(demand_seed)
        policy = MPCScenarios(horizon=horizon, scenarios=4, crn_seed=seed)
        policy.reset(system, policy_rng)
        future = system.sim.demand[:horizon]
        assert not any(np.array_equal(s, future) for s in policy.scenario_demand(system))


@pytest.mark.parametrize("bad", [-1, 2.5, "3", True])
def test_mpc_scenarios_rejects_a_bad_crn_seed(bad):
    with pytest.raises(ConfigError, match="crn_seed"):
        MPCScenarios(crn_seed=bad)


@pytest.mark.parametrize("bad", [0, -2, 2.5, "4", True])
def test_mpc_scenarios_rejects_a_bad_scenario_count(bad):
    with pytest.raises(ConfigError, match="scenarios"):
        MPCScenarios(scenarios=bad)
    with pytest.raises(ConfigError):
        solve_scenarios([])


def test_mpc_scenarios_add_the_waiting_requests_to_every_scenario(tiny_city):
    system = FleetSystem(tiny_city, max_wait=2)
    system.reset(0)
    system.sim.backlog[0] += 5
    policy = _MeanScenarios(horizon=3, scenarios=2)
    policy.reset(system, np.random.default_rng(0))
    demand = policy.scenario_demand(system)
    forecast = policy.forecast(system, system.sim.t + np.arange(3))
    for d in demand:
        np.testing.assert_allclose(d[1] - forecast[1], system.sim.carried_over())
        np.testing.assert_allclose(d[[0, 2]], forecast[[0, 2]])
    assert system.sim.carried_over().sum() > 0
