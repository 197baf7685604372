"""Reward functions of the env: selections from a step's booked money (:class:`~marl_amod.system.StepOutcome`).

* ``team``: every agent receives the system's step reward (dispatch profit of the new step minus
  the rebalancing cost just paid): the paper's objective, fully cooperative.
* ``local``: region i receives its own dispatch profit (fares minus operating cost of the trips
  that leave i) minus the cost of the vehicles it sent away to rebalance. Local rewards sum to the
  team reward, so a team of local learners still optimises the system's profit, with less noise
  per agent and more room for selfish behaviour.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Literal

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.system import StepOutcome

RewardMode = Literal["team", "local"]
REWARD_MODES: tuple[str, ...] = ("team", "local")


def rewards(mode: RewardMode, outcome: StepOutcome) -> np.ndarray:
    """(N,) rewards of one step under ``mode``, selected from the money the simulator booked."""
    if mode == "team":
        return np.full(outcome.region_profit.shape, outcome.reward)
    return outcome.region_reward


def agent_rewards(mode: RewardMode, outcome: StepOutcome, agents: Sequence[str], scale: float = 1.0) -> dict[str, float]:
    """{agent: reward} of one step for ``agents`` in region order, times ``scale``: the ParallelEnv's
    rewards. A team reward is one Python float for every agent: the same number as
    ``rewards(mode, outcome) * scale`` per region, without building the (N,) array."""
    if mode == "team":
        return dict.fromkeys(agents, outcome.reward * scale)
    return dict(zip(agents, (outcome.region_reward * scale).tolist(), strict=True))


def typical_step_revenue(city: City) -> float:
    """Expected fares of one step's requests, averaged over the episode: ``reward_scale="auto"`` divides by it.

    A city's own money unit, from its tables alone (no rollout), so scaled rewards are comparable
    across cities and seeds; 1.0 for a city without demand.
    """
    value = float(city.expected_fares[: city.horizon].sum()) / city.horizon
    return value if value > 0 else 1.0
