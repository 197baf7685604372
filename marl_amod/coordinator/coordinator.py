"""The coordinator: given a city, solves Steps 1 and 3 exactly every control step.

It turns per-region outputs (weights) into the global target, and targets into flows that are
always feasible. The fast path (greedy dispatch, OR-Tools min-cost flow) is the default; the
cvxpy path solves the same LPs literally, for cross-checks and benchmarks.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from marl_amod.coordinator.dispatch import check_dispatch_counts, check_dispatch_inputs, dispatch_plan, planned_dispatch
from marl_amod.coordinator.rebalance import (
    Rebalancer,
    check_rebalance_inputs,
    desired_targets,
    floor_targets,
    satisfies_triangle_inequality,
)
from marl_amod.errors import ActionError, ConfigError, DataError
from marl_amod.scenario.types import City

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
        self._plans: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # step -> dispatch_plan of its margin
        self._metric: bool | None = None
        self._rebalancer: Rebalancer | None = None

    def margin(self, t: int) -> np.ndarray:
        """(N, N) value of serving one request i->j in step t under the dispatch objective."""
        return self.city.margin[t] if self.objective == "profit" else self.city.price[t]

    @property
    def metric(self) -> bool:
        """Whether rebalancing times obey the triangle inequality (enables the smaller network)."""
        if self._metric is None:
            self._metric = satisfies_triangle_inequality(self.city.reb_time)
        return self._metric

    def dispatch(self, idle: np.ndarray, requests: np.ndarray, t: int, *, check: bool = True) -> np.ndarray:
        """Passenger flows x (N, N) for step t; idle (B, N) and requests (B, N, N) give (B, N, N).

        ``check=False`` skips checking idle and requests: for a caller passing a simulator's own
        integer state (:class:`~marl_amod.system.FleetSystem` unless ``validate``), which the
        checks would only confirm every step."""
        plain = type(t) is int  # the usual case, without the isinstance checks
        if not plain and (isinstance(t, bool) or not isinstance(t, (int, np.integer))) or not 0 <= t < self.city.n_steps:
            raise DataError(f"dispatch step t must be an integer in [0, {self.city.n_steps}), got {t!r}")
        if self.solver == "cvxpy":
            from marl_amod.coordinator.reference import lp_dispatch

            return lp_dispatch(*check_dispatch_inputs(idle, requests, self.margin(t)))
        plan = self._plans.get(t)
        if plan is None:  # margins are tables of the city (checked when it was built): sort once per step
            plan = self._plans[t] = dispatch_plan(self.margin(t))
        if check:
            idle, requests = check_dispatch_counts(idle, requests)  # the whole batch checked once
        return planned_dispatch(idle, requests, plan)

    def rebalance(self, idle: np.ndarray, target: np.ndarray, *, check: bool = True) -> np.ndarray:
        """Rebalancing flows y (N, N) of least cost meeting ``target`` (a -1 entry: no target);
        idle and target (B, N) give (B, N, N), each episode solved alone.

        ``check=False`` skips the input checks: for int64 arrays of the right shape that were
        checked already (a simulator's idle counts and a target through :func:`check_target`)."""
        if self.solver == "cvxpy":
            from marl_amod.coordinator.reference import lp_rebalance

            return lp_rebalance(*check_rebalance_inputs(idle, target, self.city.n_regions), self.city.reb_cost)
        if check:
            idle, target = check_rebalance_inputs(idle, target, self.city.n_regions)  # the whole batch, once
        if self._rebalancer is None:
            self._rebalancer = Rebalancer(self.city.reb_time, metric=self.metric)
        if idle.ndim == 2:  # a batch of episodes (B, N): each solved alone
            return self._rebalancer.many(idle, target)
        return self._rebalancer(idle, target)

    def targets(self, weights: np.ndarray, idle: np.ndarray, *, check: bool = True) -> np.ndarray:
        """Global target u = floor(w / sum(w) * M) from per-region non-negative weights; a NaN,
        infinite or negative weight, or one per region missing, is an ActionError naming the region.
        Weights (B, N) and idle (B, N) give (B, N) targets. ``check=False``: float weights of the
        right shape already known finite and >= 0 (the env's clipped actions), idle an array."""
        if not check:
            return floor_targets(weights, idle.sum(axis=-1))
        if np.ndim(weights) < 1 or np.shape(weights)[-1] != self.city.n_regions:
            raise ActionError(
                f"rebalancing weights must have shape ({self.city.n_regions},) (leading batch axes allowed), got {np.shape(weights)}"
            )
        return desired_targets(weights, np.asarray(idle).sum(axis=-1))
