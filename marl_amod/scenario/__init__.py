"""What a city is: typed data, readers for real cities, a synthetic generator, a name registry (variants by name included)."""

from marl_amod.scenario.registry import DEFAULT_SCENARIO, ScenarioInfo, available, catalogue, describe, load_city, load_spec
from marl_amod.scenario.simspec import SimSpec
from marl_amod.scenario.synthetic import grid_city
from marl_amod.scenario.types import City

__all__ = [
    "City", "DEFAULT_SCENARIO", "ScenarioInfo", "SimSpec", "available", "catalogue", "describe", "grid_city", "load_city", "load_spec",
]
