"""Reward functions of the env: pure functions of flows and city tables, so they can be tested alone.

* ``team``: every agent receives the system's step reward (dispatch profit of the new step minus
  the rebalancing cost just paid): the paper's objective, fully cooperative.
* ``local``: region i receives its own dispatch profit (fares minus operating cost of the trips
  that leave i) minus the cost of the vehicles it sent away to rebalance. Local rewards sum to the
  team reward, so a team of local learners still optimises the system's profit, with less noise
  per agent and more room for selfish behaviour.
"""

from __future__ import annotations

from typing import Literal

import numpy as np

from marl_amod.scenario.types import City

RewardMode = Literal["team", "local"]
REWARD_MODES: tuple[str, ...] = ("team", "local")


def dispatch_profit(city: City, t: int, dispatch: np.ndarray) -> np.ndarray:
    """(N,) profit of the trips each region served in step t: sum_j x_ij (price_ij - trip_cost_ij)."""
    return (dispatch * (city.price[t] - city.trip_cost[t])).sum(axis=1)


def rebalancing_cost(city: City, rebalance: np.ndarray) -> np.ndarray:
    """(N,) cost of the rebalancing moves that left each region: sum_j y_ij reb_cost_ij."""
    return (rebalance * city.reb_cost).sum(axis=1)


def local_rewards(city: City, t: int, dispatch: np.ndarray, rebalance: np.ndarray) -> np.ndarray:
    """(N,) local rewards: dispatch profit of step t minus the rebalancing cost paid before it."""
    return dispatch_profit(city, t, dispatch) - rebalancing_cost(city, rebalance)


def team_rewards(n: int, step_reward: float) -> np.ndarray:
    """(N,) the system's step reward, once per agent."""
    return np.full(n, float(step_reward))


def rewards(mode: RewardMode, city: City, t: int, dispatch: np.ndarray, rebalance: np.ndarray, step_reward: float) -> np.ndarray:
    """(N,) rewards of one step under ``mode``."""
    if mode == "team":
        return team_rewards(city.n_regions, step_reward)
    return local_rewards(city, t, dispatch, rebalance)
