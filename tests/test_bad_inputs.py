"""Every class of bad input gives a marl_amod error naming the culprit, never a result (issue 13).

Classes: city files, City arrays, scenario YAML and overrides, policy outputs, the coordinator's
public functions, actions, seeds, sizes; plus the city cache and --output destinations.
"""

from __future__ import annotations

import dataclasses
import errno
import json
import os
import shutil
import tempfile
from pathlib import Path

import numpy as np
import pytest
from conftest import needs_data
from test_scenarios import load, write_city
from typer.testing import CliRunner

from marl_amod import parallel_env
from marl_amod.baselines.base import WeightPolicy
from marl_amod.cli import app
from marl_amod.coordinator import Coordinator, desired_targets, greedy_dispatch, min_cost_rebalance
from marl_amod.coordinator.reference import lp_rebalance
from marl_amod.data import ENV_VAR
from marl_amod.datasets import collect
from marl_amod.errors import ActionError, ConfigError, DataError, MarlAmodError
from marl_amod.evaluation import evaluate
from marl_amod.scenario import grid_city, load_city, load_spec
from marl_amod.sim.macro import MacroSim
from marl_amod.system import FleetSystem

runner = CliRunner()


def demand_item(**changes):
    item = {"time_stamp": 1140, "origin": 0, "destination": 1, "demand": 1.0, "travel_time": 5, "price": 10.0}
    return [{**item, **changes}]


def reb_rows(**changes):
    rows = [
        {"time_stamp": 19, "origin": 0, "destination": 1, "reb_time": 7.0},
        {"time_stamp": 19, "origin": 1, "destination": 0, "reb_time": 1.0},
    ]
    rows[1].update(changes)
    return rows


# --------------------------------------------------------------------------- city JSON
@pytest.mark.parametrize(
    "changes, culprit",
    [
        ({"demand": demand_item(price=float("nan"))}, r"item 0 of 'demand': price is not finite"),
        ({"demand": demand_item(price=float("inf"))}, r"item 0 of 'demand': price is not finite"),
        ({"demand": demand_item(price=-3.0)}, r"item 0 of 'demand': price must be >= 0"),
        ({"demand": demand_item(demand=-1.0)}, r"item 0 of 'demand': demand must be >= 0"),
        ({"demand": demand_item(travel_time=float("nan"))}, r"item 0 of 'demand': travel_time is not finite"),
        ({"demand": demand_item(origin=0.5)}, r"item 0 of 'demand': origin must be a region index"),
        ({"demand": demand_item(price="cheap")}, r"item 0 of 'demand'"),
        ({"demand": demand_item(price=True)}, r"item 0 of 'demand'"),
        ({"rebTime": reb_rows(origin=-1)}, r"item 1 of 'rebTime': origin must be a region index in \[0, 2\)"),
        ({"rebTime": reb_rows(destination=2)}, r"item 1 of 'rebTime': destination must be a region index"),
        ({"rebTime": reb_rows(reb_time=float("nan"))}, r"item 1 of 'rebTime': reb_time is not finite"),
        ({"rebTime": reb_rows(reb_time=-4.0)}, r"item 1 of 'rebTime': reb_time must be >= 0"),
        ({"rebTime": reb_rows(reb_time=1e12)}, r"item 1 of 'rebTime': reb_time must be at most 100000 minutes"),
        ({"demand": demand_item(travel_time=1e300)}, r"item 0 of 'demand': travel_time must be at most"),
        ({"totalAcc": [{"hour": 19, "acc": -5}]}, r"item 0 of 'totalAcc': acc must be >= 0"),
        ({"totalAcc": [{"hour": 19, "acc": 1}]}, r"fleet \(totalAcc for hour 19: 1\) is smaller than the 2 regions"),
        ({"topology_graph": [{"i": 0, "j": 7}]}, r"item 0 of 'topology_graph': j must be a region index"),
        ({"nlat": 0}, r"'nlat' must be a positive integer"),
        ({"nlon": "1"}, r"'nlon' must be a positive integer"),
    ],
)
def test_a_corrupted_city_file_names_the_file_item_and_field(tmp_path, changes, culprit):
    path = write_city(tmp_path, **changes)
    with pytest.raises(DataError, match=culprit) as exc:
        load(path)
    assert str(path) in str(exc.value)


def test_a_scenario_fleet_smaller_than_the_regions_is_refused(tmp_path):
    with pytest.raises(DataError, match=r"'fleet': 1\) is smaller than the 2 regions"):
        load(write_city(tmp_path), fleet=1)


@needs_data
def test_a_corrupted_copy_of_a_real_city_names_the_item(tmp_path, monkeypatch):
    """The real Brooklyn file with one price made NaN and one rebTime origin made negative."""
    source = Path(os.environ[ENV_VAR]) / "macro" / "scenario_nyc_brooklyn.json"
    (tmp_path / "macro").mkdir()
    data = json.loads(source.read_text())
    data["demand"][7]["price"] = float("nan")
    (tmp_path / "macro" / source.name).write_text(json.dumps(data))
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(DataError, match=r"scenario_nyc_brooklyn\.json: item 7 of 'demand': price is not finite"):
        load_city("nyc_brooklyn")
    data = json.loads(source.read_text())
    data["rebTime"][3]["origin"] = -1
    (tmp_path / "macro" / source.name).write_text(json.dumps(data))
    with pytest.raises(DataError, match=r"item 3 of 'rebTime': origin must be a region index"):
        load_city("nyc_brooklyn")


# --------------------------------------------------------------------------- City arrays
@pytest.mark.parametrize(
    "field, value, culprit",
    [
        ("price", np.nan, r"price is not finite \(nan\) at step 2, regions 1->3"),
        ("price", -1.0, r"price must be >= 0, got -1.0 at step 2, regions 1->3"),
        ("demand_rate", np.inf, r"demand_rate is not finite \(inf\) at step 2, regions 1->3"),
        ("trip_time", 0, r"trip_time \(steps\) must be >= 1, got 0 at step 2, regions 1->3"),
    ],
)
def test_city_arrays_are_checked_and_name_the_region(tiny_city, field, value, culprit):
    arr = getattr(tiny_city, field).copy()
    arr[2, 1, 3] = value
    with pytest.raises(DataError, match=culprit):
        dataclasses.replace(tiny_city, **{field: arr})


def test_city_rejects_negative_fleets_and_bad_edges(tiny_city):
    fleet = tiny_city.initial_vehicles.copy()
    fleet[4] = -2
    with pytest.raises(DataError, match=r"initial_vehicles must be >= 0, got -2 at region 4"):
        dataclasses.replace(tiny_city, initial_vehicles=fleet)
    with pytest.raises(DataError, match=r"edge_index names region 9 but the city has 9 regions"):
        dataclasses.replace(tiny_city, edge_index=np.array([[0], [9]]))
    with pytest.raises(DataError, match="tstep"):
        dataclasses.replace(tiny_city, tstep=float("inf"))


def test_every_city_array_is_read_only(tiny_city):
    for name in ("demand_rate", "price", "trip_time", "reb_time", "initial_vehicles", "edge_index", "positions"):
        with pytest.raises(ValueError, match="read-only"):
            getattr(tiny_city, name)[0] = 0


# --------------------------------------------------------------------------- scenario YAML
def write_yaml(tmp_path, text, name="s.yaml"):
    path = tmp_path / name
    path.write_text("name: s\nsource: synthetic\n" + text)
    return str(path)


@pytest.mark.parametrize(
    "text, culprit",
    [
        ("tstep: .inf\n", "tstep: Input should be a finite number"),
        ("fare_per_step: .nan\n", "fare_per_step: Input should be a finite number"),
        ("rows: true\n", "rows must be a number, got True"),
        ("beta: '0.5'\n", "beta must be a number"),
        ("rows: 1\ncols: 1\n", "at least 2 regions"),
        ("rows: 3\nrows: 4\n", "duplicate key 'rows'"),
        ("vehicles_per_region: 0\n", "vehicles_per_region: Input should be greater than or equal to 1"),
        ("colls: 4\n", "colls: unknown key; a synthetic scenario has .*cols"),
    ],
)
def test_bad_scenario_yaml_is_a_config_error_naming_the_key(tmp_path, text, culprit):
    path = write_yaml(tmp_path, text)
    with pytest.raises(ConfigError, match=culprit) as exc:
        load_city(path)
    assert "s.yaml" in str(exc.value)


def test_an_unknown_override_says_it_is_one_and_lists_the_scenarios_keys():
    """`parallel_env("synthetic", fleet=100)`: the synthetic city sizes its fleet by vehicles_per_region."""
    with pytest.raises(ConfigError, match=r"fleet: unknown key \(a keyword override\); a synthetic scenario has .*vehicles_per_region"):
        load_city("synthetic", fleet=100)


def test_overrides_are_validated_like_the_file():
    with pytest.raises(ConfigError, match="tstep: Input should be a finite number"):
        load_city("synthetic", tstep=float("inf"))
    with pytest.raises(ConfigError, match="horizon must be a number"):
        load_city("synthetic", horizon=True)
    assert load_city("synthetic", horizon=np.int64(5)).horizon == 5  # numpy integers are integers
    with pytest.raises(ConfigError, match="at least 2 regions"):
        grid_city(1, 1)


def test_a_broken_scenario_is_a_marl_amod_error_the_listing_can_catch(tmp_path):
    """`marl-amod scenarios` marks a broken scenario and lists the others: every failure of one
    scenario is a MarlAmodError (pydantic, numpy and YAML errors never escape)."""
    (tmp_path / "macro").mkdir()
    (tmp_path / "macro" / "c.json").write_text(write_city(tmp_path).read_text().replace('"price": 10.0', '"price": NaN'))
    (tmp_path / "c.yaml").write_text(
        "name: c\nsource: json\ndata_file: macro/c.json\ntstep: 3\nstart_hour: 19\ndemand_ratio: 1\nbeta: 0.5\n"
    )
    for broken in (write_yaml(tmp_path, "rows: [1\n", "a.yaml"), write_yaml(tmp_path, "rows: -1\n", "b.yaml")):
        with pytest.raises(ConfigError):
            load_spec(broken)
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(ENV_VAR, str(tmp_path))
        with pytest.raises(MarlAmodError, match="price is not finite"):
            load_city(str(tmp_path / "c.yaml"))


# --------------------------------------------------------------------------- city cache
def test_the_city_cache_follows_the_data_folder_and_file(tmp_path, monkeypatch):
    for folder, acc in (("a", 10), ("b", 40)):
        (tmp_path / folder / "macro").mkdir(parents=True)
        write_city(tmp_path / folder / "macro", totalAcc=[{"hour": 19, "acc": acc}])
    scenario = tmp_path / "c.yaml"
    scenario.write_text("name: c\nsource: json\ndata_file: macro/city.json\ntstep: 3\nstart_hour: 19\ndemand_ratio: 1\nbeta: 0.5\n")
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "a"))
    first = load_city(str(scenario))
    assert first.fleet_size == 10 and load_city(str(scenario)) is first  # cached while nothing changed
    monkeypatch.setenv(ENV_VAR, str(tmp_path / "b"))
    assert load_city(str(scenario)).fleet_size == 40
    write_city(tmp_path / "b" / "macro", totalAcc=[{"hour": 19, "acc": 100}])  # the file is replaced
    assert load_city(str(scenario)).fleet_size == 100
    monkeypatch.delenv(ENV_VAR)
    with pytest.raises(DataError, match=ENV_VAR):
        load_city(str(scenario))


@needs_data
def test_the_real_city_cache_does_not_outlive_its_data(tmp_path, monkeypatch):
    city = load_city("nyc_brooklyn")
    assert not city.edge_index.flags.writeable and not city.positions.flags.writeable
    monkeypatch.setenv(ENV_VAR, str(tmp_path))
    with pytest.raises(DataError, match="scenario_nyc_brooklyn.json"):
        load_city("nyc_brooklyn")


# --------------------------------------------------------------------------- policy outputs
class NanPolicy(WeightPolicy):
    """A learned policy whose network has diverged: NaN weights (used to mean 'stay', silently)."""

    name = "nan"

    def weights(self, system):
        w = np.ones(system.city.n_regions)
        w[3] = np.nan
        return w


def test_nan_policy_weights_raise_instead_of_meaning_stay(tiny_city):
    with pytest.raises(ActionError, match=r"rebalancing weights is not finite \(nan\) at region 3"):
        evaluate(NanPolicy(), tiny_city, episodes=1)


def test_a_diverged_network_raises_instead_of_meaning_stay(tiny_city):
    """A GNN actor whose parameters became NaN (as after a diverged update), run as a policy."""
    torch = pytest.importorskip("torch")
    from marl_amod.checkpoints import ActorPolicy
    from marl_amod.models import build_actor

    actor = build_actor("gnn", tiny_city)
    with torch.no_grad():
        for param in actor.parameters():
            param.fill_(float("nan"))
    with pytest.raises(ActionError, match="rebalancing weights is not finite"):
        evaluate(ActorPolicy(actor, tiny_city), tiny_city, episodes=1)


# --------------------------------------------------------------------------- coordinator
def test_the_coordinators_public_functions_check_their_inputs(tiny_city):
    coord = Coordinator(tiny_city)
    n = tiny_city.n_regions
    idle = np.full(n, 5)
    with pytest.raises(ActionError, match="region 1"):
        desired_targets(np.array([1.0, np.inf, 1.0]), 10)
    with pytest.raises(ActionError, match=r"weights must be >= 0, got -1.0 at region 0"):
        coord.targets(np.r_[-1.0, np.ones(n - 1)], idle)
    with pytest.raises(ActionError, match=r"weights must have shape \(9,\)"):
        coord.targets(np.ones(4), idle)
    with pytest.raises(ActionError, match=r"rebalancing target must be whole numbers, got 0.5 at region 2"):
        coord.rebalance(idle, np.r_[0, 0, 0.5, np.zeros(n - 3)])
    with pytest.raises(ActionError, match=r"rebalancing target must have shape \(9,\)"):
        coord.rebalance(idle, np.zeros(3))
    with pytest.raises(DataError, match=r"idle vehicles is not finite \(nan\) at region 0"):
        coord.rebalance(np.r_[np.nan, idle[1:]], np.zeros(n))
    with pytest.raises(DataError, match=r"idle vehicles must have shape \(9,\)"):
        coord.rebalance(np.ones(4), np.zeros(4))
    requests = np.zeros((n, n), dtype=np.int64)
    requests[0, 1] = -1
    with pytest.raises(DataError, match=r"requests must be >= 0, got -1 at regions 0->1"):
        coord.dispatch(idle, requests, 0)
    with pytest.raises(DataError, match="dispatch step t"):
        coord.dispatch(idle, np.zeros((n, n)), tiny_city.n_steps)
    with pytest.raises(DataError, match=r"dispatch margin is not finite \(inf\) at regions 0->0"):
        greedy_dispatch(np.ones(2), np.ones((2, 2)), np.full((2, 2), np.inf))
    with pytest.raises(DataError, match=r"rebalancing cost is not finite \(nan\) at regions 0->1"):
        min_cost_rebalance(np.ones(2), np.zeros(2), np.array([[0, np.nan], [1, 0]]))
    cvxpy_coord = Coordinator(tiny_city, solver="cvxpy")
    with pytest.raises(ActionError, match="rebalancing target"):
        cvxpy_coord.rebalance(idle, np.full(n, np.nan))


@pytest.mark.parametrize("metric", [False, True])
def test_min_cost_rebalance_is_optimal_on_float_costs(metric):
    """Costs that are not whole numbers are scaled, not truncated: the LP's optimum on 20 random instances."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        n = int(rng.integers(3, 9))
        if metric:  # Euclidean distances obey the triangle inequality
            xy = rng.uniform(0, 3, size=(n, 2))
            cost = np.linalg.norm(xy[:, None] - xy[None, :], axis=2)
        else:
            cost = rng.uniform(0.01, 2.0, size=(n, n))
            np.fill_diagonal(cost, 0)
        idle = rng.integers(0, 8, size=n)
        target = desired_targets(rng.uniform(0, 1, size=n), int(idle.sum()))
        y = min_cost_rebalance(idle, target, cost, metric=metric)
        best = (lp_rebalance(idle, target, cost) * cost).sum()
        assert (y * cost).sum() == pytest.approx(best, rel=1e-7, abs=1e-7)


# --------------------------------------------------------------------------- actions and seeds
@pytest.mark.parametrize("bad", ["0.5", np.array(["0.5"]), 0.5 + 1j, np.array([0.5 + 0j]), None, {"w": 1}])
def test_strings_and_complex_numbers_are_not_actions(bad):
    env = parallel_env("synthetic", horizon=4)
    env.reset(seed=0)
    actions = {a: np.array([0.5], dtype=np.float32) for a in env.agents}
    actions["region_2"] = bad
    with pytest.raises(ActionError, match="region_2"):
        env.step(actions)


def test_numpy_seeds_are_seeds_and_negative_seeds_a_clear_error():
    env = parallel_env("synthetic", horizon=4)
    a, _ = env.reset(seed=np.int64(3))
    b, _ = env.reset(seed=3)
    assert all(np.array_equal(a[k], b[k]) for k in a)
    with pytest.raises(ConfigError, match="seed must be a non-negative integer, got -1"):
        env.reset(seed=-1)
    with pytest.raises(ConfigError, match="seed must be a non-negative integer, got 1.5"):
        env.reset(seed=1.5)
    with pytest.raises(ConfigError, match="seed must be a non-negative integer"):
        evaluate("equal-distribution", "synthetic", episodes=1, seed=-1)
    result = runner.invoke(app, ["evaluate", "--episodes", "1", "--seed", "-1"])
    assert result.exit_code == 2 and "--seed" in result.output
    for episodes in (0, -1):  # one message for every count below one
        with pytest.raises(ConfigError, match=f"episodes must be an integer >= 1, got {episodes}"):
            evaluate("equal-distribution", "synthetic", episodes=episodes)
    with pytest.raises(ConfigError, match="validate must be True or False, got 'false'"):  # bool("false") would switch it on
        evaluate("equal-distribution", "synthetic", episodes=1, validate="false")


def test_max_wait_and_episode_counts_are_bounded_up_front(tiny_city):
    with pytest.raises(ConfigError, match=r"max_wait \(steps\) must be at most 6, the horizon of grid3x3"):
        FleetSystem(tiny_city, max_wait=10**9)
    with pytest.raises(ConfigError, match="max_wait"):
        MacroSim(tiny_city, max_wait=True)
    assert FleetSystem(tiny_city, max_wait=np.int64(6)).sim.max_wait == 6
    with pytest.raises(ConfigError, match="episodes must be an integer >= 1"):
        evaluate("equal-distribution", tiny_city, episodes=0)
    with pytest.raises(ConfigError, match="episodes must be an integer >= 1"):
        collect(tiny_city, NanPolicy(), episodes=0)


# --------------------------------------------------------------------------- outputs
@pytest.mark.parametrize("command", ["evaluate", "collect"])
def test_a_bad_output_is_refused_before_the_run(tmp_path, command):
    (tmp_path / "file").write_text("x")
    for output, message in ((tmp_path, "is a directory"), (tmp_path / "file" / "r.json", "is a file, not a folder")):
        result = runner.invoke(app, [command, "--episodes", "1", "--output", str(output)])
        assert isinstance(result.exception, MarlAmodError), result.output
        assert message in str(result.exception) and str(output) in str(result.exception)


@pytest.mark.skipif(os.geteuid() == 0, reason="root writes into read-only folders")
def test_a_read_only_output_folder_is_refused_before_the_run(tmp_path):
    folder = tmp_path / "ro"
    folder.mkdir()
    folder.chmod(0o500)
    try:
        result = runner.invoke(app, ["evaluate", "--episodes", "1", "--output", str(folder / "r.json")])
        assert "is not writable" in str(result.exception)
    finally:
        folder.chmod(0o700)


@pytest.mark.parametrize("command", ["evaluate", "collect"])
def test_a_failing_final_write_saves_the_results_elsewhere_and_says_where(tmp_path, monkeypatch, command):
    """A full disk at the very end: the results go to a fresh folder and the error names it."""
    import marl_amod.files as files

    monkeypatch.setattr(tempfile, "tempdir", str(tmp_path / "tmp"))
    (tmp_path / "tmp").mkdir()
    output = tmp_path / "out" / ("r.json" if command == "evaluate" else "d.npz")
    real = files.atomic_open

    def full_disk(path, mode="wb"):
        if Path(path) == output:
            raise OSError(errno.ENOSPC, "No space left on device")
        return real(path, mode)

    monkeypatch.setattr(files, "atomic_open", full_disk)
    result = runner.invoke(app, [command, "--episodes", "1", "--output", str(output)])
    message = str(result.exception)
    assert isinstance(result.exception, MarlAmodError) and "No space left on device" in message
    saved = Path(message.rsplit("saved in ", 1)[1])
    assert saved.is_file() and saved.parent.parent == tmp_path / "tmp" and not output.exists()
    if command == "evaluate":
        assert json.loads(saved.read_text())["episodes"] == 1
    shutil.rmtree(saved.parent)
