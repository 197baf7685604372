"""Non-learning policies: no rebalancing, equal distribution, plus-one, random."""

from marl_amod.baselines.base import Policy, WeightPolicy
from marl_amod.baselines.heuristics import BASELINES, EqualDistribution, NoRebalancing, PlusOne, RandomPolicy

__all__ = ["BASELINES", "EqualDistribution", "NoRebalancing", "PlusOne", "Policy", "RandomPolicy", "WeightPolicy"]

# Optimisation baselines and behaviour policies join the by-name registry that make_policy and the
# CLI read. They go into BASELINES (every one is constructible without arguments) rather than
# through evaluation.register_policy: evaluation imports this package first, so calling it from
# here would be a circular import.
from marl_amod.baselines.behaviour import BEHAVIOUR_POLICIES  # noqa: E402
from marl_amod.baselines.mpc import MPCForecast, MPCOracle  # noqa: E402

BASELINES.update(BEHAVIOUR_POLICIES)
BASELINES.update({MPCOracle.name: MPCOracle, MPCForecast.name: MPCForecast})
