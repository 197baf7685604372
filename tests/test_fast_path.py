"""The env's fast control step against the reference semantics, bit for bit.

The single env's step skips re-checking the coordinator's own flows (``validate``), builds
observations with one gather (:class:`~marl_amod.env.observations.LocalLayout`), keeps per-step
tables of small cities and reads the metrics with fewer numpy calls. Each shortcut must give the
numbers the plain definitions give: the references below are those definitions written the
straightforward way (block copies, per-pair loops, one reduction per quantity), and whole episodes
of the env are replayed against them.
"""

from __future__ import annotations

import numpy as np
import pytest

import marl_amod
from marl_amod.coordinator.dispatch import greedy_dispatch
from marl_amod.env.features import FEATURE_SCALE, state_features
from marl_amod.env.observations import N_CONTEXT, LocalLayout, neighbour_table, time_features
from marl_amod.env.rewards import rewards
from marl_amod.metrics import gini, metric_arrays
from marl_amod.scenario import grid_city
from marl_amod.scenario.types import step_rows
from marl_amod.sim.macro import EpisodeTotals, MacroSim
from marl_amod.system import FleetSystem
from tests.conftest import needs_data

SCENARIOS = [
    pytest.param("synthetic", id="synthetic"),
    pytest.param("nyc_brooklyn", id="nyc_brooklyn", marks=needs_data),
]


# ---------------------------------------------------------------------------------- references
def reference_features(city, t: int, idle: np.ndarray, arrivals: np.ndarray, lookahead: int) -> np.ndarray:
    """(N, 1 + 2T) float32: idle, idle + arrivals in t+k (none past the buffer), expected value in
    t+k, all float64 times the scale, rounded to float32 once."""
    n = city.n_regions
    feats = np.zeros((n, 1 + 2 * lookahead))
    feats[:, 0] = idle
    for k in range(1, lookahead + 1):
        arriving = arrivals[t + k] if t + k < arrivals.shape[0] else np.zeros(n, dtype=arrivals.dtype)
        feats[:, k] = idle + arriving
        feats[:, lookahead + k] = step_rows(city.expected_fares, np.array([t + k]))[0]
    return (feats * FEATURE_SCALE).astype(np.float32)


def reference_local(feats: np.ndarray, context: np.ndarray, table: tuple[np.ndarray, np.ndarray]) -> np.ndarray:
    """(N, D): own features, time, masked neighbour features slot by slot, mask (the module doc's layout)."""
    idx, mask = table
    n, f = feats.shape
    k = idx.shape[1]
    obs = np.zeros((n, f + N_CONTEXT + k * (f + 1)), dtype=np.float32)
    for i in range(n):
        obs[i, :f] = feats[i]
        obs[i, f : f + N_CONTEXT] = context
        for slot in range(k):
            start = f + N_CONTEXT + slot * f
            obs[i, start : start + f] = feats[idx[i, slot]] * mask[i, slot]
        obs[i, f + N_CONTEXT + k * f :] = mask[i]
    return obs


def reference_metrics(totals: EpisodeTotals, fleet: int, horizon: int) -> dict[str, float]:
    """One reduction per quantity; Ginis of the per-region ratios over the regions that count."""
    served = totals.served.sum()
    wait = totals.wait_minutes.sum()
    waited = np.where(totals.served > 0, totals.wait_minutes / np.maximum(totals.served, 1e-12), 0.0)
    rate = np.where(totals.demand > 0, totals.served / np.maximum(totals.demand, 1e-12), 0.0)
    return {
        "profit": float((totals.revenue - totals.trip_cost - totals.rebalancing_cost).sum()),
        "revenue": float(totals.revenue.sum()),
        "served_demand": float(served),
        "demand": float(totals.demand.sum()),
        "rebalancing_cost": float(totals.rebalancing_cost.sum()),
        "wait_time": float(wait / max(served, 1e-300)) if served > 0 else 0.0,
        "utilization": float(totals.busy_vehicle_steps.sum() / max(fleet * horizon, 1)),
        "wait_time_gini": float(gini(waited[totals.served > 0])),
        "service_rate_gini": float(gini(rate[totals.demand > 0])),
    }


class ReferenceStep:
    """The env's step from the plain definitions, on a FleetSystem that checks every flow."""

    def __init__(self, scenario: str, reward_mode: str, action_mode: str, max_wait: int, lookahead: int = 6) -> None:
        self.env = marl_amod.parallel_env(scenario, reward_mode=reward_mode, action_mode=action_mode, max_wait=max_wait)
        self.system = FleetSystem(self.env.city, max_wait=max_wait, validate=True)
        self.table = neighbour_table(self.env.city, self.env.max_degree)
        self.reward_mode, self.action_mode, self.lookahead = reward_mode, action_mode, lookahead
        self.agents = self.env.possible_agents

    def reset(self, seed: int) -> tuple[dict, dict]:
        infos = self._infos(self.system.reset(seed))
        return self._observations(), infos

    def step(self, action: np.ndarray) -> tuple[dict, dict, dict]:
        w = np.clip(action, 0.0, 1.0)
        if self.action_mode == "logit":
            logits = 10.0 * (2.0 * w - 1.0)
            z = np.exp(logits - logits.max())
            w = z / z.sum()
        s, idle = w.sum(), self.system.sim.idle.sum()  # floor(w_i / sum(w) * M), or "stay"
        target = np.floor(w / s * idle + 1e-9).astype(np.int64) if s > 0 else np.full(w.shape, -1)
        outcome = self.outcome = self.system.step(target)
        rew = dict(zip(self.agents, rewards(self.reward_mode, outcome).tolist(), strict=True))
        return self._observations(), rew, self._infos(outcome)

    def _observations(self) -> dict:
        sim, city = self.system.sim, self.system.city
        feats = reference_features(city, sim.t, sim.idle, sim.arrivals, self.lookahead)
        obs = reference_local(feats, time_features(city, sim.t), self.table)
        return {a: obs[i] for i, a in enumerate(self.agents)}

    def _infos(self, outcome) -> dict:
        sim, city = self.system.sim, self.system.city
        metrics = reference_metrics(sim.totals, city.fleet_size, city.horizon)
        system = {f"system_{k}": v for k, v in metrics.items() if k != "revenue"}
        return {
            a: {
                "served": int(outcome.dispatch[i].sum()), "demand": int(sim.demand[sim.t, i].sum()),
                "rebalancing_cost": float(outcome.region_rebalancing_cost[i]), "idle": int(sim.idle[i]), **system,
            }
            for i, a in enumerate(self.agents)
        }


def assert_same(fast: dict, ref: dict) -> None:
    """Equal keys in the same order, equal arrays bit for bit, equal Python numbers of the same type."""
    assert list(fast) == list(ref)
    for key, value in fast.items():
        expected = ref[key]
        if isinstance(value, dict):
            assert_same(value, expected)
        elif isinstance(value, np.ndarray):
            assert value.dtype == expected.dtype and value.tobytes() == expected.tobytes(), key
        else:
            assert type(value) is type(expected) and value == expected, (key, value, expected)


# ---------------------------------------------------------------------------------- the env
@pytest.mark.parametrize("scenario", SCENARIOS)
@pytest.mark.parametrize(
    "reward_mode, action_mode, max_wait", [("team", "weight", 0), ("local", "weight", 2), ("team", "logit", 1)]
)
def test_env_step_equals_the_reference_semantics_bit_for_bit(scenario, reward_mode, action_mode, max_wait) -> None:
    env = marl_amod.parallel_env(scenario, reward_mode=reward_mode, action_mode=action_mode, max_wait=max_wait)
    ref = ReferenceStep(scenario, reward_mode, action_mode, max_wait)
    rng = np.random.default_rng(7)
    for seed in (0, 3):
        obs, infos = env.reset(seed=seed)
        ref_obs, ref_infos = ref.reset(seed)
        assert_same(obs, ref_obs)
        assert_same(infos, ref_infos)
        step = 0
        while env.agents:
            action = rng.uniform(-0.2, 1.2, size=len(env.agents)).astype(np.float32)
            if step % 5 == 0:
                action[:] = 0.0  # "stay"
            obs, rew, _term, _trunc, infos = env.step({a: action[i : i + 1] for i, a in enumerate(env.agents)})
            ref_obs, ref_rew, ref_infos = ref.step(action.astype(np.float64))
            assert_same(obs, ref_obs)
            assert_same(rew, ref_rew)
            assert_same(infos, ref_infos)
            for name in ("dispatch", "rebalancing", "region_profit", "region_rebalancing_cost"):
                assert getattr(env.last_outcome, name).tobytes() == getattr(ref.outcome, name).tobytes(), name
            step += 1
        assert step == env.city.horizon - 1


def test_validate_checks_every_flow_and_changes_no_number(small_city, monkeypatch) -> None:
    """validate=True gives the same episode; a coordinator bug is then caught, and only then."""
    fast, checked = FleetSystem(small_city), FleetSystem(small_city, validate=True)
    rng = np.random.default_rng(0)
    fast.reset(5)
    checked.reset(5)
    while not fast.done:
        target = fast.targets_from_weights(rng.random(small_city.n_regions))
        a, b = fast.step(target), checked.step(target)
        for name in ("dispatch", "rebalancing", "region_profit", "region_rebalancing_cost"):
            assert getattr(a, name).tobytes() == getattr(b, name).tobytes()
    for system in (fast, checked):  # a coordinator that dispatches vehicles it does not have
        system.reset(5)
        bad = system.coordinator.dispatch(system.sim.idle, system.sim.requests(), system.sim.t) + 1000
        monkeypatch.setattr(system.coordinator, "dispatch", lambda *args, bad=bad, **kwargs: bad)
    with pytest.raises(ValueError, match="dispatch"):
        checked.step(checked.targets_from_weights(np.ones(small_city.n_regions)))
    fast.step(fast.targets_from_weights(np.ones(small_city.n_regions)))  # trusted: not re-checked


def test_env_validate_option_gives_the_same_episode() -> None:
    envs = [marl_amod.parallel_env("synthetic", horizon=8, validate=v) for v in (False, True)]
    assert [e.system.validate for e in envs] == [False, True]
    outs = [e.reset(seed=2) for e in envs]
    assert_same(outs[0][0], outs[1][0])
    while envs[0].agents:
        act = {a: np.array([0.1 + 0.05 * i], dtype=np.float32) for i, a in enumerate(envs[0].agents)}
        a, b = (e.step(act) for e in envs)
        for x, y in zip(a, b, strict=True):
            assert_same(x, y)


# ---------------------------------------------------------------------------------- the pieces
def test_local_layout_equals_block_copies_with_padding_single_and_batched(tiny_city) -> None:
    table = neighbour_table(tiny_city, max_degree=6)  # more slots than any region has: padding everywhere
    layout = LocalLayout(table, 13)
    rng = np.random.default_rng(0)
    feats = (rng.random((4, tiny_city.n_regions, 13)) * 3).astype(np.float32)
    ctx = np.array([0.5, -0.25, 0.1], dtype=np.float32)
    for b in range(4):
        assert layout(feats[b], ctx).tobytes() == reference_local(feats[b], ctx, table).tobytes()
    batched = layout(feats, ctx)
    assert batched.shape == (4, *layout.shape) and batched.dtype == np.float32
    assert batched.tobytes() == np.stack([reference_local(f, ctx, table) for f in feats]).tobytes()
    with pytest.raises(ValueError, match="layout"):
        layout(feats[0, :, :12], ctx)


@pytest.mark.parametrize("lookahead", [2, 6, 12, 24])
def test_state_features_equal_the_definition_including_past_the_arrivals_buffer(lookahead) -> None:
    city = grid_city(2, 3, seed=3, horizon=10, vehicles_per_region=4)
    sim = MacroSim(city)
    sim.reset(np.random.default_rng(1))
    rng = np.random.default_rng(2)
    sim.arrivals[:] = rng.integers(0, 5, size=sim.arrivals.shape)
    steps = (0, 4, city.n_steps - 1)
    if lookahead == 24:  # the look-ahead reaches past the arrivals buffer: the branch that pads with nothing
        assert city.n_steps - 1 + lookahead >= sim.arrivals.shape[0]
    for t in steps:
        got = state_features(city, t, sim.idle, sim.arrivals, lookahead)
        assert got.tobytes() == reference_features(city, t, sim.idle, sim.arrivals, lookahead).tobytes(), t


def test_greedy_dispatch_equals_serving_each_origin_by_decreasing_margin() -> None:
    rng = np.random.default_rng(4)
    for k in range(300):
        n = int(rng.integers(1, 7))
        lead = () if k % 2 else (int(rng.integers(1, 4)),)
        idle = rng.integers(0, 12, size=(*lead, n))
        demand = rng.integers(0, 5, size=(*lead, n, n))
        margin = rng.normal(size=(n, n))
        margin[rng.random((n, n)) < 0.3] = 0.0
        expected = np.zeros_like(demand)
        for at in np.ndindex(*lead):
            for i in range(n):
                left = idle[at][i]
                for j in np.argsort(-margin[i], kind="stable"):
                    if margin[i, j] > 0:
                        expected[at][i, j] = take = min(left, demand[at][i, j])
                        left -= take
        np.testing.assert_array_equal(greedy_dispatch(idle, demand, margin), expected)


def test_departures_book_every_leg_as_a_per_pair_loop(small_city) -> None:
    """Arrivals and vehicle-steps of dispatch and rebalancing legs, pair by pair, every step."""
    city, system = small_city, FleetSystem(small_city)
    arrivals, busy = np.zeros_like(system.sim.arrivals), np.zeros(city.n_regions)

    def book(flows: np.ndarray, duration: np.ndarray, when: int) -> None:
        for i, j in zip(*np.nonzero(flows), strict=True):
            arrivals[when + duration[i, j], j] += flows[i, j]
            busy[i] += flows[i, j] * min(duration[i, j], city.horizon - when)

    book(system.reset(3).dispatch, city.trip_time[0], 0)
    rng = np.random.default_rng(3)
    for t in range(city.horizon - 1):
        out = system.step(system.targets_from_weights(rng.random(city.n_regions)))
        book(out.rebalancing, city.reb_time, t)
        book(out.dispatch, city.trip_time[t + 1], t + 1)
        np.testing.assert_array_equal(system.sim.arrivals, arrivals)
        np.testing.assert_array_equal(system.sim.totals.busy_vehicle_steps, busy)
    assert busy.sum() > 0


def test_metric_arrays_equal_one_reduction_per_quantity_single_and_batched() -> None:
    rng = np.random.default_rng(5)
    n = 14
    fields = EpisodeTotals.__dataclass_fields__
    batch = EpisodeTotals(**{name: rng.integers(0, 50, size=(6, n)).astype(float) * rng.random((6, n)) for name in fields})
    batch.demand[:, :3] = 0.0  # regions nobody asked from
    batch.served[1] = 0.0  # an episode that served nobody
    batch.wait_minutes[2] = 0.0
    arrays = metric_arrays(batch, fleet=40, horizon=20)
    for b in range(6):
        alone = EpisodeTotals(**{name: getattr(batch, name)[b].copy() for name in fields})
        expected = reference_metrics(alone, 40, 20)
        single = {key: float(value) for key, value in metric_arrays(alone, 40, 20).items()}
        assert single == expected
        assert {key: float(value[b]) for key, value in arrays.items()} == expected
