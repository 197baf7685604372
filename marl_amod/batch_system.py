"""The control step of :class:`~marl_amod.system.FleetSystem`, for B episodes of one city at once.

Same order of operations (reset: draw demand -> dispatch step 0; step: rebalance toward the
targets -> advance -> dispatch), applied to a :class:`~marl_amod.sim.batch.BatchMacroSim`:

* dispatch is the coordinator's exact greedy, vectorised over the batch (one sort per step,
  cached, shared by every episode);
* rebalancing is the coordinator's exact min-cost flow solved per episode (OR-Tools, one network
  per city reused; solving the B networks as one returns other optimal vertices on ties), skipped
  where every region already holds its target (then no move is the unique optimum: moves cost > 0).

Episode b reset with seed s_b equals ``FleetSystem.reset(s_b)`` driven by the same targets,
number for number (tests/test_batch.py). Macro simulator only: SUMO cities are one episode each.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from marl_amod.coordinator.coordinator import Coordinator, Objective
from marl_amod.coordinator.rebalance import check_target
from marl_amod.errors import ConfigError
from marl_amod.scenario.types import City
from marl_amod.sim.batch import BatchMacroSim
from marl_amod.validation import as_flag

Seed = int | np.random.SeedSequence | None


@dataclass(frozen=True)
class BatchOutcome:
    """:class:`~marl_amod.system.StepOutcome` with a leading episode axis; money as booked."""

    region_profit: np.ndarray  # (B, N) dispatch profit of trips leaving each region
    region_rebalancing_cost: np.ndarray  # (B, N) cost of the rebalancing moves leaving each region
    dispatch: np.ndarray  # (B, N, N) passenger flows of the new step
    rebalancing: np.ndarray  # (B, N, N) rebalancing flows applied before moving on

    @property
    def region_reward(self) -> np.ndarray:
        """(B, N) each region's share of its episode's step reward."""
        return self.region_profit - self.region_rebalancing_cost

    @property
    def reward(self) -> np.ndarray:
        """(B,) dispatch profit of the new step minus the rebalancing cost just paid, per episode."""
        return self.region_profit.sum(axis=-1) - self.region_rebalancing_cost.sum(axis=-1)


class BatchFleetSystem:
    """B macro episodes of one city plus the exact coordinator; the engine of the vector env."""

    def __init__(
        self, city: City, num_envs: int, *, max_wait: int = 0, objective: Objective = "profit", validate: bool = False
    ) -> None:
        if city.simulator.kind != "macro":
            raise ConfigError(f"{city.name} runs in its own simulator; the batched path is macro only")
        self.city = city
        self.validate = as_flag(validate, "validate")  # as FleetSystem's: re-check the coordinator's inputs and flows
        self.num_envs = int(num_envs)
        self.sim = BatchMacroSim(city, num_envs, max_wait=max_wait)
        self.coordinator = Coordinator(city, objective=objective)  # the fast exact path; cvxpy checks it in tests

    @property
    def t(self) -> int:
        return self.sim.t

    @property
    def done(self) -> bool:
        return self.sim.done

    def reset(self, seeds: Sequence[Seed]) -> BatchOutcome:
        """New episodes, episode b seeded like ``FleetSystem.reset(seeds[b])``; returns the first dispatch."""
        self.sim.reset([np.random.default_rng(s) for s in seeds])
        before = self._booked()
        self._dispatch()
        return self._outcome(before, np.zeros_like(self.sim.last_rebalance))

    def step(self, target: np.ndarray) -> BatchOutcome:
        """Rebalance toward ``target`` (B, N) idle vehicles per region (-1: no wish), then move on."""
        before = self._booked()
        idle = self.sim.idle
        target = check_target(target, idle.shape)  # the caller's: always checked
        self.sim.apply_rebalance(self.coordinator.rebalance(idle, target, check=self.validate), check=self.validate)
        applied = self.sim.last_rebalance
        self.sim.advance()
        self._dispatch()
        if self.sim.done:
            self.sim.finish()
        return self._outcome(before, applied)

    def targets_from_weights(self, weights: np.ndarray, *, check: bool = True) -> np.ndarray:
        """(B, N) targets floor(w_i / sum(w) * M) per episode from non-negative weights (B, N)
        (``check`` as in :meth:`~marl_amod.system.FleetSystem.targets_from_weights`)."""
        return self.coordinator.targets(weights, self.sim.idle, check=check)

    def _dispatch(self) -> None:
        x = self.coordinator.dispatch(self.sim.idle, self.sim.requests(), self.sim.t, check=self.validate)
        self.sim.apply_dispatch(x, check=self.validate)

    def _booked(self) -> tuple[np.ndarray, np.ndarray]:
        totals = self.sim.totals
        return totals.revenue - totals.trip_cost, totals.rebalancing_cost.copy()

    def _outcome(self, before: tuple[np.ndarray, np.ndarray], rebalancing: np.ndarray) -> BatchOutcome:
        totals = self.sim.totals
        profit = totals.revenue - totals.trip_cost
        return BatchOutcome(profit - before[0], totals.rebalancing_cost - before[1], self.sim.last_dispatch, rebalancing)
