"""Every bundled scenario through the same checks, VMAS-style: PettingZoo's parallel API and seed
tests, observations and state inside their spaces, and a fleet that is conserved, at a short
horizon so each scenario costs seconds. A scenario whose data (``MARL_AMOD_DATA``) or extra
(``libsumo``) is missing is skipped with the reason; a new YAML file in ``envs/`` joins by itself."""

from __future__ import annotations

from importlib.util import find_spec
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import parallel_api_test, parallel_seed_test

import marl_amod
from marl_amod.data import ENV_VAR, resolve
from marl_amod.errors import DataError
from marl_amod.scenario import available, describe, load_spec
from marl_amod.scenario.registry import JsonScenario, SumoScenario
from tests.conftest import REAL_CITIES

ENVS = Path(__file__).resolve().parent.parent / "envs"
FILES = sorted(p.stem for p in ENVS.glob("*.yaml"))
HORIZON = 4  # control steps: enough for dispatch, rebalancing and arrivals, cheap even in SUMO


def _missing(name: str) -> str | None:
    """Why a scenario cannot run here, or None."""
    spec = load_spec(name)
    if isinstance(spec, SumoScenario) and find_spec("libsumo") is None:
        return 'needs the SUMO extra: pip install "marl-amod[sumo]"'
    data_file = spec.data_file if isinstance(spec, JsonScenario) else getattr(spec, "osm_file", None)
    if data_file:
        try:
            resolve(data_file)
        except DataError:
            return f"needs {data_file} under {ENV_VAR}"
    return None


def _kwargs(name: str, backend: str = "libsumo") -> dict:
    """Short-horizon env arguments. A large SUMO city keeps its roads and regions but gets a tenth
    of its fleet and demand (SUMO routes every trip: Luxembourg's full fleet costs seconds a step)."""
    spec = load_spec(name)
    extra: dict = {}
    if isinstance(spec, SumoScenario) and spec.mode != "macro":
        extra["backend"] = backend
    if isinstance(spec, SumoScenario) and spec.fleet > 100:
        extra.update(fleet=spec.fleet // 10, requests_per_hour=spec.requests_per_hour / 10)
    # a scenario with events runs until its first event has started, so the shock is exercised
    horizon = max([HORIZON, *(event.start + 2 for event in getattr(spec, "events", None) or [])])
    return {"scenario": name, "horizon": horizon, **extra}


def _params(slow_city: bool = False) -> list:
    """One param per scenario file. ``slow_city``: a whole city's road network in SUMO costs a few
    seconds per start, and the API and seed tests start it several times, so there they are marked
    slow (run with MARL_AMOD_SLOW=1); the bounds test always runs them."""
    params = []
    for name in FILES:
        reason = _missing(name)
        spec = load_spec(name)
        slow = slow_city and isinstance(spec, SumoScenario) and spec.mode != "macro" and spec.network == "osm"
        marks = [pytest.mark.skip(reason=reason)] if reason else [pytest.mark.slow] if slow else []
        params.append(pytest.param(name, id=name, marks=marks))
    return params


@pytest.mark.parametrize("name", _params(slow_city=True))
def test_parallel_api(name: str) -> None:
    parallel_api_test(marl_amod.parallel_env(**_kwargs(name)), num_cycles=HORIZON + 2)


@pytest.mark.parametrize("name", _params(slow_city=True))
def test_parallel_seed(name: str) -> None:
    """The seed test steps two envs in turn; libsumo holds one simulation per process, so a SUMO
    scenario's second env runs through TraCI (the backends agree exactly: tests/test_meso.py)."""
    backends = iter(("libsumo", "traci"))
    parallel_seed_test(lambda: marl_amod.parallel_env(**_kwargs(name, next(backends))), num_cycles=HORIZON + 2)


@pytest.mark.parametrize("name", _params())
def test_bounds_and_fleet_conservation(name: str) -> None:
    """Random weights for a whole short episode: every observation and the state lie in their
    spaces, served requests never exceed demand, local rewards sum to the team reward, and the
    simulator holds exactly the fleet after every step."""
    env = marl_amod.parallel_env(reward_mode="local", **_kwargs(name))
    observations, infos = env.reset(seed=0)
    rng = np.random.default_rng(0)
    fleet = env.city.fleet_size
    steps, profit = 0, infos[env.agents[0]]["system_profit"]
    while env.agents:
        for agent, obs in observations.items():
            assert env.observation_space(agent).contains(obs), f"{agent} observation out of bounds"
        assert env.state_space.contains(env.state())
        actions = {a: rng.random(1, dtype=np.float32) for a in env.agents}
        observations, rewards, _, _, infos = env.step(actions)
        steps += 1
        assert env.system.sim.vehicles() == fleet
        info = infos[next(iter(infos))]
        assert 0 <= info["system_served_demand"] <= info["system_demand"]
        step_profit, profit = info["system_profit"] - profit, info["system_profit"]
        assert sum(rewards.values()) == pytest.approx(step_profit, rel=1e-9, abs=1e-6)
    assert steps == env.city.horizon - 1
    env.close()


def test_every_scenario_file_is_covered_and_valid() -> None:
    """The suite runs every file in envs/; each file validates, is named after itself, and the real
    cities the other tests list are exactly the JSON scenarios."""
    assert FILES == available()
    for name in FILES:
        info = describe(name)
        assert info.error is None, info.error
        assert info.name == name, f"envs/{name}.yaml is named {info.name!r}"
    json_scenarios = [n for n in FILES if describe(n).source == "json"]
    assert set(REAL_CITIES) <= set(json_scenarios)
    city_files = {load_spec(n).data_file for n in REAL_CITIES}
    assert len(city_files) == len(REAL_CITIES)  # one scenario per city file; variants (events) reuse one
    assert {load_spec(n).data_file for n in json_scenarios} == city_files
