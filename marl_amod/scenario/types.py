"""The typed contract of a city: everything the simulator, coordinator and env read.

A ``City`` is immutable data. Time is counted in control steps of ``tstep`` minutes; all
per-step tables cover ``n_steps`` steps, which is longer than the episode so that observations
and MPC can look ahead past the last control step.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from marl_amod.errors import DataError
from marl_amod.scenario.simspec import MACRO, SimSpec
from marl_amod.validation import check_array


@dataclass(frozen=True, eq=False)
class City:
    """A region graph with demand, prices, travel times and a fleet.

    Shapes: N regions, S = ``n_steps`` tabulated steps.
    """

    name: str
    tstep: float  # minutes per control step
    horizon: int  # control steps per episode (dispatch rounds)
    beta: float  # operating cost per minute of driving (money / minute)
    demand_rate: np.ndarray  # (S, N, N) float, expected requests i->j arriving in step t
    price: np.ndarray  # (S, N, N) float, fare of a trip i->j requested in step t
    trip_time: np.ndarray  # (S, N, N) int >= 1, trip duration in steps when requested in step t
    reb_time: np.ndarray  # (N, N) int, rebalancing duration in steps, 0 on the diagonal
    initial_vehicles: np.ndarray  # (N,) int, idle vehicles per region at the start
    edge_index: np.ndarray  # (2, E) int, region adjacency for message passing (no self loops)
    positions: np.ndarray  # (N, 2) float, a drawing position per region
    start_hour: float = 0.0  # clock time of step 0, for the time-of-day feature
    # (S, N, N) the usual expected requests, what planners and observations believe; differs from
    # demand_rate (what is drawn) only under a scenario's events. None: demand_rate.
    forecast_rate: np.ndarray | None = None
    meta: dict = field(default_factory=dict)  # provenance (data file, parameters), shown to users
    # which simulator runs this city (data; marl_amod.sim.base.make_simulator builds it). SUMO
    # scenarios set it, so every consumer of a City gets its simulator without asking.
    simulator: SimSpec = field(default=MACRO, repr=False)

    def __post_init__(self) -> None:
        """Every number checked once here, so no NaN, negative price or impossible time reaches a run."""
        if not isinstance(self.simulator, SimSpec):
            raise TypeError(f"City.simulator must be a SimSpec (data), got {type(self.simulator).__name__}")
        what = f"city {self.name!r}:"
        shape = np.shape(self.demand_rate)
        if len(shape) != 3 or shape[1] != shape[2]:
            raise DataError(f"{what} demand_rate must be (S, N, N), got {shape}")
        s, n, _ = shape
        check_array(self.demand_rate, f"{what} demand_rate", minimum=0)
        if self.forecast_rate is None:
            object.__setattr__(self, "forecast_rate", self.demand_rate)
        check_array(self.forecast_rate, f"{what} forecast_rate", shape=(s, n, n), minimum=0)
        check_array(self.price, f"{what} price", shape=(s, n, n), minimum=0)
        check_array(self.trip_time, f"{what} trip_time (steps)", shape=(s, n, n), minimum=1, integer=True)
        reb = check_array(self.reb_time, f"{what} reb_time (steps)", shape=(n, n), minimum=0, integer=True)
        check_array(self.initial_vehicles, f"{what} initial_vehicles", shape=(n,), minimum=0, integer=True)
        edges = np.asarray(self.edge_index)
        if edges.ndim != 2 or edges.shape[0] != 2:
            raise DataError(f"{what} edge_index must be (2, E), got {edges.shape}")
        check_array(edges, f"{what} edge_index", minimum=0, integer=True)
        if edges.size and edges.max() >= n:
            raise DataError(f"{what} edge_index names region {edges.max()} but the city has {n} regions")
        check_array(self.positions, f"{what} positions", shape=(n, 2))
        for name in ("tstep", "beta", "start_hour"):
            check_array(getattr(self, name), f"{what} {name}", minimum=0)
        if self.tstep <= 0:
            raise DataError(f"{what} tstep must be > 0 minutes, got {self.tstep}")
        if isinstance(self.horizon, bool) or not isinstance(self.horizon, (int, np.integer)) or not 1 <= self.horizon <= s:
            raise DataError(f"{what} horizon {self.horizon!r} must be an integer in [1, n_steps={s}]")
        if np.any(np.diag(reb) != 0):
            raise DataError(f"{what} rebalancing times must be 0 on the diagonal (region {np.flatnonzero(np.diag(reb))[0]})")
        off = (reb < 1) & ~np.eye(n, dtype=bool)
        if off.any():
            i, j = np.argwhere(off)[0]
            raise DataError(f"{what} rebalancing times between distinct regions must be >= 1 step (regions {i}->{j})")
        for arr in (self.demand_rate, self.forecast_rate, self.price, self.trip_time, self.reb_time, self.initial_vehicles,
                    self.edge_index, self.positions):  # fmt: skip
            arr.setflags(write=False)

    @property
    def n_regions(self) -> int:
        return self.demand_rate.shape[1]

    @property
    def n_steps(self) -> int:
        return self.demand_rate.shape[0]

    @cached_property
    def fleet_size(self) -> int:
        return int(self.initial_vehicles.sum())  # initial_vehicles is read-only: computed once

    @cached_property
    def trip_cost(self) -> np.ndarray:
        """(S, N, N) operating cost of a passenger trip: beta * tstep * duration (computed once)."""
        return _frozen(self.beta * self.tstep * self.trip_time)

    @cached_property
    def margin(self) -> np.ndarray:
        """(S, N, N) profit of serving one request i->j of step t: fare minus operating cost."""
        return _frozen(self.price - self.trip_cost)

    @cached_property
    def expected_fares(self) -> np.ndarray:
        """(S, N) expected fares of the requests out of each region in step t (forecast rate x fare over
        destinations): what a policy may know in advance, so a scenario's events are not in it."""
        return _frozen((self.forecast_rate * self.price).sum(axis=2))

    @cached_property
    def reb_cost(self) -> np.ndarray:
        """(N, N) cost of one rebalancing move: beta * tstep * duration (computed once)."""
        return _frozen(self.beta * self.tstep * self.reb_time)

    def summary(self) -> dict:
        """One row for `marl-amod scenarios`."""
        return {
            "name": self.name,
            "regions": self.n_regions,
            "fleet": self.fleet_size,
            "horizon": self.horizon,
            "tstep_min": self.tstep,
            "expected_requests": float(self.demand_rate[: self.horizon].sum()),
        }


def step_rows(table: np.ndarray, steps: np.ndarray) -> np.ndarray:
    """``table[steps]`` of a table indexed by step, with zero rows for steps past its end.

    Look-ahead (observations, MPC) reads a few steps past what a city or a simulator tabulates;
    nothing is requested and nothing arrives there.
    """
    steps = np.asarray(steps)
    rows = table[np.minimum(steps, len(table) - 1)]
    inside = (steps < len(table)).reshape(steps.shape + (1,) * (table.ndim - 1))
    return np.where(inside, rows, 0)


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
