"""Non-learning policies: no rebalancing, equal distribution, plus-one, random."""

from marl_amod.baselines.base import Policy, WeightPolicy
from marl_amod.baselines.heuristics import BASELINES, EqualDistribution, NoRebalancing, PlusOne, RandomPolicy

__all__ = ["BASELINES", "EqualDistribution", "NoRebalancing", "PlusOne", "Policy", "RandomPolicy", "WeightPolicy"]
