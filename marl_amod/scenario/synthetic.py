"""Seeded grid cities, so that everything runs with no data at all.

Regions sit on a ``rows x cols`` grid; travel time is the Manhattan distance times
``step_time``. Demand is a time-varying Poisson rate whose spatial pattern drifts over the
episode (a wave crossing the city) and trips lead away from the wave, so that vehicles pile up
where they are not needed and rebalancing pays. Prices grow with trip length. The same arguments always give the same city.
"""

from __future__ import annotations

import numpy as np

from marl_amod.errors import ConfigError
from marl_amod.scenario.types import City


def grid_city(
    rows: int = 4,
    cols: int = 4,
    *,
    seed: int = 0,
    horizon: int = 20,
    tstep: float = 3.0,
    beta: float = 0.5,
    step_time: int = 1,
    requests_per_region: float = 3.0,
    imbalance: float = 0.8,
    trip_length_preference: float = 0.5,
    fare_per_step: float = 4.0,
    vehicles_per_region: int = 12,
    name: str | None = None,
) -> City:
    """Build a synthetic grid city of ``rows * cols`` regions (4 to 400+)."""
    if rows < 1 or cols < 1 or rows * cols < 2:
        raise ConfigError(f"a grid city needs at least 2 regions, got {rows}x{cols}")
    if not 0.0 <= imbalance < 1.0:
        raise ConfigError(f"imbalance must be in [0, 1), got {imbalance}")
    rng = np.random.default_rng(seed)
    n = rows * cols
    r, c = np.divmod(np.arange(n), cols)
    dist = np.abs(r[:, None] - r[None, :]) + np.abs(c[:, None] - c[None, :])
    reb_time = (dist * step_time).astype(np.int64)

    n_steps = 2 * horizon
    t = np.arange(n_steps)[:, None]
    # a demand wave: each region peaks when the wave front (moving along the diagonal) passes it
    phase = 2 * np.pi * (r + c) / max(rows + cols - 2, 1)
    wave = 1.0 + imbalance * np.cos(2 * np.pi * t / horizon - phase[None, :])  # (S, N)
    base = requests_per_region * rng.uniform(0.7, 1.3, size=n)
    origin_rate = base[None, :] * wave  # (S, N)
    # trips run from where the wave is high to where it is low (a commute): vehicles pile up
    # in quiet regions unless they are rebalanced back toward the wave
    attract = np.exp(-trip_length_preference * dist)
    np.fill_diagonal(attract, 0.0)  # intra-region trips are not taxi trips here
    pull = 2.0 - wave  # (S, N) destination pull, highest where demand is lowest
    dest = attract[None, :, :] * pull[:, None, :]
    dest /= dest.sum(axis=2, keepdims=True)
    demand_rate = origin_rate[:, :, None] * dest

    trip_steps = np.maximum(reb_time, 1)
    markup = rng.uniform(1.0, 1.5, size=(n, n))
    price = np.broadcast_to(fare_per_step * (trip_steps + 1) * markup, (n_steps, n, n)).copy()
    trip_time = np.broadcast_to(trip_steps, (n_steps, n, n)).copy()

    ii, jj = np.nonzero(dist == 1)  # 4-neighbour grid adjacency
    return City(
        name=name or f"grid{rows}x{cols}",
        tstep=float(tstep),
        horizon=horizon,
        beta=float(beta),
        demand_rate=demand_rate,
        price=price,
        trip_time=trip_time.astype(np.int64),
        reb_time=reb_time,
        initial_vehicles=np.full(n, vehicles_per_region, dtype=np.int64),
        edge_index=np.stack([ii, jj]).astype(np.int64),
        positions=np.stack([c, -r], axis=1).astype(float),
        start_hour=8.0,
        meta={"generator": "grid_city", "seed": seed, "rows": rows, "cols": cols},
    )
