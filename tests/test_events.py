"""Scenario events: a demand shock in the realised demand only, validated like every scenario key."""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.baselines.mpc import MPCForecast, MPCOracle
from marl_amod.errors import ConfigError
from marl_amod.scenario import load_city
from marl_amod.system import FleetSystem
from tests.conftest import needs_data

BASE = "name: base\nsource: synthetic\nrows: 3\ncols: 3\nhorizon: 8\n"
EVENT = """extends: base.yaml
name: shocked
events:
  - name: concert
    regions: [2, 4]
    start: 2
    end: 5
    multiplier: 5.0
    direction: {direction}
"""


def _write(tmp_path, direction="out", **changes):
    (tmp_path / "base.yaml").write_text(BASE)
    text = EVENT.format(direction=direction)
    for key, value in changes.items():
        text = text.replace(f"    {key}: ", f"    {key}: {value}  # was: ")
    (tmp_path / "event.yaml").write_text(text)
    return str(tmp_path / "event.yaml")


@pytest.mark.parametrize("direction", ["out", "in", "both"])
def test_an_event_multiplies_only_its_regions_window_and_direction(tmp_path, direction):
    city = load_city(_write(tmp_path, direction))
    base = load_city(str(tmp_path / "base.yaml"))
    ratio = np.divide(city.demand_rate, base.demand_rate, out=np.ones_like(base.demand_rate), where=base.demand_rate > 0)
    hit = np.zeros((9, 9), dtype=bool)
    if direction in ("out", "both"):
        hit[[2, 4], :] = True
    if direction in ("in", "both"):
        hit[:, [2, 4]] = True
    expected = np.ones_like(ratio)
    expected[2:5][:, hit] = 5.0
    expected[base.demand_rate == 0] = 1.0  # no demand to multiply (the diagonal)
    np.testing.assert_allclose(ratio, expected)
    # the forecast is the usual demand; prices and times are untouched
    np.testing.assert_array_equal(city.forecast_rate, base.demand_rate)
    np.testing.assert_array_equal(city.price, base.price)
    assert base.forecast_rate is base.demand_rate and city.meta["events"][0]["name"] == "concert"


def test_forecast_mpc_plans_the_usual_demand_and_the_oracle_the_draw(tmp_path):
    city = load_city(_write(tmp_path))
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(3))
    steps = np.arange(8)
    fc, orc = MPCForecast(), MPCOracle()
    np.testing.assert_array_equal(fc.forecast(system, steps), city.forecast_rate[steps])
    np.testing.assert_array_equal(orc.forecast(system, steps), system.sim.demand[steps])
    # the simulator's draw carries the surge: over many episodes, the event window out of region 2 is ~5x the
    # forecast, and the steps outside the window are the usual demand
    draws = []
    for s in range(200):
        system.reset(np.random.SeedSequence(s))
        draws.append(system.sim.demand[:, 2].copy())
    mean = np.mean(draws, axis=0)  # (T, N) requests out of region 2 per step and destination
    assert mean[2:5].sum() / city.forecast_rate[2:5, 2].sum() == pytest.approx(5.0, rel=0.1)
    assert mean[5:8].sum() / city.forecast_rate[5:8, 2].sum() == pytest.approx(1.0, rel=0.2)


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"multiplier": "-1"}, "events.0.multiplier"),
        ({"multiplier": ".nan"}, "events.0.multiplier"),
        ({"multiplier": ".inf"}, "events.0.multiplier"),
        ({"multiplier": "true"}, "multiplier must be a number"),
        ({"end": "1"}, "end .1. must be after start"),
        ({"regions": "[2, 2]"}, "distinct"),
        ({"regions": "[]"}, "events.0.regions"),
        ({"regions": "[9]"}, "events.0.regions: region 9 is out of range"),
        ({"start": "8", "end": "10"}, "events.0.start: step 8 is past"),
        ({"direction": "sideways"}, "events.0.direction"),
    ],
)
def test_bad_events_are_config_errors_naming_file_and_key(tmp_path, change, message):
    path = _write(tmp_path, **change)
    with pytest.raises(ConfigError, match=message) as err:
        load_city(path)
    assert "event.yaml" in str(err.value)


def test_unknown_event_keys_are_refused(tmp_path):
    path = _write(tmp_path)
    text = open(path).read().replace("    direction:", "    multipler: 2\n    direction:")
    open(path, "w").write(text)
    with pytest.raises(ConfigError, match="multipler"):
        load_city(path)


@needs_data
def test_brooklyn_special_event_hurts_the_forecast_planner_more_than_the_oracle():
    """The event scenario: the oracle keeps most of its profit, MPC-Forecast (blind to it) loses more."""
    from marl_amod.evaluation import evaluate

    city = load_city("nyc_brooklyn_event")
    assert city.meta["events"] and not np.array_equal(city.demand_rate, city.forecast_rate)
    profit = {p: evaluate(p, city, episodes=1)["metrics"]["profit"]["mean"] for p in ("mpc-forecast", "mpc-oracle")}
    assert profit["mpc-oracle"] > profit["mpc-forecast"]
