"""Region-level OD demand for a road network: a doubly-weighted gravity model.

The data folder holds Luxembourg's roads, not its taxi trips, so demand is modelled, and
calibrated by three documented numbers rather than fitted:

- activity: a region's share of road length is its trip production and attraction weight
  (road density tracks population and jobs);
- imbalance: in the evening peak trips flow from the centre outwards. Production is scaled by
  ``1 + imbalance * c_i`` and attraction by ``1 + imbalance * (1 - c_j)``, c = centrality in
  [0, 1] (1 at the centre of the network), so vehicles drain from where the demand is;
- deterrence: exp(-t_ij / mean_trip_s) over free-flow travel time, so most trips are short;
- volume: ``requests_per_hour`` in total (the paper serves a few hundred requests per hour per
  region with a fleet of a few hundred vehicles), shaped over the window by a peak that rises
  to ``1 + peak`` times the base rate mid-window.
"""

from __future__ import annotations

import numpy as np

from marl_amod.scenario.sumo.network import RoadNetwork
from marl_amod.scenario.sumo.regions import Regions


def od_rates(
    net: RoadNetwork,
    regions: Regions,
    *,
    n_steps: int,
    tstep_min: float,
    requests_per_hour: float,
    imbalance: float = 0.5,
    mean_trip_s: float = 600.0,
    peak: float = 0.3,
) -> np.ndarray:
    """(S, N, N) expected requests i->j per control step."""
    n = regions.n
    activity = np.bincount(regions.of_edge, weights=net.length, minlength=n)
    activity = activity / activity.sum()
    dist = np.linalg.norm(regions.centers - regions.centers.mean(axis=0), axis=1)
    centrality = 1.0 - dist / max(dist.max(), 1e-9)
    produce = activity * (1.0 + imbalance * centrality)
    attract = activity * (1.0 + imbalance * (1.0 - centrality))
    od = produce[:, None] * attract[None, :] * np.exp(-regions.travel_s / mean_trip_s)
    od /= od.sum()
    phase = (np.arange(n_steps) + 0.5) / n_steps
    shape = 1.0 + peak * np.sin(np.pi * np.clip(phase, 0.0, 1.0))
    per_step = requests_per_hour * tstep_min / 60.0 * shape / shape.mean()
    return per_step[:, None, None] * od[None]
