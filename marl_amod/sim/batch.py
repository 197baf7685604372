"""B independent episodes of one city per array operation: :class:`MacroSim`'s semantics, batched.

Every state array gains a leading episode axis (B, ...); all episodes run in lockstep (one
shared step counter ``t``, the same horizon), so each transition is a handful of numpy calls
whatever B is. Episode b reset with ``rng_b`` draws its demand exactly as ``MacroSim.reset(rng_b)``
does, and every transition below applies the single simulator's arithmetic row by row, so
episode b agrees with a :class:`MacroSim` fed the same flows number for number (tested).

Pure numpy; like :class:`MacroSim` it never solves anything (see :mod:`marl_amod.batch_system`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.flows import as_flows, check_dispatch, check_rebalance
from marl_amod.sim.macro import EpisodeTotals


class BatchMacroSim:
    """State of B episodes of one city: reset with B generators, then apply (B, N, N) flows."""

    def __init__(self, city: City, num_envs: int, *, max_wait: int = 0) -> None:
        if max_wait < 0:
            raise ValueError(f"max_wait must be >= 0 steps, got {max_wait}")
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.city = city
        self.num_envs = b = int(num_envs)
        self.max_wait = max_wait
        n = city.n_regions
        longest = int(max(city.trip_time.max(), city.reb_time.max()))
        self._arrival_len = city.n_steps + longest + 2
        self.t = 0
        self.idle = np.broadcast_to(city.initial_vehicles.astype(np.int64), (b, n)).copy()  # (B, N)
        self.arrivals = np.zeros((b, self._arrival_len, n), dtype=np.int64)  # (B, L, N)
        self.demand = np.zeros((b, city.horizon, n, n), dtype=np.int64)  # (B, H, N, N): the steps an episode sees
        self.backlog = np.zeros((b, max_wait + 1, n, n), dtype=np.int64)  # (B, W + 1, N, N), by age
        self.totals = _zero_totals(b, n)  # fields (B, N)
        self.last_dispatch = np.zeros((b, n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((b, n, n), dtype=np.int64)

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rngs: Sequence[np.random.Generator]) -> None:
        """Start B episodes; episode b draws its demand from ``rngs[b]`` as MacroSim.reset would."""
        if len(rngs) != self.num_envs:
            raise ValueError(f"reset needs {self.num_envs} generators, got {len(rngs)}")
        city, b, n = self.city, self.num_envs, self.city.n_regions
        self.t = 0
        self.idle[:] = city.initial_vehicles
        self.arrivals[:] = 0
        rate = city.demand_rate[: city.horizon]
        for k, rng in enumerate(rngs):
            # Poisson draws fill an array in C order, so the first H steps of MacroSim's (S, N, N)
            # draw are exactly this (H, N, N) draw; the steps past the horizon are never used
            self.demand[k] = rng.poisson(rate)
        self.backlog[:] = 0
        self.backlog[:, 0] = self.demand[:, 0]
        self.totals = _zero_totals(b, n)
        self.totals.demand += self.demand[:, 0].sum(axis=-1)
        self.last_dispatch = np.zeros((b, n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((b, n, n), dtype=np.int64)

    @property
    def done(self) -> bool:
        """True once the last control step's dispatch has been applied (all episodes at once)."""
        return self.t >= self.city.horizon - 1

    def requests(self) -> np.ndarray:
        """(B, N, N) open requests right now: new ones plus those still willing to wait."""
        return self.backlog.sum(axis=1)

    def vehicles(self) -> np.ndarray:
        """(B,) idle plus in-transit vehicles per episode; constant over an episode (conservation)."""
        return self.idle.sum(axis=-1) + self.arrivals[:, self.t :].sum(axis=(1, 2))

    # ------------------------------------------------------------------ transitions
    def apply_dispatch(self, x: np.ndarray) -> np.ndarray:
        """Serve requests with passenger flows x (B, N, N); returns (B,) dispatch profits."""
        c, t, b = self.city, self.t, self.num_envs
        x = as_flows(x, c.n_regions, "dispatch", (b,))
        check_dispatch(x, self.requests(), self.idle)
        self._depart(x, c.trip_time[t])
        remaining = x.copy()  # serve the oldest requests first: they are the closest to leaving
        wait = np.zeros((b, c.n_regions))
        for age in range(self.max_wait, -1, -1):
            take = np.minimum(remaining, self.backlog[:, age])
            self.backlog[:, age] -= take
            remaining -= take
            wait += age * c.tstep * take.sum(axis=-1)
        revenue = (x * c.price[t]).sum(axis=-1)
        cost = (x * c.trip_cost[t]).sum(axis=-1)
        tot = self.totals
        tot.revenue += revenue
        tot.trip_cost += cost
        tot.served += x.sum(axis=-1)
        tot.wait_minutes += wait
        self.last_dispatch = x
        return revenue.sum(axis=-1) - cost.sum(axis=-1)

    def apply_rebalance(self, y: np.ndarray) -> np.ndarray:
        """Move idle vehicles with flows y (B, N, N); returns (B,) rebalancing costs."""
        y = as_flows(y, self.city.n_regions, "rebalancing", (self.num_envs,))
        check_rebalance(y, self.idle)
        self._depart(y, self.city.reb_time)
        cost = (y * self.city.reb_cost).sum(axis=-1)
        self.totals.rebalancing_cost += cost
        self.totals.rebalanced += y.sum(axis=-1)
        self.last_rebalance = y
        return cost.sum(axis=-1)

    def advance(self) -> None:
        """Close the step: arrivals become idle, unserved requests age or leave, new ones appear."""
        if self.done:
            raise RuntimeError("the episodes are over; call reset()")
        self.idle += self.arrivals[:, self.t]
        self.totals.lost += self.backlog[:, self.max_wait].sum(axis=-1)
        self.backlog[:, 1:] = self.backlog[:, :-1].copy()
        self.t += 1
        self.backlog[:, 0] = self.demand[:, self.t]
        self.totals.demand += self.demand[:, self.t].sum(axis=-1)
        self.last_dispatch = np.zeros_like(self.last_dispatch)
        self.last_rebalance = np.zeros_like(self.last_rebalance)

    def finish(self) -> None:
        """Count requests still open when the episodes end as lost (call after the last dispatch)."""
        self.totals.lost += self.backlog.sum(axis=(1, 3))
        self.backlog[:] = 0

    # ------------------------------------------------------------------ helpers
    def _depart(self, flows: np.ndarray, duration: np.ndarray) -> None:
        """Vehicles leave now and arrive after ``duration`` (N, N) steps (per pair, every episode)."""
        self.idle -= flows.sum(axis=-1)
        e, i, j = np.nonzero(flows)
        if e.size == 0:
            return
        moved = flows[e, i, j]
        np.add.at(self.arrivals, (e, self.t + duration[i, j], j), moved)
        steps_left = self.city.horizon - self.t
        self.totals.busy_vehicle_steps += (flows * np.minimum(duration, steps_left)).sum(axis=-1)


def _zero_totals(b: int, n: int) -> EpisodeTotals:
    """Episode totals with (B, N) fields."""
    return EpisodeTotals(**{name: np.zeros((b, n)) for name in EpisodeTotals.__dataclass_fields__})
