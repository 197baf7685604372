"""The classic non-learning rebalancing baselines of the paper."""

from __future__ import annotations

import numpy as np

from marl_amod.baselines.base import FlowPolicy, WeightPolicy
from marl_amod.coordinator.rebalance import min_cost_rebalance
from marl_amod.system import FleetSystem


class NoRebalancing(WeightPolicy):
    """Vehicles stay where their last trip ended."""

    name = "no-rebalancing"

    def weights(self, system: FleetSystem) -> np.ndarray:
        return np.zeros(system.city.n_regions)


class EqualDistribution(WeightPolicy):
    """Spread idle vehicles evenly over regions (ED)."""

    name = "equal-distribution"

    def weights(self, system: FleetSystem) -> np.ndarray:
        return np.ones(system.city.n_regions)


class RandomPolicy(WeightPolicy):
    """A uniform Dirichlet(1) desired distribution each step: the untrained-policy reference."""

    name = "random"

    def weights(self, system: FleetSystem) -> np.ndarray:
        return self.rng.dirichlet(np.ones(system.city.n_regions))


class PlusOne(FlowPolicy):
    """For every vehicle that departs from a region with a passenger, rebalance another one back (P1).

    The paper's definition, counted in vehicles: region i, which just dispatched k_i vehicles, is
    sent k_i idle vehicles from other regions. Every region's idle vehicles may be sent, also
    those of regions that dispatched themselves (on a busy city every region does), and the
    replacements come nearest first: the assignment of least total rebalancing time among those
    replacing the most departures, one min-cost transportation problem. A region never
    replaces its own departures; when the idle fleet cannot replace every departure, each region
    asks in proportion to its departures. The coordinator then meets the resulting targets, so
    two regions that would swap vehicles simply keep their own.

    The reference implementation (RL4AMOD's ``plus_one.py``) adds one per origin-destination
    pair served rather than per vehicle, and fills origins one after another in index order.
    """

    name = "plus-one"

    def flows(self, system: FleetSystem) -> np.ndarray:
        idle = system.sim.idle
        departures = system.sim.last_dispatch.sum(axis=1)  # (N,) vehicles that left with a passenger
        n_idle, n_departed = int(idle.sum()), int(departures.sum())
        if n_departed == 0 or n_idle == 0:
            return np.zeros((idle.shape[0],) * 2, dtype=np.int64)
        if n_departed > n_idle:
            departures = np.floor(departures * n_idle / n_departed).astype(np.int64)
        # a region "replacing" its own departure costs more than any real assignment could save,
        # so the transport first maximises real replacements, then minimises their travel time
        time = np.asarray(system.city.reb_time, dtype=np.int64)
        self_cost = n_idle * (int(time.max()) + 1) + 1
        cost = time + self_cost * np.eye(idle.shape[0], dtype=np.int64)
        return min_cost_rebalance(idle, departures, cost)  # the diagonal (self) comes back as zero
