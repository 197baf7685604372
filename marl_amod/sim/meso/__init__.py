"""Mesoscopic simulation through SUMO, behind the same interface as the macro simulator.

``types`` (the fleet and request records, named states), ``bookkeeping`` (what changes in them:
pure numpy, no SUMO), ``options`` (SUMO's command line from a city's ``SumoOptions``),
``engine`` (starting and stopping libsumo / TraCI runs), ``sumo_sim`` (the driver: one SUMO
vehicle per driving leg) and ``taxi_sim`` (the fleet as SUMO taxis). The cities themselves are
built in :mod:`marl_amod.scenario.sumo`. Submodules import SUMO lazily; importing this package
needs no SUMO installation.
"""
