"""The macroscopic simulator: vectorised fleet bookkeeping over regions and steps.

Pure numpy; it knows no RL API and never solves anything. Callers (the env, the rollout
loop) decide flows through the coordinator and apply them here in the paper's order:

    reset -> apply_dispatch -> [apply_rebalance -> advance -> apply_dispatch] * (horizon - 1)

Semantics follow the reference implementation: a vehicle that departs in step t on a trip of
tau steps arrives in step t + tau and is idle from step t + tau + 1. Vehicles in transit are
counted per arrival step, so no vehicle is ever created or lost. Requests not served within
``max_wait`` steps leave.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.flows import as_flows, check_dispatch, check_rebalance
from marl_amod.validation import as_count

_TOL = 1e-9


@dataclass
class EpisodeTotals:
    """Per-region accumulators over an episode; (N,) arrays, money in the data's units."""

    revenue: np.ndarray
    trip_cost: np.ndarray
    rebalancing_cost: np.ndarray
    served: np.ndarray
    demand: np.ndarray
    lost: np.ndarray
    wait_minutes: np.ndarray  # summed over served passengers
    busy_vehicle_steps: np.ndarray  # vehicle-steps spent driving, by departure region
    rebalanced: np.ndarray  # vehicles sent away for rebalancing

    @classmethod
    def zeros(cls, n: int) -> EpisodeTotals:
        return cls(**{name: np.zeros(n) for name in cls.__dataclass_fields__})

    @property
    def dispatch_profit(self) -> np.ndarray:
        """(N,) fares minus operating costs of the trips that left each region."""
        return self.revenue - self.trip_cost

    @property
    def profit(self) -> np.ndarray:
        return self.dispatch_profit - self.rebalancing_cost

    def book_trips(self, x: np.ndarray, city: City, t: int) -> float:
        """Add the fares and operating costs of dispatch flows x (N, N) of step t; returns their profit."""
        revenue = (x * city.price[t]).sum(axis=1)
        cost = (x * city.trip_cost[t]).sum(axis=1)
        self.revenue += revenue
        self.trip_cost += cost
        return float(revenue.sum() - cost.sum())


def check_max_wait(max_wait: int, city: City) -> int:
    """Steps a request waits: at most the horizon (a request cannot outwait the episode, and the
    backlog holds max_wait + 1 copies of the (N, N) demand)."""
    return as_count(max_wait, "max_wait (steps)", upper=city.horizon, why=f", the horizon of {city.name}")


class MacroSim:
    """State of one episode on one city; reset with a seed, then apply flows step by step."""

    dispatch_rounds = 1  # one dispatch per control step (the SUMO simulator may match more often)

    def __init__(self, city: City, *, max_wait: int = 0) -> None:
        max_wait = check_max_wait(max_wait, city)
        self.city = city
        self.max_wait = max_wait
        n = city.n_regions
        longest = int(max(city.trip_time.max(), city.reb_time.max()))
        self._arrival_len = city.n_steps + longest + 2
        self.t = 0
        self.idle = city.initial_vehicles.astype(np.int64).copy()
        self.arrivals = np.zeros((self._arrival_len, n), dtype=np.int64)
        self.demand = np.zeros((city.n_steps, n, n), dtype=np.int64)
        self.backlog = np.zeros((max_wait + 1, n, n), dtype=np.int64)
        self.totals = EpisodeTotals.zeros(n)
        self.last_dispatch = np.zeros((n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((n, n), dtype=np.int64)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: draw every step's OD demand (one Poisson draw per pair and step)."""
        n = self.city.n_regions
        self.t = 0
        self.idle = self.city.initial_vehicles.astype(np.int64).copy()
        self.arrivals[:] = 0
        self.demand = rng.poisson(self.city.demand_rate).astype(np.int64)
        self.backlog[:] = 0
        self.backlog[0] = self.demand[0]
        self.totals = EpisodeTotals.zeros(n)
        self.totals.demand += self.demand[0].sum(axis=1)
        self.last_dispatch = np.zeros((n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((n, n), dtype=np.int64)

    @property
    def done(self) -> bool:
        """True once the last control step's dispatch has been applied."""
        return self.t >= self.city.horizon - 1

    def requests(self) -> np.ndarray:
        """(N, N) open requests right now: new ones plus those still willing to wait."""
        return self.backlog.sum(axis=0)

    def carried_over(self) -> np.ndarray:
        """(N, N) requests open now that will still wait at the next step if not served (the
        oldest age leaves at :meth:`advance`); zero with ``max_wait`` 0."""
        return self.backlog[: self.max_wait].sum(axis=0)

    def vehicles(self) -> int:
        """Idle plus in-transit vehicles; constant over an episode (conservation)."""
        return int(self.idle.sum() + self.arrivals[self.t :].sum())

    # ------------------------------------------------------------------ transitions
    def apply_dispatch(self, x: np.ndarray) -> float:
        """Serve requests with passenger flows x (N, N); returns the step's dispatch profit."""
        x = as_flows(x, self.city.n_regions, "dispatch")
        check_dispatch(x, self.requests(), self.idle)
        out = x.sum(axis=1)
        c, t = self.city, self.t
        duration = c.trip_time[t]
        self._depart(x, duration)
        # serve the oldest requests first: they are the closest to leaving
        remaining = x.copy()
        wait = np.zeros(c.n_regions)
        for age in range(self.max_wait, -1, -1):
            take = np.minimum(remaining, self.backlog[age])
            self.backlog[age] -= take
            remaining -= take
            wait += age * c.tstep * take.sum(axis=1)
        tot = self.totals
        tot.served += out
        tot.wait_minutes += wait
        self.last_dispatch = x
        return tot.book_trips(x, c, t)

    def apply_rebalance(self, y: np.ndarray) -> float:
        """Move idle vehicles with flows y (N, N); returns the step's rebalancing cost."""
        y = as_flows(y, self.city.n_regions, "rebalancing")
        check_rebalance(y, self.idle)
        out = y.sum(axis=1)
        self._depart(y, self.city.reb_time)
        cost = (y * self.city.reb_cost).sum(axis=1)
        self.totals.rebalancing_cost += cost
        self.totals.rebalanced += out
        self.last_rebalance = y
        return float(cost.sum())

    def advance(self) -> None:
        """Close the step: arrivals become idle, unserved requests age or leave, new ones appear."""
        if self.done:
            raise RuntimeError("the episode is over; call reset()")
        self.idle += self.arrivals[self.t]
        self.totals.lost += self.backlog[self.max_wait].sum(axis=1)
        self.backlog[1:] = self.backlog[:-1].copy()
        self.t += 1
        self.backlog[0] = self.demand[self.t]
        self.totals.demand += self.demand[self.t].sum(axis=1)
        self.last_dispatch = np.zeros_like(self.last_dispatch)
        self.last_rebalance = np.zeros_like(self.last_rebalance)

    def finish(self) -> None:
        """Count requests still open when the episode ends as lost (call after the last dispatch)."""
        self.totals.lost += self.backlog.sum(axis=(0, 2))
        self.backlog[:] = 0

    def close(self) -> None:
        """Nothing to release: the macro model holds arrays only."""

    # ------------------------------------------------------------------ helpers
    def _depart(self, flows: np.ndarray, duration: np.ndarray) -> None:
        """Vehicles leave now and arrive after ``duration`` steps (per pair)."""
        self.idle -= flows.sum(axis=1)
        moving = flows > 0
        if not moving.any():
            return
        i, j = np.nonzero(moving)
        arrive = self.t + duration[i, j]
        np.add.at(self.arrivals, (arrive, j), flows[i, j])
        steps_left = self.city.horizon - self.t
        np.add.at(self.totals.busy_vehicle_steps, i, flows[i, j] * np.minimum(duration[i, j], steps_left))
