"""One control step of the paper, end to end: the order of operations lives here, once.

``FleetSystem`` joins a simulator and a coordinator. The PettingZoo env, the baseline
evaluation loop and MPC all drive it, so every path through the library applies dispatch,
target, rebalancing and bookkeeping identically:

    reset(seed):  draw demand -> dispatch step 0
    step(target): rebalance toward target -> advance -> dispatch the next step
                  (a simulator with dispatch_rounds > 1 also dispatches inside the step)

The caller's target is checked every step; the coordinator's flows are feasible by construction,
so the simulator takes them unchecked unless ``validate=True`` (a debug mode: the coordinator
re-checks the simulator's state and the simulator every flow, as the tests run it).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marl_amod.coordinator.coordinator import Backend, Coordinator, Objective
from marl_amod.coordinator.rebalance import check_target
from marl_amod.scenario.types import City
from marl_amod.sim.base import Simulator, make_simulator
from marl_amod.validation import as_flag


@dataclass(frozen=True)
class StepOutcome:
    """What one control step produced, money as the simulator booked it (data's units).

    The simulator is the one source of money: ``region_profit`` and ``region_rebalancing_cost``
    are the changes of its per-region episode totals over the step, so they hold whatever prices
    and travel times it used, however many matching rounds ran and whichever region view it held
    at each. Rewards, infos, metrics and datasets only select from these arrays.
    """

    region_profit: np.ndarray  # (N,) dispatch profit (fares - trip costs) of trips leaving each region
    region_rebalancing_cost: np.ndarray  # (N,) cost of the rebalancing moves that left each region
    dispatch: np.ndarray  # (N, N) passenger flows of the new step (last matching round)
    rebalancing: np.ndarray  # (N, N) rebalancing flows applied before moving on (zeros at reset)

    @property
    def dispatch_profit(self) -> float:
        return float(self.region_profit.sum())

    @property
    def rebalancing_cost(self) -> float:
        return float(self.region_rebalancing_cost.sum())

    @property
    def region_reward(self) -> np.ndarray:
        """(N,) each region's share of the step reward; sums to :attr:`reward`."""
        return self.region_profit - self.region_rebalancing_cost

    @property
    def reward(self) -> float:
        """Dispatch profit of the new step minus the rebalancing cost just paid."""
        return self.dispatch_profit - self.rebalancing_cost


class FleetSystem:
    """A simulator plus its exact coordinator; the shared engine of env, baselines and MPC."""

    def __init__(
        self,
        city: City,
        *,
        max_wait: int = 0,
        objective: Objective = "profit",
        solver: Backend = "fast",
        sim: Simulator | None = None,
        validate: bool = False,
    ) -> None:
        self.city = city
        self.validate = as_flag(validate, "validate")  # re-check the coordinator's inputs and flows every step (debugging)
        # the city's own simulator (macro unless the scenario says otherwise), or one passed in
        self.sim = sim if sim is not None else make_simulator(city, max_wait)
        self.coordinator = Coordinator(city, objective=objective, solver=solver)

    @property
    def t(self) -> int:
        return self.sim.t

    @property
    def done(self) -> bool:
        return self.sim.done

    def reset(self, seed: int | np.random.SeedSequence | None = None) -> StepOutcome:
        """New episode; returns the outcome of the first dispatch."""
        self.sim.reset(np.random.default_rng(seed))
        self._follow_city()
        before = self._booked()
        self._dispatch()
        n = self.city.n_regions
        return self._outcome(before, np.zeros((n, n), dtype=np.int64))

    def step(self, target: np.ndarray) -> StepOutcome:
        """Rebalance toward ``target`` (N,) idle vehicles per region (-1: no wish), then move on."""
        before = self._booked()
        idle = self.sim.idle
        target = check_target(target, idle.shape)  # the caller's: always checked
        flows = self.coordinator.rebalance(idle, target, check=self.validate)
        self.sim.apply_rebalance(flows, check=self.validate)
        applied = self.sim.last_rebalance
        for _ in range(self.sim.dispatch_rounds - 1):  # matching more often than rebalancing
            self.sim.advance_round()
            self._dispatch()
        self.sim.advance()
        self._follow_city()
        self._dispatch()
        if self.sim.done:
            self.sim.finish()
        return self._outcome(before, applied)

    def close(self) -> None:
        """Release what the simulator started (a SUMO run and its process); reset starts anew."""
        self.sim.close()

    def targets_from_weights(self, weights: np.ndarray, *, check: bool = True) -> np.ndarray:
        """The paper's target floor(w_i / sum(w) * M) from non-negative per-region weights
        (``check=False``: weights already known finite and >= 0, as the env's clipped actions)."""
        return self.coordinator.targets(weights, self.sim.idle, check=check)

    def _follow_city(self) -> None:
        """Adopt the simulator's region view when it changed (SUMO travel times follow congestion),
        so the coordinator and observations price and time moves as the simulator now sees them."""
        if self.sim.city is not self.city:
            self.city = self.sim.city
            self.coordinator = Coordinator(self.city, objective=self.coordinator.objective, solver=self.coordinator.solver)

    def _dispatch(self) -> None:
        x = self.coordinator.dispatch(self.sim.idle, self.sim.requests(), self.sim.t, check=self.validate)
        self.sim.apply_dispatch(x, check=self.validate)

    def _booked(self) -> tuple[np.ndarray, np.ndarray]:
        """Copies of the simulator's per-region money totals (dispatch profit, rebalancing cost)."""
        totals = self.sim.totals
        return totals.dispatch_profit, totals.rebalancing_cost.copy()

    def _outcome(self, before: tuple[np.ndarray, np.ndarray], rebalancing: np.ndarray) -> StepOutcome:
        totals = self.sim.totals
        profit, cost = totals.dispatch_profit - before[0], totals.rebalancing_cost - before[1]
        return StepOutcome(profit, cost, self.sim.last_dispatch, rebalancing)
