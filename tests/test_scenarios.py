"""Scenarios load with the reference semantics, and bad input gives errors that say what to fix."""

from __future__ import annotations

import json

import numpy as np
import pytest

from marl_amod.errors import ConfigError, DataError
from marl_amod.scenario import grid_city, load_city, load_spec
from marl_amod.scenario.json_city import load_json_city


def write_city(tmp_path, **changes):
    """A 2-region city file in RL4AMOD's format, starting at hour 19."""
    data = {
        "nlat": 2,
        "nlon": 1,
        "demand": [
            # step 0 with tstep 3 (minutes 1140..1142): two items 0->1 with different prices/times
            {"time_stamp": 1140, "origin": 0, "destination": 1, "demand": 1.0, "travel_time": 5, "price": 10.0},
            {"time_stamp": 1142, "origin": 0, "destination": 1, "demand": 3.0, "travel_time": 9, "price": 20.0},
            # step 1 (minute 1143)
            {"time_stamp": 1143, "origin": 1, "destination": 0, "demand": 0.5, "travel_time": 2, "price": 7.0},
            # before the start: ignored
            {"time_stamp": 1139, "origin": 1, "destination": 0, "demand": 9.0, "travel_time": 2, "price": 7.0},
        ],
        "rebTime": [
            {"time_stamp": 19, "origin": 0, "destination": 1, "reb_time": 7.4},
            {"time_stamp": 19, "origin": 1, "destination": 0, "reb_time": 1.0},
            {"time_stamp": 20, "origin": 0, "destination": 1, "reb_time": 99.0},
        ],
        "totalAcc": [{"hour": 19, "acc": 11}, {"hour": 20, "acc": 21}],
        "topology_graph": [{"i": 0, "j": 1}, {"i": 1, "j": 0}],
    }
    data.update(changes)
    path = tmp_path / "city.json"
    path.write_text(json.dumps(data))
    return path


def load(path, **kw):
    args = dict(name="t", tstep=3, start_hour=19, demand_ratio=2.0, beta=0.5, horizon=20)
    args.update(kw)
    return load_json_city(path, **args)


def test_json_city_follows_the_reference_semantics(tmp_path):
    city = load(write_city(tmp_path))
    # rate: sum of items in the step times demand_ratio
    assert city.demand_rate[0, 0, 1] == pytest.approx((1.0 + 3.0) * 2)
    assert city.demand_rate[1, 1, 0] == pytest.approx(0.5 * 2)
    assert city.demand_rate.sum() == pytest.approx(9.0)  # the item before the start is ignored
    # price: demand-weighted mean; duration: rounded weighted mean of travel_time / tstep, >= 1
    assert city.price[0, 0, 1] == pytest.approx((10 * 1 + 20 * 3) / 4)
    assert city.trip_time[0, 0, 1] == round((5 * 1 + 9 * 3) / 4 / 3)
    assert city.trip_time[1, 1, 0] == 1
    # rebalancing: rows of the start hour, max(round(t / tstep), 1)
    assert city.reb_time.tolist() == [[0, 2], [1, 0]]
    # fleet: the hour in the middle of the episode, 19 + round(3/2 * 20/60) = 19 (Python rounds
    # half to even, as the reference does), split evenly; with tstep 4 it is hour 20
    assert city.initial_vehicles.tolist() == [5, 5]
    assert load(write_city(tmp_path), tstep=4).initial_vehicles.tolist() == [10, 10]
    assert city.n_steps == 40
    assert city.trip_cost[0, 0, 1] == pytest.approx(0.5 * 3 * city.trip_time[0, 0, 1])


def test_malformed_json_names_the_file_and_position(tmp_path):
    path = tmp_path / "broken.json"
    path.write_text('{"nlat": 2, "nlon": ')
    with pytest.raises(DataError, match=r"broken\.json.*line 1"):
        load(path)


@pytest.mark.parametrize(
    "changes, message",
    [
        ({"rebTime": [{"time_stamp": 19, "origin": 0, "destination": 1, "reb_time": 3}]}, r"lacks the pair \(1, 0\)"),
        ({"demand": [{"time_stamp": 1140, "origin": 0}]}, "item 0 of 'demand'"),
        ({"demand": [{"time_stamp": 1140, "origin": 5, "destination": 0, "demand": 1, "travel_time": 1, "price": 1}]}, r"item 0 of 'demand': origin must be a region index"),
        ({"totalAcc": [{"hour": 3, "acc": 5}]}, "no entry for hour 19"),
    ],
)
def test_malformed_city_content_is_reported(tmp_path, changes, message):
    with pytest.raises(DataError, match=message):
        load(write_city(tmp_path, **changes))


def test_a_start_hour_outside_the_trip_records_names_the_hours_they_cover(tmp_path):
    """RL4AMOD files hold a few hours of one day (Brooklyn 19:00-22:00): a start_hour outside them
    must say which hours would work, not only that nothing falls in the episode."""
    with pytest.raises(DataError, match=r"starting at hour 8: its requests run from 18:59 to 19:03"):
        load(write_city(tmp_path), start_hour=8)


def test_missing_data_file_and_missing_data_dir(monkeypatch, tmp_path):
    monkeypatch.setenv("MARL_AMOD_DATA", str(tmp_path))
    with pytest.raises(DataError, match="data file not found"):
        load_city("nyc_brooklyn", horizon=19)
    monkeypatch.delenv("MARL_AMOD_DATA")
    with pytest.raises(DataError, match="MARL_AMOD_DATA"):
        load_city("nyc_brooklyn", horizon=18)


def test_unknown_scenario_and_bad_keys(tmp_path):
    with pytest.raises(ConfigError, match="unknown scenario 'atlantis'"):
        load_city("atlantis")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nsource: synthetic\nrowz: 3\n")
    with pytest.raises(ConfigError, match="rowz"):
        load_city(str(bad))
    bad.write_text("name: x\nsource: synthetic\nrows: -3\n")
    with pytest.raises(ConfigError, match="rows"):
        load_city(str(bad))
    bad.write_text("name: x\nsource: [unclosed\n")
    with pytest.raises(ConfigError, match="malformed YAML"):
        load_city(str(bad))


def test_user_yaml_scenario(tmp_path):
    mine = tmp_path / "mine.yaml"
    mine.write_text("name: mine\nsource: synthetic\nrows: 2\ncols: 3\nhorizon: 5\n")
    city = load_city(str(mine))
    assert (city.name, city.n_regions, city.horizon) == ("mine", 6, 5)
    (tmp_path / "empty.yaml").write_text("")
    with pytest.raises(ConfigError, match="empty.yaml: the scenario file is empty"):
        load_city(str(tmp_path / "empty.yaml"))
    (tmp_path / "typo.yaml").write_text("sorce: synthetic\n")
    with pytest.raises(ConfigError, match="'source' must be 'json', 'synthetic' or 'sumo', got None"):
        load_city(str(tmp_path / "typo.yaml"))


def test_a_scenario_extends_another_and_changes_only_what_it_names(tmp_path):
    (tmp_path / "base.yaml").write_text("name: base\nsource: synthetic\nrows: 2\ncols: 3\nhorizon: 5\n")
    (tmp_path / "variant.yaml").write_text("extends: base.yaml\nname: variant\nhorizon: 7\n")
    city = load_city(str(tmp_path / "variant.yaml"))
    assert (city.name, city.n_regions, city.horizon) == ("variant", 6, 7)
    (tmp_path / "synth7.yaml").write_text("extends: synthetic\nname: synth7\nhorizon: 7\n")  # a bundled base, by name
    assert load_spec(str(tmp_path / "synth7.yaml")).model_dump(exclude={"name", "horizon"}) == load_spec(
        "synthetic"
    ).model_dump(exclude={"name", "horizon"})
    lux, twin, taxi = load_spec("lux"), load_spec("lux_macro"), load_spec("lux_taxi")  # YAML only: no data needed
    assert (twin.mode, twin.osm_file, twin.fleet) == ("macro", lux.osm_file, lux.fleet) and taxi.taxi_device
    (tmp_path / "base.yaml").write_text("extends: variant.yaml\nname: base\n")
    with pytest.raises(ConfigError, match="cycle"):
        load_spec(str(tmp_path / "variant.yaml"))
    (tmp_path / "orphan.yaml").write_text("extends: atlantis\nname: orphan\n")
    with pytest.raises(ConfigError, match="unknown scenario 'atlantis'"):
        load_spec(str(tmp_path / "orphan.yaml"))


def test_extends_by_bare_name_of_a_file_beside_it_says_to_write_the_file_name(tmp_path):
    """``extends: base`` looks up bundled scenarios; when base.yaml sits beside the file, the error
    says how to name it (``extends: base.yaml``) instead of only listing the bundled names."""
    (tmp_path / "base.yaml").write_text("name: base\nsource: synthetic\nrows: 2\ncols: 3\n")
    (tmp_path / "variant.yaml").write_text("extends: base\nname: variant\n")
    with pytest.raises(ConfigError, match=r"variant\.yaml: 'extends: base'.*write 'extends: base\.yaml'"):
        load_spec(str(tmp_path / "variant.yaml"))


def test_a_variant_without_a_name_is_named_after_its_file_not_its_base(tmp_path):
    """A variant that omits ``name`` must not report its base's: evaluate's JSON, policy cards and
    results_tables.py --add file results under the city's name, so a 3x4 grid named "synthetic"
    would land in the synthetic table."""
    (tmp_path / "small_grid.yaml").write_text("extends: synthetic\nrows: 3\n")
    city = load_city(str(tmp_path / "small_grid.yaml"))
    assert (city.name, city.n_regions) == ("small_grid", 12)
    (tmp_path / "smaller.yaml").write_text("extends: small_grid.yaml\ncols: 2\n")  # two levels: still its own file
    assert load_spec(str(tmp_path / "smaller.yaml")).name == "smaller"
    (tmp_path / "named.yaml").write_text("extends: small_grid.yaml\nname: my_grid\n")  # a name given is kept
    assert load_spec(str(tmp_path / "named.yaml")).name == "my_grid"
    assert load_spec("nyc_brooklyn_event").name == "nyc_brooklyn_event"


@pytest.mark.parametrize("rows, cols", [(2, 2), (5, 10), (20, 20), (21, 21)])
def test_synthetic_cities_from_4_to_over_400_regions(rows, cols):
    city = grid_city(rows, cols, seed=3)
    n = rows * cols
    assert city.n_regions == n and city.demand_rate.shape == (40, n, n)
    assert np.all(city.trip_time >= 1) and city.fleet_size == 12 * n
    assert np.all(city.price[:, ~np.eye(n, dtype=bool)] > city.trip_cost[:, ~np.eye(n, dtype=bool)])
    assert np.array_equal(city.demand_rate, grid_city(rows, cols, seed=3).demand_rate)
    assert not np.array_equal(city.demand_rate, grid_city(rows, cols, seed=4).demand_rate)


def test_step_rows_reads_a_step_table_and_zero_past_its_end():
    from marl_amod.scenario.types import step_rows

    table = np.arange(1, 13).reshape(3, 2, 2)
    got = step_rows(table, np.array([1, 2, 3, 9]))
    assert got.shape == (4, 2, 2)
    assert np.array_equal(got[:2], table[1:]) and not got[2:].any()


def test_city_margin_and_expected_fares_are_per_request_profit_and_fares(small_city):
    c = small_city
    t, i, j = 3, 1, 2
    assert c.margin[t, i, j] == pytest.approx(c.price[t, i, j] - c.beta * c.tstep * c.trip_time[t, i, j])
    assert c.expected_fares[t, i] == pytest.approx(sum(c.demand_rate[t, i, k] * c.price[t, i, k] for k in range(c.n_regions)))
    assert c.margin.shape == c.price.shape and c.expected_fares.shape == (c.n_steps, c.n_regions)
