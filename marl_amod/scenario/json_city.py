"""Read a city in RL4AMOD's JSON format, with RL4AMOD's interpretation of every field.

The conventions below are the reference semantics, so that numbers are comparable:

* a ``demand`` item (a per-minute rate) with time stamp ``ts`` minutes belongs to step
  ``k = (ts - 60 * start_hour) // tstep``; a step's OD rate is the sum of its items times
  ``demand_ratio``; the OD price is the demand-weighted mean price; the trip duration in steps is
  the demand-weighted mean of ``travel_time / tstep``, rounded, at least 1;
* rebalancing times come from the ``rebTime`` rows stamped with the start hour:
  ``max(round(reb_time / tstep), 1)`` steps, constant over the episode;
* the fleet is the ``totalAcc`` entry for the hour in the middle of the episode, split evenly
  (integer per region).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from marl_amod.data import read_json
from marl_amod.errors import DataError
from marl_amod.scenario.layout import positions_from_travel_times
from marl_amod.scenario.types import City

_DEMAND_KEYS = ("time_stamp", "origin", "destination", "demand", "travel_time", "price")
_REB_KEYS = ("time_stamp", "origin", "destination", "reb_time")


def _table(path: Path, data: dict, key: str, fields: tuple[str, ...]) -> np.ndarray:
    """Rows of ``data[key]`` as a finite float array (rows, fields); errors name the file, item and field."""
    rows = data.get(key)
    if not isinstance(rows, list) or not rows:
        raise DataError(f"{path}: '{key}' must be a non-empty list")
    try:
        table = np.array([[_number(row[f]) for f in fields] for row in rows], dtype=float)
    except (KeyError, TypeError, ValueError) as exc:
        bad = next((i for i, r in enumerate(rows) if not isinstance(r, dict) or any(f not in r for f in fields)), None)
        if bad is None:
            bad = next(i for i, r in enumerate(rows) if not all(_is_number(r[f]) for f in fields))
        raise DataError(f"{path}: item {bad} of '{key}' lacks one of {fields} or is not numeric ({exc})") from exc
    _check_items(path, key, fields, table, ~np.isfinite(table), "is not finite")
    return table


def _number(value: object) -> float:
    if not _is_number(value):
        raise TypeError(f"{value!r} is not a number")
    return float(value)  # type: ignore[arg-type]


def _is_number(value: object) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


def _check_items(path: Path, key: str, fields: tuple[str, ...], table: np.ndarray, bad: np.ndarray, problem: str) -> None:
    """Raise naming the first item and field of ``key`` flagged in ``bad`` (rows, fields)."""
    if bad.any():
        i, f = np.argwhere(bad)[0]
        raise DataError(f"{path}: item {i} of '{key}': {fields[f]} {problem} (got {table[i, f]:g})")


def _check_regions(path: Path, key: str, fields: tuple[str, ...], table: np.ndarray, n: int) -> None:
    """Origin and destination columns must be whole region indices in [0, n)."""
    cols = np.array([f in ("origin", "destination") for f in fields])
    bad = cols & ((table < 0) | (table >= n) | (table != np.round(table)))
    _check_items(path, key, fields, table, bad, f"must be a region index in [0, {n}) (nlat*nlon)")


def _check_non_negative(path: Path, key: str, fields: tuple[str, ...], table: np.ndarray, names: tuple[str, ...]) -> None:
    cols = np.array([f in names for f in fields])
    _check_items(path, key, fields, table, cols & (table < 0), "must be >= 0")


# a longer trip is a unit error (seconds for minutes); the simulator keeps one row per step of it
MAX_MINUTES = 100_000


def _check_durations(path: Path, key: str, fields: tuple[str, ...], table: np.ndarray, name: str) -> None:
    cols = np.array([f == name for f in fields])
    _check_items(path, key, fields, table, cols & (table > MAX_MINUTES), f"must be at most {MAX_MINUTES} minutes")


def load_json_city(
    path: Path,
    *,
    name: str,
    tstep: float,
    start_hour: int,
    demand_ratio: float,
    beta: float,
    horizon: int = 20,
    fleet: int | None = None,
) -> City:
    """Build a :class:`City` from one RL4AMOD scenario JSON file."""
    data = read_json(path)
    if not isinstance(data, dict):
        raise DataError(f"{path}: expected a JSON object at the top level")
    for key in ("nlat", "nlon", "demand", "rebTime", "totalAcc"):
        if key not in data:
            raise DataError(f"{path}: missing key '{key}'")
    for key in ("nlat", "nlon"):
        if not isinstance(data[key], int) or isinstance(data[key], bool) or data[key] < 1:
            raise DataError(f"{path}: '{key}' must be a positive integer, got {data[key]!r}")
    n = int(data["nlat"]) * int(data["nlon"])
    n_steps = 2 * horizon  # tabulate past the episode for look-ahead features, as the reference does

    dem = _table(path, data, "demand", _DEMAND_KEYS)
    _check_regions(path, "demand", _DEMAND_KEYS, dem, n)
    _check_non_negative(path, "demand", _DEMAND_KEYS, dem, ("demand", "travel_time", "price"))
    _check_durations(path, "demand", _DEMAND_KEYS, dem, "travel_time")
    ts, o, d, rate, tt, price = dem.T
    o, d = o.astype(int), d.astype(int)
    step = np.floor_divide(ts - 60 * start_hour, tstep).astype(int)
    keep = (step >= 0) & (step < n_steps)
    if not keep.any():
        first, last = (int(m) for m in (ts.min(), ts.max()))  # minutes of the day
        raise DataError(
            f"{path}: no demand falls in the episode starting at hour {start_hour}: its requests run from "
            f"{first // 60:02d}:{first % 60:02d} to {last // 60:02d}:{last % 60:02d} (start_hour picks a clock hour in that window)"
        )
    step, o, d, rate, tt, price = step[keep], o[keep], d[keep], rate[keep], tt[keep], price[keep]
    w = rate * demand_ratio
    shape = (n_steps, n, n)
    demand_rate = np.zeros(shape)
    price_sum = np.zeros(shape)
    time_sum = np.zeros(shape)
    np.add.at(demand_rate, (step, o, d), w)
    np.add.at(price_sum, (step, o, d), price * w)
    np.add.at(time_sum, (step, o, d), tt * w / tstep)

    reb = _table(path, data, "rebTime", _REB_KEYS)
    _check_regions(path, "rebTime", _REB_KEYS, reb, n)
    _check_non_negative(path, "rebTime", _REB_KEYS, reb, ("reb_time",))
    _check_durations(path, "rebTime", _REB_KEYS, reb, "reb_time")
    rows = reb[reb[:, 0] == start_hour]
    if rows.size == 0:
        raise DataError(f"{path}: no rebTime rows stamped with the start hour {start_hour}")
    reb_time = np.full((n, n), -1, dtype=np.int64)
    ro, rd = rows[:, 1].astype(int), rows[:, 2].astype(int)
    reb_time[ro, rd] = np.maximum(np.rint(rows[:, 3] / tstep), 1).astype(np.int64)
    np.fill_diagonal(reb_time, 0)
    if np.any(reb_time < 0):
        i, j = np.argwhere(reb_time < 0)[0]
        raise DataError(f"{path}: rebTime lacks the pair ({i}, {j}) at hour {start_hour}")

    has = demand_rate > 0
    price_mean = np.where(has, price_sum / np.where(has, demand_rate, 1.0), 0.0)
    fallback = np.broadcast_to(np.maximum(reb_time, 1), shape)
    trip_time = np.where(has, np.maximum(np.rint(time_sum / np.where(has, demand_rate, 1.0)), 1), fallback)

    if fleet is None:
        hour = start_hour + int(round(tstep / 2 * horizon / 60))
        acc = _table(path, data, "totalAcc", ("hour", "acc"))
        _check_non_negative(path, "totalAcc", ("hour", "acc"), acc, ("hour", "acc"))
        _check_items(path, "totalAcc", ("hour", "acc"), acc, acc != np.round(acc), "must be a whole number")
        accs = dict(zip(acc[:, 0].astype(int).tolist(), acc[:, 1].astype(int).tolist(), strict=True))
        if hour not in accs:
            raise DataError(f"{path}: totalAcc has no entry for hour {hour} (has {sorted(accs)}); set 'fleet'")
        fleet = accs[hour]
        source = f"totalAcc for hour {hour}"
    else:
        source = "the scenario's 'fleet'"
    if int(fleet) < n:  # split evenly, a smaller fleet would silently become 0 vehicles per region
        raise DataError(f"{path}: the fleet ({source}: {fleet}) is smaller than the {n} regions; give at least one vehicle per region")
    initial = np.full(n, int(fleet) // n, dtype=np.int64)

    topo = data.get("topology_graph") or []
    pairs = _table(path, data, "topology_graph", ("i", "j")) if topo else np.zeros((0, 2))
    _check_items(path, "topology_graph", ("i", "j"), pairs, (pairs < 0) | (pairs >= n) | (pairs != np.round(pairs)),
                 f"must be a region index in [0, {n})")  # fmt: skip
    edges = {(int(i), int(j)) for i, j in pairs if i != j}
    if edges:
        edge_index = np.array(sorted(edges), dtype=np.int64).T
    else:  # no topology: connect every pair, the reference's complete graph
        ii, jj = np.nonzero(~np.eye(n, dtype=bool))
        edge_index = np.stack([ii, jj])

    try:
        return City(
            name=name,
            tstep=float(tstep),
            horizon=horizon,
            beta=float(beta),
            demand_rate=demand_rate,
            price=price_mean,
            trip_time=trip_time.astype(np.int64),
            reb_time=reb_time,
            initial_vehicles=initial,
            edge_index=edge_index,
            positions=positions_from_travel_times(reb_time),
            start_hour=float(start_hour),
            meta={"data_file": str(path), "demand_ratio": demand_ratio, "fleet_total": int(fleet)},
        )
    except DataError as exc:  # a derived table is impossible: say which file it came from
        raise DataError(f"{path}: {exc}") from exc
