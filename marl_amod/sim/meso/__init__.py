"""Mesoscopic simulation through SUMO, behind the same interface as the macro simulator.

Submodules import SUMO lazily; importing this package needs no SUMO installation.
"""
