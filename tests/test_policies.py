"""The policy registry, outside policies scored like ours, shipped policies as callables, and plus-one."""

from __future__ import annotations

import json
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

import marl_amod
from marl_amod.baselines import NoRebalancing, PlusOne, Policy, WeightPolicy
from marl_amod.checkpoints import ActorPolicy, load_policy, save_policy
from marl_amod.cli import app
from marl_amod.errors import ConfigError
from marl_amod.models import build_actor
from marl_amod.policies import POLICIES, make_policy
from marl_amod.scenario import City, grid_city, load_city
from marl_amod.system import FleetSystem

SHIPPED = Path(__file__).resolve().parents[1] / "policies" / "a2c_gnn_synthetic.pt"


@pytest.fixture
def tiny_yaml(tmp_path: Path) -> str:
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return str(path)


def _saved_actor(tmp_path: Path, city: City, time_context: bool = False) -> Path:
    torch.manual_seed(0)
    actor = build_actor("gnn", city, 13 + 3 * time_context, 8)  # time_context: the 3 time values on every node too
    card = {"scenario": city.name, "algorithm": "a2c", "mode": "centralised", "actor": "gnn", "conv": "gcn",
            "hidden": 8, "n_features": 13, "lookahead": 6, "seed": 0, "time_context": time_context}
    return save_policy(tmp_path / "x.pt", actor, card)


def _without_name(result: dict) -> dict:
    """The record without what names the policy (its name, and a checkpoint's path among the settings)."""
    settings = {k: v for k, v in result.get("settings", {}).items() if k != "checkpoint"}
    return {k: v for k, v in result.items() if k != "policy"} | {"settings": settings}


# ------------------------------------------------------------------------------------------ registry
def test_every_registered_name_builds_a_policy_that_reports_that_name(tiny_city):
    for name in POLICIES:
        policy = make_policy(name, tiny_city)
        assert isinstance(policy, Policy) and policy.name == name


class Toy(WeightPolicy):
    """All idle vehicles to region 0: one class, then one registry line in the test."""

    name = "toy"

    def weights(self, system: FleetSystem) -> np.ndarray:
        w = np.zeros(system.city.n_regions)
        w[0] = 1.0
        return w


def test_a_new_policy_is_one_class_plus_one_registry_line(monkeypatch, tmp_path, tiny_yaml):
    monkeypatch.setitem(POLICIES, "toy", Toy)
    out = tmp_path / "toy.json"
    result = CliRunner().invoke(app, ["evaluate", "--scenario", tiny_yaml, "--policy", "toy", "--episodes", "2", "--output", str(out)])
    assert result.exit_code == 0, result.output
    from_cli = json.loads(out.read_text())
    assert from_cli == marl_amod.evaluate("toy", tiny_yaml, episodes=2, seed=0)
    assert from_cli["policy"] == "toy"
    baseline = marl_amod.evaluate("no-rebalancing", tiny_yaml, episodes=2)
    assert from_cli["metrics"]["rebalancing_cost"]["mean"] > baseline["metrics"]["rebalancing_cost"]["mean"]


def test_policy_options_reach_the_factory_and_unknown_ones_are_clear_errors(tiny_city):
    assert make_policy("mpc-forecast", tiny_city, horizon=3, noise=0.5).noise == 0.5
    with pytest.raises(ConfigError, match="'equal-distribution'.*horizon"):
        make_policy("equal-distribution", tiny_city, horizon=3)
    with pytest.raises(ConfigError, match="unknown policy 'teleport'"):
        make_policy("teleport", tiny_city)
    with pytest.raises(ConfigError, match="policy first"):
        marl_amod.evaluate(tiny_city, "equal-distribution")  # the old argument order fails loudly


@pytest.mark.parametrize(
    "name, options, culprit",
    [
        ("mpc-forecast", {"horizon": "abc"}, "MPC horizon"),  # --policy-option horizon=abc reads a string
        ("mpc-forecast", {"horizon": 2.5}, "MPC horizon"),
        ("mpc-oracle", {"horizon": 0}, "MPC horizon"),
        ("mpc-forecast", {"demand_scale": "big"}, "demand_scale"),
        ("mpc-forecast", {"noise": None}, "noise"),
        ("mpc-scenarios", {"scenarios": 1.5}, "scenarios"),
        ("inf", {"roh": "x"}, "roh"),
        ("inf", {"window": 0}, "window"),
        ("inf", {"max_reb": True}, "max_reb"),
        ("prop", {"lookahead": None}, "lookahead"),
    ],
)
def test_policy_options_of_the_wrong_type_are_config_errors_naming_the_option(tiny_city, name, options, culprit):
    """Options come from the command line as YAML scalars; a string or a fraction where a count
    belongs is refused where the policy is made, not met later as a TypeError in a solver."""
    with pytest.raises(ConfigError, match=culprit):
        make_policy(name, tiny_city, **options)


# ------------------------------------------------------------------------------------------ callables
def test_a_callable_that_always_returns_one_reproduces_equal_distribution_exactly(tiny_city):
    def always_one(observations: dict) -> dict:
        return {agent: np.ones(1, dtype=np.float32) for agent in observations}

    ed = marl_amod.evaluate("equal-distribution", tiny_city, episodes=3, seed=4)
    ones = marl_amod.evaluate(always_one, tiny_city, episodes=3, seed=4)
    assert ones["policy"] == "always_one"
    assert _without_name(ones) == _without_name(ed)


@pytest.mark.parametrize("time_context", [False, True])
def test_load_policy_acts_identically_as_a_callable_and_on_the_simulator(tmp_path, tiny_city, time_context):
    """The env-callable path reads the time values from the observations, the simulator path from the clock."""
    path = _saved_actor(tmp_path, tiny_city, time_context)
    policy = marl_amod.load_policy(path, tiny_city)
    assert isinstance(policy, ActorPolicy) and callable(policy) and policy.time_context == time_context
    env = marl_amod.parallel_env(tiny_city)
    obs, _ = env.reset(seed=5)
    while env.agents:
        actions = policy(obs)
        expected = policy.weights(env.system)
        np.testing.assert_array_equal(np.concatenate([actions[a] for a in env.agents]), expected)
        obs, *_ = env.step(actions)
    as_path = marl_amod.evaluate(str(path), tiny_city, episodes=2, seed=1)
    as_callable = marl_amod.evaluate(lambda o: policy(o), tiny_city, episodes=2, seed=1)
    assert _without_name(as_callable) == _without_name(as_path)


def test_load_policy_defaults_to_the_city_on_the_card():
    policy = marl_amod.load_policy(SHIPPED)
    assert policy.name == "a2c_gnn_synthetic" and len(policy.agents) == load_city("synthetic").n_regions


def test_a_policy_trained_on_a_scenario_file_loads_and_evaluates_from_its_card(tmp_path, monkeypatch):
    """A run on a user's YAML records the city's name ("mine"), which is no bundled scenario: the
    card's training args keep the file, and load_policy and the card's Evaluate line use it."""
    from marl_amod.checkpoints import card_markdown

    monkeypatch.chdir(tmp_path)
    Path("mine.yaml").write_text("extends: synthetic\nrows: 3\n")
    city = load_city("mine.yaml")
    torch.manual_seed(0)
    card = {"scenario": city.name, "algorithm": "a2c", "mode": "centralised", "actor": "gnn", "conv": "gcn", "hidden": 8,
            "n_features": 13, "lookahead": 6, "seed": 0, "args": {"scenario": "mine.yaml"}}
    path = save_policy(tmp_path / "mine.pt", build_actor("gnn", city, 13, 8), card)
    assert len(marl_amod.load_policy(path).agents) == 12
    assert "--scenario mine.yaml " in card_markdown(path, card)


def test_record_episode_runs_a_shipped_policy():
    from marl_amod.env.render import record_episode

    env = marl_amod.parallel_env("synthetic", horizon=3, render_mode="rgb_array")
    frames = record_episode(env, load_policy(SHIPPED), seed=0)
    assert len(frames) == 3 and frames[0].ndim == 3


# ------------------------------------------------------------------------------------------ plus-one
def _fake_system(idle: list[int], departures: dict[tuple[int, int], int], reb_time: np.ndarray) -> SimpleNamespace:
    """Only what plus-one reads: idle vehicles, this step's passenger flows, rebalancing times."""
    n = len(idle)
    dispatch = np.zeros((n, n), dtype=np.int64)
    for (i, j), k in departures.items():
        dispatch[i, j] = k
    return SimpleNamespace(sim=SimpleNamespace(idle=np.array(idle), last_dispatch=dispatch), city=SimpleNamespace(reb_time=reb_time))


def test_plus_one_brings_back_one_vehicle_per_departure_nearest_first():
    line = np.abs(np.subtract.outer(np.arange(4), np.arange(4)))  # four regions on a line
    system = _fake_system([0, 2, 0, 5], {(0, 2): 2, (0, 3): 1}, line)  # region 0 sent 3 vehicles away
    flows = PlusOne().flows(system)
    assert flows[1, 0] == 2 and flows[3, 0] == 1  # both spares of the neighbour first, then the far one
    assert flows.sum() == 3


def test_plus_one_lets_regions_that_dispatched_send_their_spare_vehicles():
    system = _fake_system([4, 4], {(0, 1): 3, (1, 0): 1}, np.array([[0, 1], [1, 0]]))
    policy = PlusOne()
    np.testing.assert_array_equal(policy.flows(system), [[0, 1], [3, 0]])
    np.testing.assert_array_equal(policy.target(system), [6, 2])  # net of the swap: two vehicles move


def test_plus_one_sends_k_back_to_a_region_that_dispatched_k_and_differs_from_no_rebalancing():
    """On a city where every region dispatches every step (the old plus-one was no rebalancing there)."""
    city = grid_city(2, 2, seed=0, horizon=8, imbalance=0.0, vehicles_per_region=30, requests_per_region=8.0)
    system = FleetSystem(city)
    system.reset(0)
    policy = PlusOne()
    policy.reset(system, np.random.default_rng(0))
    departures = system.sim.last_dispatch.sum(axis=1)
    assert np.all(departures > 0) and system.sim.idle.sum() >= 2 * departures.sum()  # spares everywhere
    flows = policy.flows(system)
    np.testing.assert_array_equal(flows.sum(axis=0), departures)
    assert np.all(np.diag(flows) == 0) and np.all(flows.sum(axis=1) <= system.sim.idle)
    while not system.done:
        assert np.all(system.sim.last_dispatch.sum(axis=1) > 0)
        system.step(policy.target(system))
    plus_one = marl_amod.evaluate(policy, city, episodes=2)["metrics"]
    none = marl_amod.evaluate(NoRebalancing(), city, episodes=2)["metrics"]
    assert plus_one["rebalancing_cost"]["mean"] > 0 == none["rebalancing_cost"]["mean"]
    assert plus_one["profit"]["mean"] != none["profit"]["mean"]


def test_an_evaluation_records_what_else_decided_its_numbers(tmp_path):
    """Two records of one policy name differ by their settings: the system's options, the policy's
    options, and which checkpoint file was played."""
    path = "policies/a2c_gnn_synthetic.pt"
    played = marl_amod.evaluate(path, "synthetic", episodes=1, max_wait=2, objective="revenue")
    assert played["settings"] == {"max_wait": 2, "objective": "revenue", "solver": "fast", "policy_options": {}, "checkpoint": path}
    mpc = marl_amod.evaluate("mpc-forecast", "synthetic", episodes=1, horizon=4)["settings"]
    assert mpc["policy_options"] == {"horizon": 4} and "checkpoint" not in mpc and mpc["max_wait"] == 0


def test_a_policy_loaded_for_one_city_refuses_another():
    """Its graph and region count are the city's it was loaded for: another city's system is a clear
    error (it was a torch shape error deep in the actor), and loading it for that city plays there."""
    policy = marl_amod.load_policy("policies/a2c_gnn_synthetic.pt")
    grid = marl_amod.scenario.grid_city(3, 3, seed=0, horizon=4)
    with pytest.raises(ConfigError, match="loaded for synthetic .16 regions.; this system is grid3x3 .9 regions."):
        marl_amod.evaluate(policy, grid, episodes=1)
    assert marl_amod.evaluate(marl_amod.load_policy("policies/a2c_gnn_synthetic.pt", grid), grid, episodes=1)["episodes"] == 1
