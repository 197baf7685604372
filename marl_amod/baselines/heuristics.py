"""The classic non-learning rebalancing baselines of the paper."""

from __future__ import annotations

import numpy as np

from marl_amod.baselines.base import Policy, WeightPolicy
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


class PlusOne(Policy):
    """For every vehicle that left a region with a passenger, bring one back (P1).

    Regions that just dispatched ask for their idle vehicles plus one per departure; every other
    region asks for nothing, so the min-cost flow pulls replacements from the nearest idle
    vehicles. When the idle fleet elsewhere cannot cover every departure, replacements are
    shared in proportion to departures.
    """

    name = "plus-one"

    def target(self, system: FleetSystem) -> np.ndarray:
        idle = system.sim.idle
        departures = system.sim.last_dispatch.sum(axis=1)
        asking = departures > 0
        spare = int(idle[~asking].sum())
        extra = departures.astype(float)
        if extra.sum() > spare:
            extra = np.floor(extra * spare / extra.sum())
        return np.where(asking, idle + extra.astype(np.int64), 0)
