"""The typed contract of a city: everything the simulator, coordinator and env read.

A ``City`` is immutable data. Time is counted in control steps of ``tstep`` minutes; all
per-step tables cover ``n_steps`` steps, which is longer than the episode so that observations
and MPC can look ahead past the last control step.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from marl_amod.scenario.simspec import MACRO, SimSpec


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
    meta: dict = field(default_factory=dict)  # provenance (data file, parameters), shown to users
    # which simulator runs this city (data; marl_amod.sim.base.make_simulator builds it). SUMO
    # scenarios set it, so every consumer of a City gets its simulator without asking.
    simulator: SimSpec = field(default=MACRO, repr=False)

    def __post_init__(self) -> None:
        if not isinstance(self.simulator, SimSpec):
            raise TypeError(f"City.simulator must be a SimSpec (data), got {type(self.simulator).__name__}")
        s, n, n2 = self.demand_rate.shape
        if n != n2:
            raise ValueError(f"demand_rate must be (S, N, N), got {self.demand_rate.shape}")
        for name in ("price", "trip_time"):
            if getattr(self, name).shape != (s, n, n):
                raise ValueError(f"{name} must have shape {(s, n, n)}, got {getattr(self, name).shape}")
        if self.reb_time.shape != (n, n):
            raise ValueError(f"reb_time must be {(n, n)}, got {self.reb_time.shape}")
        if self.initial_vehicles.shape != (n,):
            raise ValueError(f"initial_vehicles must be {(n,)}, got {self.initial_vehicles.shape}")
        if self.horizon < 1 or self.horizon > s:
            raise ValueError(f"horizon {self.horizon} must be in [1, n_steps={s}]")
        if np.any(self.trip_time < 1) or np.any(np.diag(self.reb_time) != 0):
            raise ValueError("trip times must be >= 1 step and rebalancing times 0 on the diagonal")
        if np.any(self.reb_time[~np.eye(n, dtype=bool)] < 1):
            raise ValueError("rebalancing times between distinct regions must be >= 1 step")
        for arr in (self.demand_rate, self.price, self.trip_time, self.reb_time, self.initial_vehicles):
            arr.setflags(write=False)

    @property
    def n_regions(self) -> int:
        return self.demand_rate.shape[1]

    @property
    def n_steps(self) -> int:
        return self.demand_rate.shape[0]

    @property
    def fleet_size(self) -> int:
        return int(self.initial_vehicles.sum())

    @cached_property
    def trip_cost(self) -> np.ndarray:
        """(S, N, N) operating cost of a passenger trip: beta * tstep * duration (computed once)."""
        return _frozen(self.beta * self.tstep * self.trip_time)

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


def _frozen(a: np.ndarray) -> np.ndarray:
    a.setflags(write=False)
    return a
