"""Episode metrics, their aggregation over episodes, and the JSON schema of results.

Besides the operator's numbers (profit, demand served, utilisation) every episode reports how
evenly service is spread over the city -- the paper names equity of service as future work: the
Gini coefficient of the per-region mean waiting time and of the per-region service rate
(served / requested). 0 means every region is treated alike; (n - 1) / n means one region gets
everything.
"""

from __future__ import annotations

import functools
from collections.abc import Mapping
from typing import Any

import numpy as np

from marl_amod.sim.macro import EpisodeTotals

METRICS: dict[str, str] = {
    "profit": "revenue minus trip and rebalancing costs (money)",
    "revenue": "fares of served trips (money)",
    "served_demand": "passengers served",
    "demand": "passengers who requested a trip",
    "rebalancing_cost": "cost of rebalancing moves (money)",
    "wait_time": "mean passenger wait in minutes (0 when requests are served or lost at once)",
    "utilization": "share of vehicle-steps spent carrying passengers or rebalancing",
    "wait_time_gini": "Gini coefficient of per-region mean wait over regions that served someone (0: equal)",
    "service_rate_gini": "Gini coefficient of per-region service rate over regions with requests (0: equal)",
}

# decimals shown in tables; metrics not named here show one
DISPLAY_DIGITS: dict[str, int] = {"wait_time": 2, "utilization": 2, "wait_time_gini": 3, "service_rate_gini": 3}
# short column headers for terminal tables (the JSON keeps the full names)
DISPLAY_NAMES: dict[str, str] = {
    "served_demand": "served", "rebalancing_cost": "reb. cost", "wait_time": "wait min",
    "utilization": "util.", "wait_time_gini": "wait Gini", "service_rate_gini": "service Gini",
}


SCORE_ANCHORS = ("equal-distribution", "mpc-oracle")  # the policies a normalised score puts at 0 and 100


def score_anchors(profits: Mapping[str, float]) -> tuple[float, float] | None:
    """(equal distribution's, MPC-Oracle's) profit from profits by policy name (on one set of episodes),
    or None where either is missing: what :func:`normalised_score` scales by."""
    floor, ceiling = SCORE_ANCHORS
    return (profits[floor], profits[ceiling]) if floor in profits and ceiling in profits else None


def normalised_score(profit: float, ed: float, oracle: float) -> float:
    """100 (P - P_ED) / (P_oracle - P_ED): equal distribution 0, MPC-Oracle 100 (D4RL's
    normalisation, on the same evaluation episodes); nan when the two anchors coincide."""
    return 100.0 * (profit - ed) / (oracle - ed) if oracle != ed else float("nan")


def score_points(spread: float, ed: float, oracle: float) -> float:
    """A profit spread (an episode std) in points of :func:`normalised_score`."""
    return 100.0 * spread / (oracle - ed) if oracle != ed else float("nan")


def gini(values: np.ndarray | list[float], axis: int = -1) -> np.ndarray | float:
    """Gini coefficient of non-negative values along ``axis`` (0: all equal; one-hot: (n - 1) / n).

    Sorted form of mean |x_i - x_j| / (2 mean x), O(n log n); all-zero (or empty) rows give 0.
    """
    x = np.array(values, dtype=float)  # a copy, sorted in place below
    if axis not in (-1, x.ndim - 1):
        x = np.moveaxis(x, axis, -1)
    x.sort(axis=-1)
    n = x.shape[-1]
    if x.ndim == 1:  # one row (the env asks every step): the same float64 operations on scalars
        if n and x[0] < 0:  # sorted: the first value is the smallest
            raise ValueError("the Gini coefficient needs non-negative values")
        total = float(x.sum())
        return 2.0 * float((x * _ranks(n)).sum()) / (n * total) - (n + 1.0) / n if total > 0 else 0.0
    if n and (x[..., 0] < 0).any():  # sorted: the first value is each row's smallest
        raise ValueError("the Gini coefficient needs non-negative values")
    total = x.sum(axis=-1)
    rank = np.arange(1, n + 1)
    positive = total > 0
    g = 2.0 * (x * rank).sum(axis=-1) / np.where(positive, n * total, 1.0) - (n + 1.0) / max(n, 1)
    g = np.where(positive, g, 0.0)
    return float(g) if g.ndim == 0 else g


@functools.lru_cache(maxsize=64)
def _ranks(n: int) -> np.ndarray:
    """1..n, read-only: the weights of the sorted form of the Gini coefficient."""
    rank = np.arange(1, n + 1)
    rank.setflags(write=False)
    return rank


def region_wait_time(totals: EpisodeTotals) -> np.ndarray:
    """(N,) mean wait in minutes of the passengers served from each region (0 where none was)."""
    return _region_ratio(totals.wait_minutes, totals.served)


def region_service_rate(totals: EpisodeTotals) -> np.ndarray:
    """(N,) served / requested per region (0 where nobody requested a trip)."""
    return _region_ratio(totals.served, totals.demand)


def _region_ratio(part: np.ndarray, whole: np.ndarray) -> np.ndarray:
    """part / whole per region, 0 where whole is 0."""
    return np.where(whole > 0, part / np.maximum(whole, 1e-12), 0.0)


def _masked_gini(values: np.ndarray, keep: np.ndarray) -> np.ndarray:
    """Gini of ``values[..., keep]`` per leading index (each episode keeps its own regions).

    Rows keeping the same number of regions are compacted into one (rows, kept) array and go
    through :func:`gini` together: a batch of episodes costs one call per distinct count (usually
    one), and each row's numbers are those of a call on that row alone (same sort, same sums).
    """
    if values.ndim == 1:  # one episode
        return np.asarray(gini(values[keep]))
    n = values.shape[-1]
    flat, mask = values.reshape(-1, n), keep.reshape(-1, n)
    if mask.all():
        return np.asarray(gini(flat), dtype=float).reshape(values.shape[:-1])
    counts = mask.sum(axis=-1)
    out = np.empty(flat.shape[0])
    for count in np.unique(counts):
        rows = counts == count
        out[rows] = gini(flat[rows][mask[rows]].reshape(int(rows.sum()), count))  # a boolean mask keeps row order
    return out.reshape(values.shape[:-1])


def _ratio_gini(part: np.ndarray, whole: np.ndarray) -> np.ndarray:
    """Gini of :func:`_region_ratio` (..., N) over the regions where whole > 0, per leading index:
    of :func:`region_wait_time` (wait / served) and :func:`region_service_rate` (served / demand)."""
    keep = whole > 0
    ratio = part / np.maximum(whole, 1e-12)
    if ratio.ndim == 1:  # one episode: the kept entries of _region_ratio, selected directly
        return np.asarray(gini(ratio[keep]))
    return _masked_gini(np.where(keep, ratio, 0.0), keep)


def episode_metrics(totals: EpisodeTotals, fleet: int, horizon: int) -> dict[str, float]:
    """Scalar metrics of one finished episode."""
    return {key: float(value) for key, value in metric_arrays(totals, fleet, horizon).items()}


def metric_arrays(totals: EpisodeTotals, fleet: int, horizon: int) -> dict[str, np.ndarray]:
    """The metrics of :func:`episode_metrics` as arrays over the leading axes of (..., N) totals
    (a batch of episodes, :mod:`marl_amod.sim.batch`); summed over regions.

    The env asks every step, so the seven sums over regions are one reduction of the stacked totals:
    each row of a C-ordered stack sums in the same pairwise order as that array alone.
    """
    stacked = np.array((
        totals.profit, totals.revenue, totals.served, totals.demand, totals.rebalancing_cost, totals.wait_minutes,
        totals.busy_vehicle_steps,
    ))
    profit, revenue, served, demand, rebalancing_cost, wait, busy = stacked.sum(axis=-1)
    return {
        "profit": profit,
        "revenue": revenue,
        "served_demand": served,
        "demand": demand,
        "rebalancing_cost": rebalancing_cost,
        "wait_time": _mean_wait(wait, served),
        "utilization": busy / max(fleet * horizon, 1),
        # regions where the quantity is undefined (nobody served / nobody asked) are left out; when
        # nobody has waited (always with max_wait 0) every region's mean wait is 0, whose Gini is 0
        "wait_time_gini": (
            _ratio_gini(totals.wait_minutes, totals.served) if totals.wait_minutes.any() else np.zeros(served.shape)
        ),
        "service_rate_gini": _ratio_gini(totals.served, totals.demand),
    }


def _mean_wait(wait: np.ndarray, served: np.ndarray) -> np.ndarray:
    """wait / served, 0 where nobody was served; one episode's scalars in Python arithmetic (the
    same float64 operations, without numpy's per-call cost on 0-d values)."""
    if served.ndim == 0:
        return np.float64(float(wait) / max(float(served), 1e-300) if served > 0 else 0.0)
    return np.where(served > 0, wait / np.maximum(served, 1e-300), 0.0)


def region_metrics(totals: EpisodeTotals) -> dict[str, list[float]]:
    """Per-region metrics of one episode (attributed to the region vehicles leave from)."""
    return {
        "profit": totals.profit.tolist(),
        "revenue": totals.revenue.tolist(),
        "served_demand": totals.served.tolist(),
        "demand": totals.demand.tolist(),
        "rebalancing_cost": totals.rebalancing_cost.tolist(),
        "wait_time": region_wait_time(totals).tolist(),
        "service_rate": region_service_rate(totals).tolist(),
    }


def aggregate(episodes: list[dict[str, float]]) -> dict[str, dict[str, float]]:
    """Mean and (population) std of every metric over episodes."""
    return {
        key: {"mean": float(np.mean([e[key] for e in episodes])), "std": float(np.std([e[key] for e in episodes]))}
        for key in METRICS
    }


def aggregate_regions(regions: list[dict[str, list[float]]]) -> dict[str, list[float]]:
    """Per-region means over episodes."""
    return {key: np.mean([r[key] for r in regions], axis=0).tolist() for key in regions[0]}


def result_record(
    scenario: str, policy: str, seed: int, episodes: list[dict[str, float]], regions: list[dict], **extra: Any
) -> dict[str, Any]:
    """The evaluation JSON: scenario, policy, episodes, seed, metrics{name: {mean, std}}, ..."""
    return {
        "scenario": scenario,
        "policy": policy,
        "episodes": len(episodes),
        "seed": seed,
        "metrics": aggregate(episodes),
        "per_region": aggregate_regions(regions),
        "per_episode": episodes,
        **extra,
    }
