"""How a city evolves: pure-numpy simulators that know no RL API."""

from marl_amod.sim.macro import EpisodeTotals, MacroSim

__all__ = ["EpisodeTotals", "MacroSim"]
