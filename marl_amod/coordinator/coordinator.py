"""The coordinator: given a city, solves Steps 1 and 3 exactly every control step.

It turns per-region outputs (weights) into the global target, and targets into flows that are
always feasible. The fast path (greedy dispatch, OR-Tools min-cost flow) is the default; the
cvxpy path solves the same LPs literally, for cross-checks and benchmarks.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from marl_amod.coordinator.dispatch import check_dispatch_inputs, greedy_dispatch, margin_order
from marl_amod.coordinator.rebalance import (
    check_rebalance_inputs,
    desired_targets,
    min_cost_rebalance,
    satisfies_triangle_inequality,
)
from marl_amod.errors import ActionError, ConfigError, DataError
from marl_amod.scenario.types import City
from marl_amod.validation import check_array

Objective = Literal["profit", "revenue"]
Backend = Literal["fast", "cvxpy"]


class Coordinator:
    """Exact dispatch and rebalancing for one city; solver state is built lazily and picklable."""

    def __init__(self, city: City, *, objective: Objective = "profit", solver: Backend = "fast") -> None:
        if objective not in ("profit", "revenue"):
            raise ConfigError(f"dispatch objective must be 'profit' or 'revenue', got {objective!r}")
        if solver not in ("fast", "cvxpy"):
            raise ConfigError(f"solver must be 'fast' or 'cvxpy', got {solver!r}")
        self.city = city
        self.objective = objective
        self.solver = solver
        self._orders: dict[int, np.ndarray] = {}
        self._metric: bool | None = None

    def margin(self, t: int) -> np.ndarray:
        """(N, N) value of serving one request i->j in step t under the dispatch objective."""
        return self.city.margin[t] if self.objective == "profit" else self.city.price[t]

    @property
    def metric(self) -> bool:
        """Whether rebalancing times obey the triangle inequality (enables the smaller network)."""
        if self._metric is None:
            self._metric = satisfies_triangle_inequality(self.city.reb_time)
        return self._metric

    def dispatch(self, idle: np.ndarray, requests: np.ndarray, t: int) -> np.ndarray:
        """Passenger flows x (N, N) for step t."""
        if isinstance(t, bool) or not isinstance(t, (int, np.integer)) or not 0 <= t < self.city.n_steps:
            raise DataError(f"dispatch step t must be an integer in [0, {self.city.n_steps}), got {t!r}")
        margin = self.margin(t)
        if self.solver == "cvxpy":
            from marl_amod.coordinator.reference import lp_dispatch

            return lp_dispatch(*check_dispatch_inputs(idle, requests, margin))
        if t not in self._orders:
            self._orders[t] = margin_order(margin)
        return greedy_dispatch(idle, requests, margin, self._orders[t])

    def rebalance(self, idle: np.ndarray, target: np.ndarray) -> np.ndarray:
        """Rebalancing flows y (N, N) of least cost meeting ``target`` (a -1 entry: no target)."""
        if self.solver == "cvxpy":
            from marl_amod.coordinator.reference import lp_rebalance

            return lp_rebalance(*check_rebalance_inputs(idle, target, self.city.n_regions), self.city.reb_cost)
        if np.shape(idle) != (self.city.n_regions,):
            raise DataError(f"idle vehicles must have shape ({self.city.n_regions},), got {np.shape(idle)}")
        return min_cost_rebalance(idle, target, self.city.reb_time, metric=self.metric)

    def targets(self, weights: np.ndarray, idle: np.ndarray) -> np.ndarray:
        """Global target u = floor(w / sum(w) * M) from per-region non-negative weights; a NaN,
        infinite or negative weight, or one per region missing, is an ActionError naming the region."""
        w = check_array(weights, "rebalancing weights", shape=(self.city.n_regions,), minimum=0, error=ActionError)
        return desired_targets(w.astype(float), int(np.sum(idle)))
