"""Episode metrics, their aggregation over episodes, and the JSON schema of results."""

from __future__ import annotations

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
}


def episode_metrics(totals: EpisodeTotals, fleet: int, horizon: int) -> dict[str, float]:
    """Scalar metrics of one finished episode."""
    return {key: float(value) for key, value in metric_arrays(totals, fleet, horizon).items()}


def metric_arrays(totals: EpisodeTotals, fleet: int, horizon: int) -> dict[str, np.ndarray]:
    """The metrics of :func:`episode_metrics` as arrays over the leading axes of (..., N) totals
    (a batch of episodes, :mod:`marl_amod.sim.batch`); summed over regions."""
    served = totals.served.sum(axis=-1)
    wait = totals.wait_minutes.sum(axis=-1)
    return {
        "profit": totals.profit.sum(axis=-1),
        "revenue": totals.revenue.sum(axis=-1),
        "served_demand": served,
        "demand": totals.demand.sum(axis=-1),
        "rebalancing_cost": totals.rebalancing_cost.sum(axis=-1),
        "wait_time": np.where(served > 0, wait / np.maximum(served, 1e-300), 0.0),
        "utilization": totals.busy_vehicle_steps.sum(axis=-1) / max(fleet * horizon, 1),
    }


def region_metrics(totals: EpisodeTotals) -> dict[str, list[float]]:
    """Per-region metrics of one episode (attributed to the region vehicles leave from)."""
    served = np.maximum(totals.served, 1e-12)
    return {
        "profit": totals.profit.tolist(),
        "revenue": totals.revenue.tolist(),
        "served_demand": totals.served.tolist(),
        "demand": totals.demand.tolist(),
        "rebalancing_cost": totals.rebalancing_cost.tolist(),
        "wait_time": np.where(totals.served > 0, totals.wait_minutes / served, 0.0).tolist(),
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
