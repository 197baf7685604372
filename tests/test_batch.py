"""The batched simulator and vector env agree episode for episode with FleetSystem and the ParallelEnv."""

from __future__ import annotations

import numpy as np
import pytest

import marl_amod
from marl_amod.batch_system import BatchFleetSystem
from marl_amod.coordinator.reference import lp_dispatch, lp_rebalance
from marl_amod.errors import ActionError, ConfigError
from marl_amod.scenario import load_city
from marl_amod.sim.macro import EpisodeTotals
from marl_amod.system import FleetSystem
from tests.conftest import needs_data

SCENARIOS = ["synthetic", pytest.param("nyc_brooklyn", marks=needs_data)]


def _random_actions(rng: np.random.Generator, b: int, n: int) -> np.ndarray:
    """Actions that exercise every branch: noise, exact zeros (a 'stay' row), values above 1."""
    a = rng.random((b, n)) * 1.2
    a[rng.random((b, n)) < 0.2] = 0.0
    a[0] = 0.0 if rng.random() < 0.3 else a[0]
    return a


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("max_wait", [0, 2])
def test_batch_system_equals_fleet_system_episode_for_episode(scenario: str, max_wait: int) -> None:
    city = load_city(scenario)
    seeds = [11, 12, 13, 14]
    batch = BatchFleetSystem(city, len(seeds), max_wait=max_wait)
    singles = [FleetSystem(city, max_wait=max_wait) for _ in seeds]
    outs = [batch.reset(seeds)] + [None]
    firsts = [s.reset(seed) for s, seed in zip(singles, seeds, strict=True)]
    for b, first in enumerate(firsts):
        np.testing.assert_array_equal(batch.sim.demand[b], singles[b].sim.demand[: city.horizon])  # same draws
        np.testing.assert_array_equal(outs[0].region_profit[b], first.region_profit)
        np.testing.assert_array_equal(outs[0].dispatch[b], first.dispatch)
    rng = np.random.default_rng(0)
    fleet = city.fleet_size
    while not batch.done:
        weights = rng.random((len(seeds), city.n_regions)) * (rng.random((len(seeds), 1)) > 0.1)
        target = batch.targets_from_weights(weights)
        before_idle = batch.sim.idle.copy()
        out = batch.step(target)
        sim = batch.sim
        np.testing.assert_array_equal(sim.vehicles(), fleet)  # conservation every step
        assert (sim.idle >= 0).all() and (sim.backlog >= 0).all()  # feasibility (the sim also checks each flow)
        assert (out.rebalancing.sum(axis=-1) <= before_idle).all()
        for b, single in enumerate(singles):
            np.testing.assert_array_equal(target[b], single.targets_from_weights(weights[b]))
            ref = single.step(target[b])
            np.testing.assert_array_equal(out.rebalancing[b], ref.rebalancing)
            np.testing.assert_array_equal(out.dispatch[b], ref.dispatch)
            np.testing.assert_array_equal(out.region_profit[b], ref.region_profit)
            np.testing.assert_array_equal(out.region_rebalancing_cost[b], ref.region_rebalancing_cost)
            assert out.reward[b] == ref.reward
            np.testing.assert_array_equal(sim.idle[b], single.sim.idle)
            np.testing.assert_array_equal(sim.arrivals[b], single.sim.arrivals)
            np.testing.assert_array_equal(sim.backlog[b], single.sim.backlog)
    assert all(s.done for s in singles)
    for name in EpisodeTotals.__dataclass_fields__:
        for b, single in enumerate(singles):
            np.testing.assert_array_equal(getattr(batch.sim.totals, name)[b], getattr(single.sim.totals, name), name)


def test_batch_flows_match_the_cvxpy_problems_every_episode(small_city) -> None:
    """Each episode's dispatch and rebalancing reach the optimum of the literal LPs (a few steps)."""
    batch = BatchFleetSystem(small_city, 3)
    batch.reset([0, 1, 2])
    rng = np.random.default_rng(3)
    margin = batch.coordinator.margin
    for _ in range(3):
        idle = batch.sim.idle.copy()
        target = batch.targets_from_weights(rng.random((3, small_city.n_regions)))
        out = batch.step(target)
        t = batch.t
        for b in range(3):
            cost = small_city.reb_cost
            lp = lp_rebalance(idle[b], target[b], cost)
            assert (out.rebalancing[b] * cost).sum() == pytest.approx((lp * cost).sum(), abs=1e-6)
            after = idle[b] - out.rebalancing[b].sum(axis=1) + out.rebalancing[b].sum(axis=0)
            assert (after >= np.maximum(target[b], 0)).all()
            # the dispatch of the new step: optimal for the requests and vehicles it saw
            requests = batch.sim.demand[b, t]  # max_wait 0: the new step's requests only
            pre_idle = batch.sim.idle[b] + out.dispatch[b].sum(axis=1)
            x = lp_dispatch(pre_idle, requests, margin(t))
            assert (out.dispatch[b] * margin(t)).sum() == pytest.approx((x * margin(t)).sum(), abs=1e-6)


@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize("reward_mode", ["team", "local"])
def test_vector_env_equals_parallel_env_episode_for_episode(scenario: str, reward_mode: str) -> None:
    b, seed = 3, 40
    venv = marl_amod.vector_env(scenario, num_envs=b, reward_mode=reward_mode, max_wait=1, action_mode="logit")
    envs = [marl_amod.parallel_env(scenario, reward_mode=reward_mode, max_wait=1, action_mode="logit") for _ in range(b)]
    obs, infos = venv.reset(seed=seed)
    assert obs.shape == (b, venv.num_agents, venv.observation_space.shape[0]) and obs.dtype == np.float32
    for k, env in enumerate(envs):
        o, i = env.reset(seed=seed + k)
        np.testing.assert_array_equal(obs[k], np.stack([o[a] for a in env.agents]))
        np.testing.assert_array_equal(venv.state()[k], env.state())
        np.testing.assert_array_equal(venv.graph()["x"][k], env.graph()["x"])
        assert infos["system_demand"][k] == i["region_0"]["system_demand"]
    np.testing.assert_array_equal(venv.graph()["edge_index"], envs[0].graph()["edge_index"])
    rng = np.random.default_rng(1)
    steps = 0
    while True:
        actions = _random_actions(rng, b, venv.num_agents)
        obs, rew, term, trunc, infos = venv.step(actions[..., None] if steps % 2 else actions)
        steps += 1
        assert rew.shape == term.shape == trunc.shape == (b, venv.num_agents)
        for k, env in enumerate(envs):
            o, r, te, tr, i = env.step({a: actions[k, j] for j, a in enumerate(env.possible_agents)})
            agents = env.possible_agents
            np.testing.assert_array_equal(obs[k], np.stack([o[a] for a in agents]))
            np.testing.assert_array_equal(rew[k], [r[a] for a in agents])
            np.testing.assert_array_equal(trunc[k], [tr[a] for a in agents])
            assert not term[k].any()
            for key in ("served", "demand", "rebalancing_cost", "idle"):
                np.testing.assert_array_equal(infos[key][k], [i[a][key] for a in agents], key)
            for key in ("system_profit", "system_wait_time", "system_utilization"):
                assert infos[key][k] == i["region_0"][key], key
        if trunc.all():
            break
    assert steps == venv.city.horizon - 1 and all(not env.agents for env in envs)
    with pytest.raises(RuntimeError, match="reset"):
        venv.step(actions)


def test_vector_env_reset_without_seed_continues_the_seeded_sequence() -> None:
    a = marl_amod.vector_env("synthetic", num_envs=2)
    b = marl_amod.vector_env("synthetic", num_envs=2)
    a.reset(seed=5)
    b.reset(seed=5)
    np.testing.assert_array_equal(a.reset()[0], b.reset()[0])
    assert not np.array_equal(a.system.sim.demand[0], a.system.sim.demand[1])  # distinct episodes
    a.reset(seed=[5, 9])  # a list of seeds is a seeded reset too: what follows is reproducible
    fresh = marl_amod.vector_env("synthetic", num_envs=2)  # whatever came before
    fresh.reset(seed=[5, 9])
    np.testing.assert_array_equal(a.reset()[0], fresh.reset()[0])


@pytest.mark.parametrize("seed", [-3, 1.5, "a", True, [1, -1], [0, 1.5]])
def test_vector_env_seeds_are_checked_like_the_parallel_envs(seed) -> None:
    """A negative, fractional or string seed, alone or in the per-episode list, is a ConfigError
    (a string was read as a list of one seed; the others escaped as numpy errors)."""
    venv = marl_amod.vector_env("synthetic", num_envs=2, horizon=3)
    with pytest.raises(ConfigError, match="seed"):
        venv.reset(seed=seed)
    obs, _ = venv.reset(seed=np.int64(4))  # numpy integers are seeds, as in the ParallelEnv
    np.testing.assert_array_equal(obs, venv.reset(seed=[4, 5])[0])


@pytest.mark.parametrize("seeds", [range(4, 6), (4, 5), np.array([4, 5])])
def test_vector_env_takes_any_sequence_of_per_episode_seeds(seeds) -> None:
    """reset(seed=...) takes a Sequence of B seeds (a range too), as its signature says: only a
    single value is checked as one seed."""
    venv = marl_amod.vector_env("synthetic", num_envs=2, horizon=3)
    np.testing.assert_array_equal(venv.reset(seed=seeds)[0], venv.reset(seed=[4, 5])[0])


def test_vector_env_rejects_bad_actions() -> None:
    venv = marl_amod.vector_env("synthetic", num_envs=2)
    venv.reset(seed=0)
    n = venv.num_agents
    with pytest.raises(ActionError, match="shape"):
        venv.step(np.zeros((2, n + 1)))
    bad = np.full((2, n), 0.5)
    bad[1, 3] = np.nan
    with pytest.raises(ActionError, match="region_3 in episode 1"):
        venv.step(bad)
    bad[1, 3] = -0.5
    strict = marl_amod.vector_env("synthetic", num_envs=2, strict_actions=True)
    strict.reset(seed=0)
    with pytest.raises(ActionError, match="region_3 in episode 1 is -0.5, outside"):
        strict.step(bad)
    venv.step(bad)  # clipped to 0 like the ParallelEnv does
    # what the ParallelEnv refuses as an action (strings it would read as numbers, complex values whose
    # imaginary part numpy drops, bools) the vector env refuses too, before any episode moves
    for wrong in (np.full((2, n), "0.5"), np.full((2, n), 0.5 + 1j), np.ones((2, n), dtype=bool)):
        with pytest.raises(ActionError, match="real numbers"):
            venv.step(wrong)
    assert venv.system.t == 1
    import torch

    venv.step(torch.full((2, n), 0.5))  # a tensor of numbers is fine


def test_rebalancer_reusing_its_network_equals_a_fresh_solve_and_pickles() -> None:
    """The coordinator keeps one OR-Tools network per city; reusing it must not change any flow."""
    import pickle

    from marl_amod.coordinator.rebalance import Rebalancer, desired_targets, min_cost_rebalance
    from marl_amod.scenario import grid_city

    city = grid_city(4, 4, seed=2)
    rng = np.random.default_rng(7)
    cost = city.reb_time.copy()
    cost[0, 5] = cost[0, 5] + 3  # break the triangle inequality: the full network is reused
    for metric, c in ((False, cost), (True, city.reb_time)):
        solver = Rebalancer(c, metric)
        cases = []
        for k in range(60):
            idle = rng.multinomial(rng.integers(0, 200), rng.dirichlet(np.full(16, 0.5)))
            target = desired_targets(rng.random(16) * (rng.random(16) > 0.3), idle.sum())
            target = target if k % 5 else np.minimum(target, idle)  # some instances need no move
            flows = solver(idle, target)
            np.testing.assert_array_equal(flows, min_cost_rebalance(idle, target, c, metric=metric))
            assert ((idle - flows.sum(axis=1) + flows.sum(axis=0)) >= np.maximum(target, 0)).all()
            cases.append((idle, target, flows))
        idles, targets, expected = map(np.stack, zip(*cases, strict=True))
        np.testing.assert_array_equal(solver.many(idles, targets), expected)  # a batch: each solved alone
        copy = pickle.loads(pickle.dumps(solver))
        np.testing.assert_array_equal(copy(idle, target), flows)


def test_torchrl_vector_env_passes_check_env_specs_and_replays_the_vector_env() -> None:
    pytest.importorskip("torchrl")
    from torchrl.envs.utils import check_env_specs

    from marl_amod.integrations.torchrl import torchrl_vector_env

    env = torchrl_vector_env("synthetic", num_envs=3, reward_mode="local")
    check_env_specs(env)
    env.set_seed(8)
    td = env.rollout(100, break_when_any_done=True)  # stops at the horizon: all episodes end together
    horizon = env.vector.city.horizon
    assert td.batch_size == (3, horizon - 1) and td["next", "truncated"][:, -1].all()
    venv = marl_amod.vector_env("synthetic", num_envs=3, reward_mode="local")
    obs, _ = venv.reset(seed=8)
    np.testing.assert_array_equal(td["agents", "observation"][:, 0].numpy(), obs)
    for k in range(horizon - 1):
        obs, rew, *_ = venv.step(td["agents", "action"][:, k].numpy())
        np.testing.assert_array_equal(td["next", "agents", "observation"][:, k].numpy(), obs)
        np.testing.assert_allclose(td["next", "agents", "reward"][:, k, :, 0].numpy(), rew.astype(np.float32))


def test_torchrl_vector_env_refuses_a_partial_reset_and_auto_resets_all_at_the_horizon() -> None:
    """The B episodes run in lockstep: a ``_reset`` mask for some of them would restart all of them
    while TorchRL believes the others continue, so it is an error; past the horizon (all done) every
    episode restarts together."""
    pytest.importorskip("torchrl")
    import torch
    from tensordict import TensorDict

    from marl_amod.integrations.torchrl import torchrl_vector_env

    env = torchrl_vector_env("synthetic", num_envs=3, horizon=4)
    env.set_seed(1)
    td = env.rand_step(env.reset())["next"]
    with pytest.raises(ConfigError, match="lockstep"):
        env.reset(TensorDict({"_reset": torch.tensor([[True], [False], [False]])}, batch_size=[3]))
    assert env.vector.system.t == 1  # nothing was restarted
    env.reset(TensorDict({"_reset": torch.ones(3, 1, dtype=torch.bool)}, batch_size=[3]))
    assert env.vector.system.t == 0
    td = env.rollout(9, break_when_any_done=False)  # 3 steps an episode, then all reset at once
    assert td["next", "done"][:, :, 0].all(dim=0).tolist() == [False, False, True] * 3


def test_vector_env_copy_continues_identically() -> None:
    """Vector wrappers and workers copy envs: a pickled copy (solver state rebuilt) steps the same."""
    import pickle

    venv = marl_amod.vector_env("synthetic", num_envs=2, max_wait=1)
    venv.reset(seed=3)
    actions = np.random.default_rng(0).random((2, venv.num_agents))
    venv.step(actions)
    copy = pickle.loads(pickle.dumps(venv))
    for got, want in zip(copy.step(actions), venv.step(actions), strict=True):
        if isinstance(want, dict):
            for key in want:
                np.testing.assert_array_equal(got[key], want[key])
        else:
            np.testing.assert_array_equal(got, want)


def test_vector_env_reward_scale_and_max_cycles_follow_the_parallel_env() -> None:
    plain = marl_amod.vector_env("synthetic", num_envs=2)
    scaled = marl_amod.vector_env("synthetic", num_envs=2, reward_scale=0.5, max_cycles=3)
    plain.reset(seed=4), scaled.reset(seed=4)
    actions = np.full((2, plain.num_agents), 0.5)
    for step in range(1, 4):
        _, r_plain, _, trunc_plain, _ = plain.step(actions)
        _, r_scaled, _, trunc_scaled, _ = scaled.step(actions)
        np.testing.assert_allclose(r_scaled, 0.5 * r_plain, rtol=1e-12)
        assert not trunc_plain.any() and trunc_scaled.all() == (step == 3)
    with pytest.raises(RuntimeError, match="call reset"):
        scaled.step(actions)


def _one_instance_metric_build(idle: np.ndarray, target: np.ndarray, cost: np.ndarray) -> np.ndarray:
    """The metric network built the literal way, one instance: surplus regions x shortfall regions."""
    from marl_amod.coordinator.rebalance import _network

    need = np.maximum(target, 0)
    flows = np.zeros((idle.size, idle.size), dtype=np.int64)
    senders, receivers = np.flatnonzero(idle > need), np.flatnonzero(need > idle)
    if receivers.size == 0:
        return flows
    supply, demand = idle[senders] - need[senders], need[receivers] - idle[receivers]
    smcf, arcs, nodes = _network(cost[np.ix_(senders, receivers)])
    smcf.set_arc_capacities(arcs, np.concatenate([np.repeat(supply, receivers.size), supply]))
    smcf.set_nodes_supplies(nodes, np.concatenate([supply, -demand, [demand.sum() - supply.sum()]]))
    assert smcf.solve() == smcf.OPTIMAL
    flows[np.ix_(senders, receivers)] = smcf.flows(arcs)[: senders.size * receivers.size].reshape(senders.size, -1)
    return flows


def test_batched_metric_networks_are_the_one_instance_networks() -> None:
    """The batch lays out every instance's surplus x shortfall network at once; each must be the
    network a one-instance build makes (same nodes, arcs, order), i.e. give the very same flows
    (tied optima are everywhere with whole-step costs, so any other network shows)."""
    from marl_amod.coordinator.rebalance import Rebalancer, desired_targets
    from marl_amod.scenario import grid_city

    city = grid_city(4, 4, seed=5)
    solver = Rebalancer(city.reb_time, metric=True)
    rng = np.random.default_rng(11)
    idles = rng.multinomial(60, np.full(16, 1 / 16), size=50)
    targets = desired_targets(rng.random((50, 16)) * (rng.random((50, 16)) > 0.4), idles.sum(axis=1))
    targets[::7] = np.minimum(targets[::7], idles[::7])  # no shortfall: no solve
    expected = np.stack([_one_instance_metric_build(i, t, solver.cost) for i, t in zip(idles, targets, strict=True)])
    assert expected.any(axis=(1, 2)).sum() > 30
    np.testing.assert_array_equal(solver.many(idles, targets), expected)
    for k in range(0, 50, 9):
        np.testing.assert_array_equal(solver(idles[k], targets[k]), expected[k])


def test_batch_and_single_rebalancing_agree_when_some_move_costs_nothing() -> None:
    """With a free move 'no region short' no longer has one optimum: the batch must not skip the solve."""
    from marl_amod.coordinator.rebalance import Rebalancer

    cost = np.array([[0, 0, 3], [2, 0, 1], [4, 1, 0]])
    solver = Rebalancer(cost)
    idles = np.array([[4, 4, 1], [4, 3, 3], [2, 2, 2], [0, 6, 0]])
    targets = np.array([[3, 4, 1], [1, 3, -1], [-1, -1, -1], [0, 2, 0]])  # nobody short of its target
    assert solver(idles[0], targets[0])[0, 1] > 0  # OR-Tools picks the free move among the optima
    np.testing.assert_array_equal(solver.many(idles, targets), np.stack([solver(i, t) for i, t in zip(idles, targets, strict=True)]))
