"""What the env does: determinism, action rules, feasible flows, rewards, observations."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import marl_amod
from marl_amod.env import actions as act
from marl_amod.env.observations import local_observations, neighbour_table, split_local
from marl_amod.errors import ActionError, ConfigError
from marl_amod.scenario import grid_city
from marl_amod.sim.macro import MacroSim
from marl_amod.system import FleetSystem
from tests.conftest import needs_data


def _const(env, value: float) -> dict:
    return {a: np.array([value], dtype=np.float32) for a in env.agents}


def _run(env, seed: int, policy_seed: int = 0) -> list:
    rng = np.random.default_rng(policy_seed)
    obs, _ = env.reset(seed=seed)
    trace = [obs]
    while env.agents:
        a = {k: rng.random(1).astype(np.float32) for k in env.agents}
        trace.append(env.step(a))
    return trace


def _same(a, b) -> bool:
    if isinstance(a, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, (tuple, list)):
        return len(a) == len(b) and all(_same(x, y) for x, y in zip(a, b, strict=True))
    if isinstance(a, np.ndarray):
        return np.array_equal(a, b)
    return a == b


def test_two_envs_with_the_same_seed_and_actions_stay_identical_for_a_whole_episode() -> None:
    t1 = _run(marl_amod.parallel_env(), seed=11)
    t2 = _run(marl_amod.parallel_env(), seed=11)
    assert len(t1) == 20  # reset + horizon - 1 steps
    assert _same(t1, t2)
    t3 = _run(marl_amod.parallel_env(), seed=12)
    assert not _same(t1, t3)


def test_reset_seed_draws_the_same_demand_as_the_fleet_system(small_city) -> None:
    env = marl_amod.parallel_env(small_city)
    env.reset(seed=5)
    system = FleetSystem(small_city)
    system.reset(5)
    assert np.array_equal(env.system.sim.demand, system.sim.demand)


def test_unseeded_resets_continue_the_first_seed(tiny_city) -> None:
    def demands(env):
        env.reset(seed=3)
        return [env.system.sim.demand.copy() for _ in range(3) if env.reset() is not None]

    a, b = demands(marl_amod.parallel_env(tiny_city)), demands(marl_amod.parallel_env(tiny_city))
    assert all(np.array_equal(x, y) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0], a[1])


def test_episode_truncates_every_agent_at_the_horizon(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city)
    with pytest.raises(RuntimeError, match="reset.. was never called"):  # not "the episode is over"
        env.step({})
    env.reset(seed=0)
    for _ in range(tiny_city.horizon - 2):
        _, _, term, trunc, _ = env.step(_const(env, 0.5))
        assert not any(trunc.values()) and not any(term.values())
    _, _, term, trunc, _ = env.step(_const(env, 0.5))
    assert all(trunc.values()) and not any(term.values()) and env.agents == []
    with pytest.raises(RuntimeError, match="every agent was truncated.*call reset"):
        env.step({})


@pytest.mark.parametrize("max_cycles", [1, 3, 99])
def test_max_cycles_truncates_at_the_cap_or_the_horizon(small_city, max_cycles) -> None:
    env = marl_amod.parallel_env(small_city, max_cycles=max_cycles)
    for seed in (0, 1):  # the count restarts on reset
        env.reset(seed=seed)
        steps = 0
        while env.agents:
            _, _, term, trunc, infos = env.step(_const(env, 0.5))
            steps += 1
            assert all(trunc.values()) == (env.agents == []) and not any(term.values())
        assert steps == min(max_cycles, small_city.horizon - 1)
        # the episode's rates are over the steps it ran (step 0 and each control step), not the whole horizon
        busy = env.system.sim.totals.busy_vehicle_steps.sum()
        assert infos["region_0"]["system_utilization"] == pytest.approx(busy / (small_city.fleet_size * (steps + 1)))


def test_reward_scale_multiplies_rewards_and_leaves_infos_in_money(small_city) -> None:
    from marl_amod.env.rewards import typical_step_revenue

    envs = {s: marl_amod.parallel_env(small_city, reward_mode="local", reward_scale=s) for s in (1.0, 0.01, "auto")}
    auto = 1.0 / typical_step_revenue(small_city)
    assert envs["auto"].reward_scale == pytest.approx(auto) and 0 < auto < 1
    for e in envs.values():
        e.reset(seed=2)
    while envs[1.0].agents:
        out = {s: e.step(_const(e, 0.3)) for s, e in envs.items()}
        r = {s: np.array(list(o[1].values())) for s, o in out.items()}
        assert np.abs(r[1.0]).sum() > 0
        np.testing.assert_allclose(r[0.01], 0.01 * r[1.0], rtol=1e-12)
        np.testing.assert_allclose(r["auto"], auto * r[1.0], rtol=1e-12)
        assert out["auto"][4] == out[1.0][4]  # infos: money as booked


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.array([np.nan], dtype=np.float32), "not finite"),
        (np.array([np.inf], dtype=np.float32), "not finite"),
        (np.array([0.2, 0.3], dtype=np.float32), "shape"),
        (np.zeros((1, 1), dtype=np.float32), "shape"),
        ("lots", "number"),
    ],
)
def test_invalid_action_raises_action_error_naming_the_agent(tiny_city, bad, match) -> None:
    env = marl_amod.parallel_env(tiny_city)
    env.reset(seed=0)
    actions = _const(env, 0.5)
    actions["region_4"] = bad
    with pytest.raises(ActionError, match=match) as err:
        env.step(actions)
    assert "region_4" in str(err.value)


def test_missing_and_unknown_agents_raise(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city)
    env.reset(seed=0)
    actions = _const(env, 0.5)
    del actions["region_2"]
    with pytest.raises(ActionError, match="region_2"):
        env.step(actions)
    with pytest.raises(ActionError, match="unknown"):
        env.step({**_const(env, 0.5), "region_99": np.array([0.1])})


def test_out_of_range_actions_are_clipped_into_the_unit_interval() -> None:
    agents = ["a", "b", "c", "d"]
    got = act.joint_action({"a": np.array([3.0]), "b": -1e-8, "c": np.array([0.25]), "d": np.array([-7.5])}, agents)
    assert np.array_equal(got, [1.0, 0.0, 0.25, 0.0])


@pytest.mark.parametrize("odd", [True, np.bool_(False), np.array([True]), [0.5], np.array(["0.5"]), 0.5 + 1j])
def test_actions_of_any_other_type_take_the_checked_path(odd) -> None:
    """The one-array shortcut takes plain real numbers only: a bool mixed into float actions
    would otherwise be read as 1.0/0.0, a one-element list or string as its number."""
    agents = ["a", "b", "c"]
    shape = np.shape(odd)  # the others alike, so one array call would accept the mix
    actions = {"a": np.full(shape, 0.5, dtype=np.float32), "b": np.full(shape, 0.25), "c": odd}
    if isinstance(odd, list):  # a list of one number is a valid (1,) action on the checked path
        assert np.array_equal(act.joint_action(actions, agents), [0.5, 0.25, 0.5])
        return
    with pytest.raises(ActionError, match="action of c"):
        act.joint_action(actions, agents)


def test_stacked_actions_equal_the_agent_by_agent_reading() -> None:
    """Every mix of scalar kinds and shapes () / (1,) gives the numbers np.asarray(value, float64) gives."""
    values = [np.float32(0.1), 0.7, 2, np.int64(0), np.array(0.3), np.array([0.9], dtype=np.float16), np.array([1.5])]
    agents = [f"r{k}" for k in range(len(values))]
    got = act.joint_action(dict(zip(agents, values, strict=True)), agents)
    expect = np.clip([float(np.asarray(v, dtype=np.float64).reshape(())) for v in values], 0.0, 1.0)
    assert got.dtype == np.float64 and np.array_equal(got, expect)


def test_a_gaussian_policy_steps_the_env_like_its_clipped_actions(small_city) -> None:
    """Unclipped Gaussian samples (negative ones included) act exactly as their clipped values."""
    rng = np.random.default_rng(0)
    raw_env, clip_env = marl_amod.parallel_env(small_city), marl_amod.parallel_env(small_city)
    raw_env.reset(seed=4)
    clip_env.reset(seed=4)
    while raw_env.agents:
        raw = {a: rng.normal(0.3, 1.0, size=1).astype(np.float32) for a in raw_env.agents}
        _, r1, *_ = raw_env.step(raw)
        _, r2, *_ = clip_env.step({a: np.clip(v, 0.0, 1.0) for a, v in raw.items()})
        assert r1 == r2
        assert np.array_equal(raw_env.last_outcome.rebalancing, clip_env.last_outcome.rebalancing)


@pytest.mark.parametrize("value", [-0.5, -1e-8, 1.5])
def test_strict_actions_raise_on_finite_values_outside_the_space(tiny_city, value) -> None:
    env = marl_amod.parallel_env(tiny_city, strict_actions=True)
    env.reset(seed=0)
    actions = {**_const(env, 0.5), "region_3": np.array([value], dtype=np.float64)}
    with pytest.raises(ActionError, match="region_3.*outside the action space"):
        env.step(actions)
    env.step(_const(env, 1.0))  # the bounds themselves are inside


def test_all_zero_weights_mean_no_rebalancing(small_city) -> None:
    env = marl_amod.parallel_env(small_city)
    env.reset(seed=0)
    for _ in range(4):
        _, _, _, _, infos = env.step(_const(env, 0.0))
        assert env.last_outcome.rebalancing.sum() == 0
        assert infos["region_0"]["system_rebalancing_cost"] == 0.0


def test_logit_mode_all_zero_is_uniform_and_a_high_action_attracts_vehicles(small_city) -> None:
    w = act.weights(np.zeros(4), "logit")
    assert np.allclose(w, 0.25)
    w = act.weights(np.array([1.0, 0.0, 0.0, 0.0]), "logit")
    assert w[0] > 0.999 and np.isclose(w.sum(), 1.0)
    env = marl_amod.parallel_env(small_city, action_mode="logit")
    env.reset(seed=0)
    idle = env.system.sim.idle.sum()
    env.step({a: np.array([1.0 if a == "region_5" else 0.0], dtype=np.float32) for a in env.agents})
    assert env.last_outcome.rebalancing[:, 5].sum() > 0.5 * idle - env.system.sim.idle[5]


def test_local_rewards_sum_to_the_team_reward_and_match_region_profit(small_city) -> None:
    team = marl_amod.parallel_env(small_city, reward_mode="team")
    local = marl_amod.parallel_env(small_city, reward_mode="local")
    team.reset(seed=2)
    local.reset(seed=2)
    rng = np.random.default_rng(0)
    while team.agents:
        actions = {a: rng.random(1).astype(np.float32) for a in team.agents}
        before = local.system.sim.totals.profit.copy()
        _, rt, *_ = team.step(actions)
        _, rl, *_ = local.step(actions)
        delta = local.system.sim.totals.profit - before  # profit booked to each departure region
        r_local = np.array([rl[a] for a in local.possible_agents])
        assert np.allclose(r_local, delta)
        assert np.isclose(r_local.sum(), rt["region_0"])
        assert len(set(rt.values())) == 1


class _SwappingSim(MacroSim):
    """A simulator that replaces its region view before every matching round (as SUMO does when
    travel times change) and matches three times per control step, booking each round's money
    with the city it holds at that moment."""

    dispatch_rounds = 3

    def _swap(self) -> None:
        k = len(self.swaps) % 4 + 1
        base = self.swaps[0] if self.swaps else self.city
        self.city = dataclasses.replace(base, price=base.price * (1.0 + 0.3 * k), trip_time=base.trip_time + k % 3)
        self.swaps.append(self.city)

    def reset(self, rng: np.random.Generator) -> None:
        self.swaps: list = []
        super().reset(rng)
        self._swap()

    def advance_round(self) -> None:
        self._swap()

    def advance(self) -> None:
        super().advance()
        self._swap()


def test_local_rewards_are_the_booked_money_when_the_simulator_replaces_its_city(small_city) -> None:
    env = marl_amod.parallel_env(small_city, reward_mode="local")
    env.system = FleetSystem(small_city, sim=_SwappingSim(small_city))
    env.reset(seed=3)
    rng = np.random.default_rng(1)
    steps_with_money = 0
    while env.agents:
        totals = env.system.sim.totals
        before = totals.revenue - totals.trip_cost - totals.rebalancing_cost
        _, rew, *_ = env.step({a: rng.random(1).astype(np.float32) for a in env.agents})
        booked = totals.revenue - totals.trip_cost - totals.rebalancing_cost - before
        r_local = np.array([rew[a] for a in env.possible_agents])
        np.testing.assert_allclose(r_local, booked, rtol=0, atol=1e-9)
        np.testing.assert_allclose(r_local.sum(), env.last_outcome.reward, rtol=1e-12)
        assert env.city is env.system.sim.city is not small_city
        steps_with_money += bool(np.any(booked != 0))
    assert len(env.system.sim.swaps) > 2 * small_city.horizon  # the view changed before every round
    assert steps_with_money > 0


def test_local_observation_layout_matches_features_and_neighbours(small_city) -> None:
    env = marl_amod.parallel_env(small_city)
    obs, _ = env.reset(seed=0)
    env.step(_const(env, 0.3))
    obs, *_ = env.step(_const(env, 0.7))
    x = env.graph()["x"]
    stacked = np.stack([obs[a] for a in env.possible_agents])
    assert np.array_equal(stacked, local_observations(env.system, 6, env.max_degree))
    own, context, neigh, mask = split_local(stacked)
    assert np.array_equal(own, x)
    idx, m = neighbour_table(small_city)
    assert np.array_equal(mask, m)
    src, dst = small_city.edge_index
    for i in (0, 5):  # a corner (2 neighbours) and an inner region (4 neighbours)
        expected = np.sort(src[dst == i])
        k = len(expected)
        assert mask[i].sum() == k and np.array_equal(neigh[i, :k], x[expected])
        assert not neigh[i, k:].any()
    hour = small_city.start_hour + 2 * small_city.tstep / 60
    assert np.allclose(context[0], [np.sin(2 * np.pi * hour / 24), np.cos(2 * np.pi * hour / 24), 2 / small_city.horizon])
    assert all(env.observation_space(a).contains(obs[a]) for a in obs)


def test_split_local_works_on_torch_batches() -> None:
    torch = pytest.importorskip("torch")
    env = marl_amod.parallel_env()
    obs, _ = env.reset(seed=0)
    batch = torch.from_numpy(np.stack([obs[a] for a in env.agents]))[None]  # (1, N, D)
    own, context, neigh, mask = split_local(batch)
    assert own.shape == (1, 16, 13) and context.shape == (1, 16, 3)
    assert neigh.shape == (1, 16, env.max_degree, 13) and mask.shape == (1, 16, env.max_degree)
    with pytest.raises(ValueError, match="layout"):
        split_local(np.zeros(20))


def test_state_and_graph_describe_the_whole_city(small_city) -> None:
    env = marl_amod.parallel_env(small_city)
    env.reset(seed=0)
    state = env.state()
    g = env.graph()
    assert state.dtype == np.float32 and state.shape == env.state_space.shape
    assert np.array_equal(state[:-3], g["x"].ravel())
    assert g["x"].shape == (16, 13) and g["x"].dtype == np.float32
    assert g["edge_index"].dtype == np.int64 and g["edge_index"].shape == small_city.edge_index.shape
    src, dst = g["edge_index"]
    assert g["edge_attr"].shape == (src.size, 2) and g["edge_attr"].dtype == np.float32
    assert np.allclose(g["edge_attr"][:, 0], small_city.reb_time[src, dst])
    assert np.allclose(g["edge_attr"][:, 1], small_city.reb_cost[src, dst])


def test_bad_configuration_raises_config_error(tiny_city) -> None:
    with pytest.raises(ConfigError, match="reward_mode"):
        marl_amod.parallel_env(reward_mode="selfish")
    with pytest.raises(ConfigError, match="action_mode"):
        marl_amod.parallel_env(action_mode="dirichlet")
    with pytest.raises(ConfigError, match="render_mode"):
        marl_amod.parallel_env(render_mode="ansi")
    with pytest.raises(ConfigError):
        marl_amod.parallel_env(hoirzon=5)  # typo in a scenario key
    with pytest.raises(ConfigError, match="overrides"):
        marl_amod.parallel_env(tiny_city, horizon=3)
    for bad in (0, -1.0, float("nan"), "big"):
        with pytest.raises(ConfigError, match="reward_scale"):
            marl_amod.parallel_env(tiny_city, reward_scale=bad)
    for bad in (0, 2.5, True):
        with pytest.raises(ConfigError, match="max_cycles"):
            marl_amod.parallel_env(tiny_city, max_cycles=bad)
    for key, bad in (("lookahead", True), ("reward_scale", True), ("strict_actions", "no"), ("strict_actions", 0),
                     ("arrivals_now", 1)):
        for make in (marl_amod.parallel_env, marl_amod.vector_env):  # the two faces read the same options
            with pytest.raises(ConfigError, match=key):
                make(tiny_city, **{key: bad})


@needs_data
def test_real_city_episode_runs_with_local_rewards() -> None:
    env = marl_amod.parallel_env("nyc_brooklyn", reward_mode="local", horizon=5)
    obs, _ = env.reset(seed=0)
    assert len(obs) == env.city.n_regions == 14
    while env.agents:
        obs, rew, *_ = env.step({a: env.action_space(a).sample() for a in env.agents})
    assert env.system.sim.vehicles() == env.city.fleet_size


# ---------------------------------------------------------------------- feasibility properties
_CITY = grid_city(3, 3, seed=1, horizon=6, vehicles_per_region=5, requests_per_region=3.0)
_N = _CITY.n_regions

tiny = st.floats(min_value=0.0, max_value=1e-30, allow_subnormal=True)
in_range = st.floats(min_value=0.0, max_value=1.0)
clipped = st.floats(min_value=-50.0, max_value=50.0)
one_hot = st.integers(0, _N - 1).map(lambda i: [1.0 if k == i else 0.0 for k in range(_N)])
joint = st.one_of(
    st.lists(in_range, min_size=_N, max_size=_N),
    st.lists(tiny, min_size=_N, max_size=_N),
    st.lists(clipped, min_size=_N, max_size=_N),
    st.lists(st.sampled_from([0.0, 1.0, 1e-12, 2.0]), min_size=_N, max_size=_N),
    one_hot,
    st.just([0.0] * _N),
)


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    episode=st.lists(joint, min_size=_CITY.horizon - 1, max_size=_CITY.horizon - 1),
    mode=st.sampled_from(["weight", "logit"]),
    seed=st.integers(0, 2**16),
)
def test_flows_stay_feasible_under_any_valid_actions(episode, mode, seed) -> None:
    env = marl_amod.parallel_env(_CITY, action_mode=mode)
    env.reset(seed=seed)
    sim = env.system.sim
    fleet = _CITY.fleet_size
    for values in episode:
        a = np.clip(np.asarray(values, dtype=np.float32).astype(np.float64), 0.0, 1.0)
        idle_before = sim.idle.copy()
        target = env.system.targets_from_weights(act.weights(a, mode))
        env.step({f"region_{i}": np.array([v], dtype=np.float32) for i, v in enumerate(values)})
        y = env.last_outcome.rebalancing
        assert y.dtype == np.int64 and (y >= 0).all() and (np.diag(y) == 0).all()
        assert (y.sum(axis=1) <= idle_before).all()  # nobody sends more than it had idle
        if target.min() >= 0:  # a wish: each region ends with at least its target (own + incoming)
            assert target.sum() <= idle_before.sum()
            assert (idle_before - y.sum(axis=1) + y.sum(axis=0) >= target).all()
        else:
            assert y.sum() == 0
        assert sim.vehicles() == fleet
        assert (sim.idle >= 0).all() and (sim.last_dispatch >= 0).all()
    assert env.agents == []


@pytest.mark.parametrize(
    "scenario", [pytest.param("synthetic", id="synthetic"), pytest.param("nyc_brooklyn", id="nyc_brooklyn", marks=needs_data)]
)
def test_observations_and_state_stay_inside_finite_bounds(scenario: str) -> None:
    """Spaces are finite, and a policy that herds the fleet into one region still fits them."""
    env = marl_amod.parallel_env(scenario)
    space = env.observation_space(env.possible_agents[0])
    assert np.all(np.isfinite(space.high)) and np.all(np.isfinite(env.state_space.high))
    obs, _ = env.reset(seed=0)
    herd = {a: np.array([1.0 if a == "region_0" else 0.0], dtype=np.float32) for a in env.possible_agents}
    peak = 0.0
    while env.agents:
        assert all(space.contains(o) for o in obs.values())
        assert env.state_space.contains(env.state())
        peak = max(peak, float(obs["region_0"][0]))  # region 0's idle vehicles x 0.01
        obs, *_ = env.step(herd)
    assert peak > 0.5 * space.high[0]  # the idle bound is reached in practice, not loose by orders of magnitude
