"""Policies that do not learn: the paper's heuristics, MPC, and the offline behaviour policies.

They are looked up by name through :mod:`marl_amod.policies`; this package only defines them.
"""

from marl_amod.baselines.base import FlowPolicy, Policy, WeightPolicy
from marl_amod.baselines.behaviour import DynamicTripVehicle, Informed, Proportional
from marl_amod.baselines.heuristics import EqualDistribution, NoRebalancing, PlusOne, RandomPolicy
from marl_amod.baselines.mpc import MPCForecast, MPCOracle, MPCScenarios
from marl_amod.baselines.observation import ObservationPolicy

__all__ = [
    "DynamicTripVehicle", "EqualDistribution", "FlowPolicy", "Informed", "MPCForecast", "MPCOracle", "MPCScenarios",
    "NoRebalancing", "ObservationPolicy", "PlusOne", "Policy", "Proportional", "RandomPolicy", "WeightPolicy",
]
