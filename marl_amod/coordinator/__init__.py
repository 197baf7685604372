"""The exact optimisation layer: dispatch (Step 1) and rebalancing (Step 3) of the paper."""

from marl_amod.coordinator.coordinator import Coordinator
from marl_amod.coordinator.dispatch import greedy_dispatch
from marl_amod.coordinator.rebalance import desired_targets, min_cost_rebalance

__all__ = ["Coordinator", "desired_targets", "greedy_dispatch", "min_cost_rebalance"]
