"""Scenario variants by name (scenario/variants.py): every entry point that takes a scenario name
(load_city, parallel_env, vector_env, the CLI) takes ``<scenario>~hot<r>x<m>``, ``<scenario>~sink<r>x<m>``,
``<scenario>~skew<gamma>`` and ``<scenario>~ev...``, built on the scenario with its overrides first; a malformed one is one line."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from typer.testing import CliRunner

import marl_amod
from marl_amod.algos import meta
from marl_amod.cli import app
from marl_amod.errors import ConfigError
from marl_amod.scenario import load_city
from marl_amod.scenario.variants import base_city, event_task, hotspot, in_out_imbalance, sink, skew, split
from tests.conftest import needs_data

HOT = "synthetic~hot2x3"  # requests out of region 2 x3 against the rest, draw and forecast
EVENT = "synthetic~ev3+7x20@2-8"  # requests out of regions 3 and 7 x20 over steps [2, 8), draw only
VALUE = slice(7, 13)  # an agent's own expected request values over the look-ahead (lookahead 6)


def _same_city(a, b) -> None:
    assert a.name == b.name and a.horizon == b.horizon and a.meta == b.meta
    for table in ("demand_rate", "forecast_rate", "price", "trip_time", "reb_time", "initial_vehicles"):
        np.testing.assert_array_equal(getattr(a, table), getattr(b, table), err_msg=table)


def _parallel_demand(name: str, seeds: range) -> np.ndarray:
    """(T, N) requests that appeared per step and region, summed over episodes of ``seeds`` with no rebalancing."""
    env = marl_amod.parallel_env(name)
    total = np.zeros((env.max_cycles + 1, len(env.possible_agents)))
    for seed in seeds:
        _, infos = env.reset(seed=seed)
        rows = [[infos[a]["demand"] for a in env.possible_agents]]
        while env.agents:
            _, _, _, _, infos = env.step({a: np.zeros(1, np.float32) for a in env.agents})
            rows.append([infos[a]["demand"] for a in env.possible_agents])
        total += np.array(rows)
    return total


def _vector_demand(name: str, num_envs: int) -> np.ndarray:
    """(T, N) requests per step and region, summed over the batch's ``num_envs`` episodes (seed 0)."""
    env = marl_amod.vector_env(name, num_envs=num_envs)
    _, infos = env.reset(seed=0)
    rows = [infos["demand"].sum(axis=0)]
    for _ in range(env.max_cycles):
        _, _, _, _, infos = env.step(np.zeros((num_envs, env.city.n_regions)))
        rows.append(infos["demand"].sum(axis=0))
    return np.array(rows)


def test_load_city_builds_a_variant_on_its_scenario_with_the_overrides_first(tmp_path):
    """The name is the base scenario (bundled or a YAML path, overrides applied) then the variant,
    bit for bit what hotspot / event_task give; variants stack left to right; meta.task_city is
    this very call; a YAML path with a ``~`` in its folder is still a plain path."""
    base = load_city("synthetic", horizon=9)
    _same_city(load_city(HOT, horizon=9), hotspot(base, 2, 3.0))
    _same_city(load_city(EVENT, horizon=9), event_task(base, [3, 7], 20.0, 2, 8))
    assert load_city(HOT, horizon=9).horizon == 9 and load_city(HOT).horizon == 20
    stacked = load_city(f"{HOT}~ev5x2@0-4dr2x0.5")
    _same_city(stacked, event_task(hotspot(load_city("synthetic"), 2, 3.0), [5], 2.0, 0, 4, [2], 0.5))
    assert stacked.name == "synthetic~hot2x3~ev5x2@0-4dr2x0.5" and base_city(stacked.name) == "synthetic"
    assert meta.task_city is load_city and meta.hotspot is hotspot and meta.event_task is event_task

    folder = tmp_path / "a~b"
    folder.mkdir()
    (folder / "mine.yaml").write_text("name: mine\nsource: synthetic\nrows: 2\ncols: 3\nhorizon: 6\n")
    path = str(folder / "mine.yaml")
    assert split(path) == (path, None) and load_city(path).name == "mine"
    _same_city(load_city(f"{path}~hot1x2"), hotspot(load_city(path), 1, 2.0))
    assert [e["regions"] for e in load_city(path + "~ev0+4x3@1-3").meta["events"]] == [[0, 4]]


def test_a_hotspot_over_a_window_changes_only_those_steps_and_keeps_every_steps_total():
    """``~hot<r>x<m>@<s>-<e>``: inside [s, e) the region's share of the requests out rises as the
    all-day hotspot's does, in the draw and the forecast; outside it the city is untouched; each
    step's total stays; the name rebuilds the city."""
    base, day = load_city("synthetic"), load_city("synthetic~hot2x3")
    late = load_city("synthetic~hot2x3@15-20")
    assert late.name == "synthetic~hot2x3@15-20" and late.meta["hotspot"] == {"region": 2, "multiplier": 3.0, "start": 15, "end": 20}
    _same_city(late, hotspot(base, 2, 3.0, 15, 20))
    for table in ("demand_rate", "forecast_rate"):
        b, d, w = (np.asarray(getattr(c, table)) for c in (base, day, late))
        np.testing.assert_array_equal(w[:15], b[:15])
        np.testing.assert_array_equal(w[20:], b[20:])
        np.testing.assert_allclose(w[15:20], d[15:20])
        np.testing.assert_allclose(w.sum(axis=(1, 2)), b.sum(axis=(1, 2)))
        share = w[15:20, 2].sum() / w[15:20].sum()
        assert share > 1.5 * b[15:20, 2].sum() / b[15:20].sum()
    with pytest.raises(ConfigError, match="needs both start and end"):
        hotspot(base, 2, 3.0, start=4)


def test_a_variant_on_a_scenario_with_events_keeps_them_and_adds_its_own(tmp_path):
    (tmp_path / "shocked.yaml").write_text(
        "name: shocked\nsource: synthetic\nrows: 2\ncols: 2\nhorizon: 6\n"
        "events: [{name: concert, regions: [1], start: 1, end: 3, multiplier: 4.0}]\n"
    )
    plain = load_city(str(tmp_path / "shocked.yaml"))
    both = load_city(str(tmp_path / "shocked.yaml") + "~ev2x5@2-4")
    assert [e["name"] for e in both.meta["events"]] == ["concert", "surge"]
    np.testing.assert_array_equal(both.forecast_rate, plain.forecast_rate)  # neither is in the forecast
    ratio = np.asarray(both.demand_rate)[:6, 2].sum(axis=1) / np.asarray(plain.demand_rate)[:6, 2].sum(axis=1)
    np.testing.assert_allclose(ratio, [1, 1, 5, 5, 1, 1])  # requests out of region 2 in steps 0..5


@pytest.mark.parametrize(
    "bad, message",
    [
        ("synthetic~hot2", "is no variant; a variant is named <scenario>~hot<region>x<multiplier>"),
        ("synthetic~hotAx2", "is no variant"),
        ("synthetic~hot2x-1", "is no variant"),
        ("synthetic~ev3x2", "is no variant"),
        ("synthetic~ev3x1.2.3@0-5", "is no variant"),
        ("synthetic~cold2x3", "<scenario>~ev<r>"),
        ("synthetic~hot99x2", "hotspot of synthetic: region 99"),
        ("synthetic~ev3x2@5-5", "event task of synthetic, its surge"),
        ("atlantis~hot1x2", "unknown scenario 'atlantis'"),
        ("synthetic~skew", "is no variant; a variant is named <scenario>~hot<region>x<multiplier>"),
        ("synthetic~skew-1", "<scenario>~skew<gamma>"),
        ("synthetic~skew1.5x2", "is no variant"),
        ("synthetic~skew0", "skew of synthetic: gamma 0.0"),
        ("synthetic~sink2", "is no variant"),
        ("synthetic~sink99x2", "sink of synthetic: region 99"),
        ("synthetic~sink2x0", "sink of synthetic: region 2 (0..15) and multiplier 0.0"),
        ("synthetic~hot2x3@5", "is no variant"),
        ("synthetic~hot2x3@6-4", "hotspot of synthetic: window [6, 4)"),
        ("synthetic~hot2x3@20-25", "start < the horizon 20"),
    ],
)
def test_a_bad_variant_is_one_line_naming_the_forms(bad, message):
    for make in (load_city, marl_amod.parallel_env, marl_amod.vector_env):
        with pytest.raises(ConfigError, match=re.escape(message)) as err:
            make(bad)
        assert "\n" not in str(err.value)


def test_parallel_env_on_a_hotspot_draws_and_forecasts_more_out_of_its_region():
    """Region 2's share of the drawn requests grows about x3 (every step's total kept), and its
    observation's expected request values grow too: the forecast knows a hotspot."""
    base, hot = _parallel_demand("synthetic", range(4)), _parallel_demand(HOT, range(4))
    share = lambda d: d[:, 2].sum() / d.sum()  # noqa: E731
    assert 2.0 < share(hot) / share(base) < 4.0 and 0.8 < hot.sum() / base.sum() < 1.2
    env, plain = marl_amod.parallel_env(HOT), marl_amod.parallel_env("synthetic")
    assert env.city.name == HOT
    obs, base_obs = env.reset(seed=0)[0], plain.reset(seed=0)[0]
    assert (obs["region_2"][VALUE] > 1.5 * base_obs["region_2"][VALUE]).all()


def _out_share(city) -> np.ndarray:
    """Each region's share of the day's expected requests out, x the number of regions (as meta.place_table)."""
    out = city.forecast_rate[: city.horizon].sum(axis=(0, 2))
    return out * city.n_regions / out.sum()


@needs_data
def test_a_skew_variant_is_rebuilt_by_its_name_keeps_each_steps_total_and_skews_the_shares():
    """``<city>~skew<gamma>``: the name rebuilds the city bit for bit (gamma exactly, short), every
    step's total is kept in the draw and the forecast, gamma 1 is the city's demand itself, and
    gamma > 1 makes the busiest / median share ratio grow (< 1 shrink), monotonically."""
    city = load_city("porto")
    for g, text in ((1.6, "1.6"), (2.0, "2"), (2.1234567, "2.1234567"), (0.5, "0.5")):
        skewed = skew(city, g)
        assert skewed.name == f"porto~skew{text}" and skewed.meta["skew"] == {"gamma": g}
        _same_city(load_city(skewed.name), skewed)
        for table in ("demand_rate", "forecast_rate"):
            np.testing.assert_allclose(getattr(skewed, table).sum(axis=(1, 2)), getattr(city, table).sum(axis=(1, 2)), rtol=1e-9)
    same = skew(city, 1.0)
    assert same.name == "porto~skew1" and base_city(same.name) == "porto"
    np.testing.assert_array_equal(same.demand_rate, city.demand_rate)
    np.testing.assert_array_equal(same.forecast_rate, city.forecast_rate)
    ratio = lambda c: _out_share(c).max() / np.median(_out_share(c))  # noqa: E731
    ratios = [ratio(skew(city, g)) for g in (0.5, 1.0, 1.6, 2.5)]
    assert ratios == sorted(ratios) and ratios[2] > 1.2 * ratios[1]
    busiest = int(np.argmax(_out_share(city)))
    assert _out_share(skew(city, 2.0))[busiest] > _out_share(city)[busiest]  # the busiest region grows
    for bad in (0.0, -1.0, float("nan"), float("inf")):
        with pytest.raises(ConfigError, match="gamma") as err:
            skew(city, bad)
        assert "\n" not in str(err.value)
    assert meta.skew_name("porto", 1.6) == "porto~skew1.6" and meta.SKEW == "~skew"


def test_a_sink_variant_sends_more_trips_into_its_region_from_every_origin_and_keeps_each_origins_requests():
    """``~sink<r>x<m>``: every origin's requests to r x m against its other destinations, in the draw
    and the forecast, each origin's requests of every step kept (only where they go changes); the
    trips in and out then differ more (in_out_imbalance); rebuilt bit for bit from its name."""
    city = load_city("synthetic")
    drained = sink(city, 4, 5.0)
    assert drained.name == "synthetic~sink4x5" and drained.meta["sink"] == {"region": 4, "multiplier": 5.0} and base_city(drained.name) == "synthetic"
    _same_city(load_city(drained.name), drained)
    for table in ("demand_rate", "forecast_rate"):
        before, after = getattr(city, table), getattr(drained, table)
        np.testing.assert_allclose(after.sum(axis=2), before.sum(axis=2), rtol=1e-9)  # every step's requests out of every origin
        to_sink = lambda r: r[..., 4] / np.maximum(r.sum(axis=2), 1e-12)  # noqa: E731  (S, N) share of an origin's requests bound for region 4
        bound = to_sink(before) > 0  # origins with trips to region 4 (none from region 4 itself)
        assert bound.sum() > bound.size / 2 and (to_sink(after)[bound] > to_sink(before)[bound]).all()
        np.testing.assert_array_equal(to_sink(after)[~bound], 0.0)
        others = np.delete(np.arange(city.n_regions), 4)
        scale = np.where(before[..., others] > 0, after[..., others] / np.where(before[..., others] > 0, before[..., others], 1), np.nan)
        np.testing.assert_allclose(np.nanmax(scale, -1), np.nanmin(scale, -1), rtol=1e-9)  # an origin's other destinations in proportion
    for table in ("price", "trip_time", "reb_time"):
        np.testing.assert_array_equal(getattr(drained, table), getattr(city, table))
    imbalances = [in_out_imbalance(sink(city, 4, m)) for m in (1.0, 2.0, 5.0)]
    assert imbalances == sorted(imbalances) and imbalances[2] > imbalances[0] + 0.1
    assert imbalances[0] == pytest.approx(in_out_imbalance(city)) and 0 <= imbalances[0] < 1
    assert meta.sink_name("porto", 4, 3.0) == "porto~sink4x3" and meta.SINK == "~sink"


def test_parallel_env_on_an_event_draws_the_surge_in_its_window_but_does_not_forecast_it():
    base, event = _parallel_demand("synthetic", range(3)), _parallel_demand(EVENT, range(3))
    surge = event[:, [3, 7]].sum(axis=1) / base[:, [3, 7]].sum(axis=1)  # per step
    assert (surge[2:8] > 8).all() and (surge[:2] < 3).all() and (surge[8:] < 3).all()
    np.testing.assert_array_equal(event[:2], base[:2])  # the same draws before the event
    env, plain = marl_amod.parallel_env(EVENT), marl_amod.parallel_env("synthetic")
    obs, base_obs = env.reset(seed=0)[0], plain.reset(seed=0)[0]
    stay = {a: np.zeros(1, np.float32) for a in env.possible_agents}
    for _ in range(3):  # up to step 3, inside the window: the expected values observed are the usual ones
        for agent in ("region_3", "region_7"):
            np.testing.assert_array_equal(obs[agent][VALUE], base_obs[agent][VALUE])
        obs, base_obs = env.step(stay)[0], plain.step(stay)[0]


@pytest.mark.parametrize("name", [HOT, EVENT])
def test_vector_env_runs_a_variant_as_the_parallel_env_does(name):
    """The batched env gets the same city and draws its demand: the batch of seeds 0..B-1 is the
    parallel env's episodes of those seeds."""
    env = marl_amod.vector_env(name, num_envs=3)
    _same_city(env.city, load_city(name))
    np.testing.assert_array_equal(_vector_demand(name, 3), _parallel_demand(name, range(3)))
    assert not np.array_equal(_vector_demand(name, 3), _vector_demand("synthetic", 3))


def test_cli_evaluate_takes_a_variant(tmp_path):
    """``marl-amod evaluate --scenario <variant>`` scores the variant and files it under its name."""

    def evaluate(scenario: str) -> dict:
        out = tmp_path / "r.json"
        result = CliRunner().invoke(app, ["evaluate", "--scenario", scenario, "--episodes", "1", "--output", str(out)])
        assert result.exit_code == 0, result.output
        assert scenario in result.output
        return json.loads(out.read_text())

    event, base = evaluate(EVENT), evaluate("synthetic")
    assert event["scenario"] == EVENT and event["metrics"]["demand"]["mean"] > 1.3 * base["metrics"]["demand"]["mean"]
