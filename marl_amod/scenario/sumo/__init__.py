"""Building SUMO cities: road networks, their regions, a demand model and background traffic.

Everything here produces data (network files in a user cache, arrays, a :class:`City` with a
:class:`~marl_amod.scenario.simspec.SimSpec`); the SUMO simulators in :mod:`marl_amod.sim.meso`
read that data and never build it. Importing this package needs no SUMO installation.
"""
