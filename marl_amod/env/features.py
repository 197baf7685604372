"""The paper's per-region features, computed from the system state after dispatch.

For region i at step t, with look-ahead T (6 by default) and scale 0.01:

* ``idle``: idle vehicles now (after dispatch), 1 column;
* ``supply[k]``: idle now plus vehicles arriving at i in step t+k, k = 1..T (T columns);
* ``value[k]``: expected requests out of i in step t+k times their price, summed over
  destinations, k = 1..T (T columns); expected = ``city.forecast_rate``, which does not know a
  scenario's events (policies see a demand shock only through the state it leaves).

Steps past the tabulated horizon count as zero.
"""

from __future__ import annotations

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.system import FleetSystem

FEATURE_SCALE = 0.01


def feature_names(lookahead: int = 6) -> list[str]:
    """Column names of :func:`node_features`."""
    return ["idle"] + [f"supply_t+{k}" for k in range(1, lookahead + 1)] + [f"value_t+{k}" for k in range(1, lookahead + 1)]


def node_features(system: FleetSystem, lookahead: int = 6, scale: float = FEATURE_SCALE) -> np.ndarray:
    """(N, 1 + 2T) float32 features of every region (the paper's GNN input)."""
    sim, city = system.sim, system.city
    t = sim.t
    steps = np.arange(t + 1, t + lookahead + 1)
    valid = steps < city.n_steps
    idx = np.minimum(steps, city.n_steps - 1)
    arriving = sim.arrivals[np.minimum(steps, sim.arrivals.shape[0] - 1)]  # (T, N)
    supply = sim.idle[None, :] + arriving
    value = (city.forecast_rate[idx] * city.price[idx]).sum(axis=2) * valid[:, None]  # (T, N), expected: not a scenario's events
    feats = np.concatenate([sim.idle[None, :], supply, value], axis=0).T * scale
    return feats.astype(np.float32)


def feature_high(city: City, lookahead: int = 6, scale: float = FEATURE_SCALE) -> np.ndarray:
    """(1 + 2T,) finite upper bounds of :func:`node_features` on ``city``.

    Idle and supply count disjoint vehicles, so neither exceeds the fleet; the request value is
    a function of the city's tables alone. Finite bounds keep observation spaces usable by
    learners that normalise or sample them.
    """
    fleet = city.fleet_size * scale
    value = float((city.forecast_rate * city.price).sum(axis=2).max()) * scale
    high = np.concatenate([np.full(1 + lookahead, fleet), np.full(lookahead, value)])
    return (high * (1 + 1e-6)).astype(np.float32)
