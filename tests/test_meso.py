"""The SUMO (meso) simulator behind the same system and env: conservation, accounting, determinism,
the PettingZoo API, and configuration errors. A 14-minute grid episode takes well under a second."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("libsumo")

from conftest import has_data  # noqa: E402

from marl_amod.env.parallel import AmodParallelEnv  # noqa: E402
from marl_amod.errors import ConfigError, DataError  # noqa: E402
from marl_amod.evaluation import evaluate  # noqa: E402
from marl_amod.scenario import load_city, load_spec  # noqa: E402
from marl_amod.scenario.simspec import SimSpec  # noqa: E402
from marl_amod.scenario.sumo.network import read_network  # noqa: E402
from marl_amod.sim.base import make_simulator  # noqa: E402
from marl_amod.sim.meso.sumo_sim import MesoSim  # noqa: E402
from marl_amod.sim.meso.taxi_sim import TaxiMesoSim  # noqa: E402
from marl_amod.sim.meso.types import RequestState  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402


def _episode(seed: int, *, weights=None, **overrides):
    """Run one grid episode, checking the invariants after every step; returns the system."""
    city = load_city("sumo_grid", **overrides)
    system = FleetSystem(city)
    system.reset(seed)
    sim = system.sim
    assert isinstance(sim, MesoSim)
    fleet = city.fleet_size
    n = city.n_regions
    rng = np.random.default_rng(seed)
    while not system.done:
        w = rng.random(n) if weights is None else weights
        out = system.step(system.targets_from_weights(w))
        tot = sim.totals
        assert sim.vehicles() == fleet  # no vehicle created or lost
        assert sim.idle.min() >= 0 and sim.idle.sum() <= fleet
        assert out.rebalancing.sum(axis=1).min() >= 0 and np.all(np.diag(out.rebalancing) == 0)
        # every request is served, still open, or gone after its maximum wait
        assert tot.demand.sum() == tot.served.sum() + tot.lost.sum() + sim.requests().sum()
        assert getattr(sim, "longest_dispatch_wait_s", 0.0) < 60  # taxis: every assignment reaches SUMO
    tot = sim.totals
    assert tot.demand.sum() == tot.served.sum() + tot.lost.sum()  # finish() closed the books
    assert sim.teleports == 0
    return system


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_meso_grid_episode_conserves_fleet_and_accounts_for_every_request(taxi_device):
    system = _episode(0, taxi_device=taxi_device)
    tot = system.sim.totals
    assert tot.served.sum() > 0 and tot.rebalanced.sum() > 0
    assert 0 < tot.busy_vehicle_steps.sum() <= system.city.fleet_size * system.city.horizon
    assert tot.wait_minutes.sum() > 0  # pickups take real driving time in SUMO


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_meso_same_seed_same_result_and_other_seed_differs(taxi_device):
    a, b, c = (_episode(s, taxi_device=taxi_device).sim.totals for s in (3, 3, 4))
    for name in a.__dataclass_fields__:
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    assert not np.array_equal(a.demand, c.demand)


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_meso_requests_leave_after_max_wait(taxi_device):
    # one vehicle and heavy demand: most requests must time out rather than wait forever
    city = load_city("sumo_grid", fleet=1, requests_per_hour=600, max_wait_min=2, taxi_device=taxi_device)
    system = FleetSystem(city)
    system.reset(0)
    while not system.done:
        system.step(np.full(city.n_regions, -1))
        if taxi_device:  # a request that left is no longer a person waiting in SUMO
            sim = system.sim
            lost = {f"req{k}" for k in sim.ride_requests.in_state(RequestState.LOST)}
            assert not lost & set(sim.sumo.person.getIDList())
    tot = system.sim.totals
    assert tot.lost.sum() > tot.served.sum() > 0
    assert tot.demand.sum() == tot.served.sum() + tot.lost.sum()


def test_taxi_device_fleet_is_sumo_taxis_and_serves_like_the_leg_model():
    legs = _episode(0, requests_per_hour=600, fleet=40)
    taxi = _episode(0, requests_per_hour=600, fleet=40, taxi_device=True)
    assert isinstance(taxi.sim, TaxiMesoSim) and not isinstance(legs.sim, TaxiMesoSim)
    assert len(taxi.sim.sumo.vehicle.getTaxiFleet(-1)) == 40  # every fleet vehicle is one SUMO taxi
    a, b = legs.sim.totals, taxi.sim.totals
    np.testing.assert_array_equal(a.demand, b.demand)  # same requests; only the driving differs
    assert b.served.sum() > 0 and abs(b.served.sum() - a.served.sum()) <= 0.15 * a.served.sum()
    assert 0 < b.wait_minutes.sum() / b.served.sum() < taxi.city.tstep * 5  # boarding happens in SUMO


def test_meso_evaluate_gives_the_macro_json_schema():
    res = evaluate("equal-distribution", "sumo_grid", episodes=1, seed=0)
    macro = evaluate("equal-distribution", load_city("synthetic", horizon=3), episodes=1, seed=0)
    assert res["metrics"].keys() == macro["metrics"].keys()
    assert res["per_region"].keys() == macro["per_region"].keys()
    assert len(res["per_region"]["wait_time"]) == 4


def test_the_evaluate_command_says_waits_are_zero_only_where_they_are():
    from typer.testing import CliRunner

    from marl_amod.cli import app

    for scenario, note in (("sumo_grid", False), ("synthetic", True)):  # SUMO's requests wait for their pickup at --max-wait 0 too
        result = CliRunner().invoke(app, ["evaluate", "--scenario", scenario, "--episodes", "1"])
        assert result.exit_code == 0, result.output
        assert ("wait min and wait Gini are 0" in " ".join(result.output.split())) is note, scenario


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_mpc_plans_on_meso_with_the_requests_that_will_still_wait(taxi_device):
    city = load_city("sumo_grid", fleet=6, requests_per_hour=900, max_wait_min=3, taxi_device=taxi_device)
    for policy in ("mpc-oracle", "mpc-forecast"):
        assert evaluate(policy, city, episodes=1, seed=0)["metrics"]["served_demand"]["mean"] > 0
    system = FleetSystem(city)
    system.reset(0)
    sim, leaving = system.sim, 0
    while not system.done:
        sim.apply_rebalance(np.zeros((4, 4), dtype=np.int64))
        carried, open_now = sim.carried_over(), sim.requests()
        assert np.all(carried <= open_now)
        leaving += int((open_now - carried).sum())
        sim.advance()
        assert np.all(sim.requests() >= carried)  # nothing carried over has left
        sim.apply_dispatch(system.coordinator.dispatch(sim.idle, sim.requests(), sim.t))
    assert leaving > 0  # some open requests were not carried: they left at their maximum wait


def test_meso_city_is_a_valid_region_view():
    city = load_city("sumo_grid")
    assert city.n_regions == 4 and city.fleet_size == 24
    assert city.edge_index.shape[0] == 2 and city.edge_index.shape[1] > 0
    assert np.all(city.price > 0) and np.all(city.trip_time >= 1)


def test_meso_simulator_pickles_without_its_sumo_connection():
    import pickle

    def first_step(system: FleetSystem) -> list[np.ndarray]:
        start = system.reset(1)
        step = system.step(system.targets_from_weights(np.ones(4)))
        return [start.dispatch, step.dispatch, step.rebalancing, step.region_profit, system.sim.idle.copy()]

    system = FleetSystem(load_city("sumo_grid"))
    system.reset(0)
    copy = pickle.loads(pickle.dumps(system))  # mid-episode, with SUMO running: the connection is not pickled
    got = first_step(copy)  # the copy restarts SUMO itself
    for a, b in zip(got, first_step(FleetSystem(load_city("sumo_grid"))), strict=True):  # as a fresh system does
        np.testing.assert_array_equal(a, b)
    assert got[0].sum() > 0  # the episode dispatched someone: the comparison is not of empty arrays


def test_sumo_scenario_config_errors(tmp_path: Path):
    with pytest.raises(ConfigError, match="osm_file"):
        load_spec("sumo_grid", network="osm")
    with pytest.raises(ConfigError, match="fleett"):
        load_spec("sumo_grid", fleett=3)
    with pytest.raises(ConfigError, match="mode"):
        load_spec("sumo_grid", mode="nano")
    bad = tmp_path / "nowhere.yaml"
    bad.write_text("name: x\nsource: sumo\nnetwork: osm\nosm_file: lux/missing.osm\nfleet: 3\nrequests_per_hour: 10\n")
    monkey_data = tmp_path / "data"
    monkey_data.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MARL_AMOD_DATA", str(monkey_data))
        with pytest.raises(DataError, match="missing.osm"):
            load_city(str(bad))


def test_missing_sumo_extra_names_the_install_command(monkeypatch):
    import sys

    from marl_amod.scenario.sumo import install

    monkeypatch.setitem(sys.modules, "sumo", None)  # import sumo now fails
    with pytest.raises(ConfigError, match=r'pip install "marl-amod\[sumo\]"'):
        install.sumo_home()


def test_meso_flows_are_validated():
    system = FleetSystem(load_city("sumo_grid"))
    system.reset(0)
    with pytest.raises(ValueError, match="diagonal"):
        system.sim.apply_rebalance(np.eye(4, dtype=int))
    with pytest.raises(ValueError, match="open"):
        system.sim.apply_dispatch(np.full((4, 4), 1000))


def _has_lux() -> bool:
    return has_data() and (Path(os.environ["MARL_AMOD_DATA"]) / "lux").is_dir()


@pytest.mark.skipif(not _has_lux(), reason="set MARL_AMOD_DATA to a folder with lux/ to build Luxembourg")
def test_lux_network_and_regions_build():
    city = load_city("lux", horizon=2)
    assert city.n_regions == 10 and city.fleet_size == load_spec("lux").fleet
    spec = city.simulator
    assert isinstance(spec, SimSpec) and spec.kind == "meso"  # data naming the simulator, no factory
    net = read_network(spec.sumo.net_file)
    assert net.n_edges > 1000 and len(spec.sumo.of_edge) == net.n_edges  # every usable edge has a region
    assert np.all(np.bincount(spec.sumo.of_edge, minlength=10) > 0)  # and no region is empty
    off = ~np.eye(10, dtype=bool)
    assert np.all(city.reb_time[off] >= 1) and np.all(city.trip_time[:, off] >= 1)  # regions apart take time


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_meso_traci_backend_matches_libsumo(taxi_device):
    a = _episode(5, taxi_device=taxi_device).sim.totals
    b = _episode(5, backend="traci", taxi_device=taxi_device).sim.totals
    for name in a.__dataclass_fields__:
        np.testing.assert_allclose(getattr(a, name), getattr(b, name))


def test_micro_mode_runs_the_same_episode_contract():
    system = _episode(0, mode="micro")
    assert system.sim.options.mode == "micro" and "--mesosim" not in system.sim.sumo_args()


def test_macro_twin_is_the_same_city_without_sumo():
    meso, macro = load_city("sumo_grid"), load_city("sumo_grid", mode="macro")
    assert macro.simulator.kind == "macro" and meso.simulator.kind == "meso"
    assert type(make_simulator(meso)) is MesoSim and type(make_simulator(load_city("sumo_grid", taxi_device=True))) is TaxiMesoSim
    np.testing.assert_array_equal(meso.demand_rate, macro.demand_rate)
    np.testing.assert_array_equal(meso.reb_time, macro.reb_time)
    assert type(FleetSystem(macro).sim).__name__ == "MacroSim"


def test_meso_travel_times_follow_sumo_and_the_system_adopts_them():
    system = _episode(0, requests_per_hour=600, fleet=60)
    assert system.city is system.sim.city  # coordinator and observations read the simulator's view
    assert np.all(system.city.trip_time >= 1)


def test_a_second_libsumo_simulation_makes_the_first_refuse_to_continue():
    first, second = FleetSystem(load_city("sumo_grid")), FleetSystem(load_city("sumo_grid"))
    first.reset(0)
    second.reset(0)  # libsumo: one simulation per process
    with pytest.raises(RuntimeError, match="traci"):
        first.step(first.targets_from_weights(np.ones(4)))
    second.step(second.targets_from_weights(np.ones(4)))
    first.reset(1)  # a reset takes the simulation back
    first.step(first.targets_from_weights(np.ones(4)))


def test_meso_env_renders_the_region_map():
    env = AmodParallelEnv("sumo_grid", render_mode="rgb_array")
    env.reset(seed=0)
    env.step({a: np.array([1.0], dtype=np.float32) for a in env.agents})
    assert env.render().ndim == 3


def test_meso_matches_more_often_than_it_rebalances():
    system = _episode(0, tstep=3, horizon=5, dispatch_every_min=1)
    assert system.sim.dispatch_rounds == 3
    assert system.sim.totals.served.sum() > 0
    with pytest.raises(ConfigError, match="divide"):
        load_spec("sumo_grid", tstep=3, dispatch_every_min=2)


@pytest.mark.skipif(not _has_lux(), reason="set MARL_AMOD_DATA to a folder with lux/ to build Luxembourg")
def test_lux_taxi_sent_to_a_pickup_on_the_edge_it_is_driving_is_not_lost():
    # Found on Luxembourg (episode (0, 1)): a taxi still driving from its insertion was sent to a
    # pickup on that same edge; meso skips a stop added on the segment a vehicle is in, so it drove
    # past and left the network. The simulator now waits until such a taxi parks.
    city = load_city("lux_taxi")
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence([0, 1]))
    for _ in range(3):
        system.step(np.full(city.n_regions, -1))  # raises if SUMO lost a taxi
        # and none waits for ever: meso reports a parked taxi as neither stopped nor moving
        assert system.sim.longest_dispatch_wait_s < 60
    assert system.sim.vehicles() == city.fleet_size


@pytest.mark.parametrize("taxi_device", [False, True], ids=["legs", "taxi_device"])
def test_background_traffic_shares_the_roads_and_the_fleet_is_still_conserved(taxi_device):
    system = _episode(0, background_per_hour=3000, taxi_device=taxi_device)  # checks conservation every step
    api = system.sim.sumo
    others = [v for v in api.vehicle.getIDList() if v.startswith("bg")]
    assert len(others) > 50  # randomTrips' cars are on the roads next to the fleet
    routes = system.sim.options.route_files
    assert routes and load_city("sumo_grid", background_per_hour=3000).simulator.sumo.route_files == routes  # cached
    assert load_city("sumo_grid", background_per_hour=3000, mode="macro").simulator.kind == "macro"


def _sumo_children() -> set[int]:
    """Process ids of the ``sumo`` processes this test process started and has not reaped."""
    import psutil  # a dependency of torch-geometric, so always installed

    return {p.pid for p in psutil.Process().children(recursive=True) if p.name() == "sumo"}


def test_traci_env_close_and_garbage_collection_end_the_sumo_process():
    import gc

    before = _sumo_children()
    env = AmodParallelEnv("sumo_grid", backend="traci")
    env.reset(seed=0)
    env.step({a: np.array([1.0], dtype=np.float32) for a in env.agents})
    assert len(_sumo_children() - before) == 1  # TraCI runs SUMO as a child process
    env.close()
    assert _sumo_children() == before
    env.reset(seed=1)  # a closed env starts a new run on reset
    assert len(_sumo_children() - before) == 1
    env.close()
    dropped = FleetSystem(load_city("sumo_grid", backend="traci"))
    dropped.reset(0)
    assert len(_sumo_children() - before) == 1
    del dropped  # never closed: collecting the simulator ends its run
    gc.collect()
    assert _sumo_children() == before


def test_libsumo_env_close_unloads_the_simulation():
    import libsumo

    env = AmodParallelEnv("sumo_grid")
    env.reset(seed=0)
    assert libsumo.simulation.isLoaded()
    env.close()
    assert not libsumo.simulation.isLoaded()
    with pytest.raises(RuntimeError, match="reset"):
        _ = env.system.sim.sumo
    other = FleetSystem(load_city("sumo_grid"))
    other.reset(0)
    env.reset(seed=0)  # takes libsumo over from `other`
    other.close()  # so closing `other` must leave env's simulation running
    assert libsumo.simulation.isLoaded()
    env.step({a: np.array([1.0], dtype=np.float32) for a in env.agents})
    env.close()
    assert not libsumo.simulation.isLoaded()
