"""The macroscopic simulator: vectorised fleet bookkeeping over regions and steps.

Pure numpy; it knows no RL API and never solves anything. Callers (the env, the rollout
loop) decide flows through the coordinator and apply them here in the paper's order:

    reset -> apply_dispatch -> [apply_rebalance -> advance -> apply_dispatch] * (horizon - 1)

Semantics follow the reference implementation: a vehicle that departs in step t on a trip of
tau steps arrives in step t + tau and is idle from step t + tau + 1. Vehicles in transit are
counted per arrival step, so no vehicle is ever created or lost. Requests not served within
``max_wait`` steps leave.

Every transition is written over leading axes (``...``), so :class:`~marl_amod.sim.batch.BatchMacroSim`
runs this same code on B episodes at once: state arrays gain a leading (B,) axis there.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.flows import as_flows, check_dispatch, check_rebalance
from marl_amod.validation import as_count

# cities up to this many regions keep each step's leg tables (4 small N x N arrays per step): for
# them the per-step numpy calls, not the arithmetic, are the cost; bigger cities recompute
LEG_TABLE_REGIONS = 64


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
    def zeros(cls, n: int, lead: tuple[int, ...] = ()) -> EpisodeTotals:
        """All-zero totals with fields (*lead, n)."""
        return cls(**{name: np.zeros((*lead, n)) for name in cls.__dataclass_fields__})

    @property
    def dispatch_profit(self) -> np.ndarray:
        """(N,) fares minus operating costs of the trips that left each region."""
        return self.revenue - self.trip_cost

    @property
    def profit(self) -> np.ndarray:
        return self.dispatch_profit - self.rebalancing_cost

    def book_trips(self, x: np.ndarray, city: City, t: int) -> float | np.ndarray:
        """Add the fares and operating costs of dispatch flows x (..., N, N) of step t; returns their
        profit: a float for one episode, an array over the leading axes for a batch."""
        revenue = (x * city.price[t]).sum(axis=-1)
        cost = (x * city.trip_cost[t]).sum(axis=-1)
        self.revenue += revenue
        self.trip_cost += cost
        profit = revenue.sum(axis=-1) - cost.sum(axis=-1)
        return float(profit) if profit.ndim == 0 else profit


def check_max_wait(max_wait: int, city: City) -> int:
    """Steps a request waits: at most the horizon (a request cannot outwait the episode, and the
    backlog holds max_wait + 1 copies of the (N, N) demand)."""
    return as_count(max_wait, "max_wait (steps)", upper=city.horizon, why=f", the horizon of {city.name}")


class MacroSim:
    """State of one episode on one city; reset with a seed, then apply flows step by step."""

    dispatch_rounds = 1  # one dispatch per control step (the SUMO simulator may match more often)

    def __init__(self, city: City, *, max_wait: int = 0) -> None:
        self._setup(city, check_max_wait(max_wait, city), ())

    def _setup(self, city: City, max_wait: int, lead: tuple[int, ...]) -> None:
        """State arrays with leading axes ``lead``: () for one episode, (B,) for a batch."""
        self.city = city
        self.max_wait = max_wait
        self._lead = lead
        n = city.n_regions
        longest = int(max(city.trip_time.max(), city.reb_time.max()))
        self._arrival_len = city.n_steps + longest + 2
        self.t = 0
        self.idle = np.broadcast_to(city.initial_vehicles.astype(np.int64), (*lead, n)).copy()  # (..., N)
        self.arrivals = np.zeros((*lead, self._arrival_len, n), dtype=np.int64)  # (..., L, N), C order (see _depart)
        # where region j's row 0 and episode b's block start in arrivals.reshape(-1): (N,) and (..., 1, 1)
        self._column = np.arange(n)
        self._episode_start = (np.arange(int(np.prod(lead))) * (self._arrival_len * n)).reshape(*lead, 1, 1)
        self._leg_tables: dict[tuple[str, int], tuple[np.ndarray, np.ndarray]] = {}  # see _legs
        self._leg_city = city
        self.demand = np.zeros((*lead, city.n_steps, n, n), dtype=np.int64)  # (..., S, N, N)
        self.backlog = np.zeros((*lead, max_wait + 1, n, n), dtype=np.int64)  # (..., W + 1, N, N) by age
        self.totals = EpisodeTotals.zeros(n, lead)
        self.last_dispatch = np.zeros((*lead, n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((*lead, n, n), dtype=np.int64)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: draw every step's OD demand (one Poisson draw per pair and step)."""
        self.demand = rng.poisson(self.city.demand_rate).astype(np.int64)
        self._start()

    def _start(self) -> None:
        """Step 0 of fresh episodes whose demand is drawn."""
        n = self.city.n_regions
        self.t = 0
        self.idle = np.broadcast_to(self.city.initial_vehicles.astype(np.int64), (*self._lead, n)).copy()
        self.arrivals[:] = 0
        self.backlog[:] = 0
        self.backlog[..., 0, :, :] = self.demand[..., 0, :, :]
        self.totals = EpisodeTotals.zeros(n, self._lead)
        self.totals.demand += self.demand[..., 0, :, :].sum(axis=-1)
        self.last_dispatch = np.zeros((*self._lead, n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((*self._lead, n, n), dtype=np.int64)

    @property
    def done(self) -> bool:
        """True once the last control step's dispatch has been applied."""
        return self.t >= self.city.horizon - 1

    def requests(self) -> np.ndarray:
        """(N, N) open requests right now: new ones plus those still willing to wait."""
        return self.backlog.sum(axis=-3)

    def carried_over(self) -> np.ndarray:
        """(N, N) requests open now that will still wait at the next step if not served (the
        oldest age leaves at :meth:`advance`); zero with ``max_wait`` 0."""
        return self.backlog[..., : self.max_wait, :, :].sum(axis=-3)

    def vehicles(self) -> int:
        """Idle plus in-transit vehicles; constant over an episode (conservation)."""
        return int(self._vehicles())

    def _vehicles(self) -> np.ndarray:
        return self.idle.sum(axis=-1) + self.arrivals[..., self.t :, :].sum(axis=(-2, -1))

    # ------------------------------------------------------------------ transitions
    def apply_dispatch(self, x: np.ndarray, *, check: bool = True) -> float:
        """Serve requests with passenger flows x (N, N); returns the step's dispatch profit.

        ``check=False`` trusts x to be feasible int64 flows that the simulator may keep (the
        coordinator's fresh output): :class:`~marl_amod.system.FleetSystem` unless ``validate``."""
        return float(self._apply_dispatch(x, check))

    def _apply_dispatch(self, x: np.ndarray, check: bool = True) -> np.ndarray:
        c, t = self.city, self.t
        if check:
            x = as_flows(x, c.n_regions, "dispatch", self._lead)
            check_dispatch(x, self.requests(), self.idle)
        sent = x.sum(axis=-1)
        self._depart(x, sent, "trip")
        tot = self.totals
        if self.max_wait == 0:  # one age: every served request is new and waited 0 minutes
            self.backlog[..., 0, :, :] -= x
        else:  # serve the oldest requests first: they are the closest to leaving
            remaining = x.copy()
            wait = np.zeros((*self._lead, c.n_regions))
            for age in range(self.max_wait, -1, -1):
                take = np.minimum(remaining, self.backlog[..., age, :, :])
                self.backlog[..., age, :, :] -= take
                remaining -= take
                wait += age * c.tstep * take.sum(axis=-1)
            tot.wait_minutes += wait
        tot.served += sent
        self.last_dispatch = x
        return np.asarray(tot.book_trips(x, c, t))

    def apply_rebalance(self, y: np.ndarray, *, check: bool = True) -> float:
        """Move idle vehicles with flows y (N, N); returns the step's rebalancing cost
        (``check`` as in :meth:`apply_dispatch`)."""
        return float(self._apply_rebalance(y, check))

    def _apply_rebalance(self, y: np.ndarray, check: bool = True) -> np.ndarray:
        if check:
            y = as_flows(y, self.city.n_regions, "rebalancing", self._lead)
            check_rebalance(y, self.idle)
        sent = y.sum(axis=-1)
        self._depart(y, sent, "move")
        cost = (y * self.city.reb_cost).sum(axis=-1)
        self.totals.rebalancing_cost += cost
        self.totals.rebalanced += sent
        self.last_rebalance = y
        return cost.sum(axis=-1)

    def advance(self) -> None:
        """Close the step: arrivals become idle, unserved requests age or leave, new ones appear."""
        if self.done:
            raise RuntimeError("the episode is over; call reset()")
        self.idle += self.arrivals[..., self.t, :]
        self.totals.lost += self.backlog[..., self.max_wait, :, :].sum(axis=-1)
        if self.max_wait:  # requests age by one step (with max_wait 0 the only age is replaced below)
            self.backlog[..., 1:, :, :] = self.backlog[..., :-1, :, :].copy()
        self.t += 1
        self.backlog[..., 0, :, :] = self.demand[..., self.t, :, :]
        self.totals.demand += self.demand[..., self.t, :, :].sum(axis=-1)
        self.last_dispatch = np.zeros(self.last_dispatch.shape, dtype=np.int64)
        self.last_rebalance = np.zeros(self.last_rebalance.shape, dtype=np.int64)

    def finish(self) -> None:
        """Count requests still open when the episode ends as lost (call after the last dispatch)."""
        self.totals.lost += self.backlog.sum(axis=(-3, -1))
        self.backlog[:] = 0

    def close(self) -> None:
        """Nothing to release: the macro model holds arrays only."""

    # ------------------------------------------------------------------ helpers
    def _depart(self, flows: np.ndarray, sent: np.ndarray, kind: str) -> None:
        """Vehicles ``flows`` (..., N, N), ``sent`` (..., N) of them per origin, leave now on trips
        ("trip": ``city.trip_time[t]``) or rebalancing moves ("move": ``city.reb_time``) and
        arrive after their duration."""
        self.idle -= sent
        at, steps = self._legs(kind)
        if self._lead:
            at = self._episode_start + at
        # arrivals[..., t + duration[i, j], j] += flows[..., i, j] for every pair: one unbuffered add
        # into the flat view of the C-ordered buffer (pairs arriving at one region in one step add
        # up; the zero flows add nothing), far cheaper than picking the non-zero pairs first
        np.add.at(self.arrivals.reshape(-1), at.reshape(-1), flows.reshape(-1))
        # integer vehicle-steps: summing per origin first gives the same float totals as adding one by one
        self.totals.busy_vehicle_steps += (flows * steps).sum(axis=-1)

    def _legs(self, kind: str) -> tuple[np.ndarray, np.ndarray]:
        """For legs of ``kind`` leaving now: (N, N) positions in an episode's flat arrivals block
        where each pair's vehicles arrive, and (N, N) vehicle-steps each leg drives within the
        episode. Tables of the city and the step, kept for small cities (``LEG_TABLE_REGIONS``)."""
        if self._leg_city is not self.city:  # a new region view: new tables
            self._leg_tables, self._leg_city = {}, self.city
        key = (kind, self.t)
        legs = self._leg_tables.get(key)
        if legs is None:
            duration = self.city.trip_time[self.t] if kind == "trip" else self.city.reb_time
            n = self._column.size
            legs = (duration * n + (self.t * n + self._column), np.minimum(duration, self.city.horizon - self.t))
            for table in legs:
                table.setflags(write=False)
            if n <= LEG_TABLE_REGIONS:
                self._leg_tables[key] = legs
        return legs
