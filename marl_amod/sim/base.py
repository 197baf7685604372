"""What every simulator offers, so that one :class:`~marl_amod.system.FleetSystem` drives any of them.

The macro model (``MacroSim``) and the SUMO models (``MesoSim``, ``TaxiMesoSim``) all satisfy
this protocol. A city names its simulator as data (``City.simulator``, a
:class:`~marl_amod.scenario.simspec.SimSpec`) and :func:`make_simulator` is the one place that
builds it, so the env, the evaluation loop and training need no per-simulator branches.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.macro import EpisodeTotals, MacroSim, check_max_wait
from marl_amod.sim.meso.sumo_sim import MesoSim
from marl_amod.sim.meso.taxi_sim import TaxiMesoSim


class Simulator(Protocol):
    city: City
    t: int
    totals: EpisodeTotals
    demand: np.ndarray  # (S, N, N) requests drawn for every step
    arrivals: np.ndarray  # (L, N) busy vehicles becoming idle after step k
    last_dispatch: np.ndarray  # (N, N)
    last_rebalance: np.ndarray  # (N, N)
    dispatch_rounds: int  # dispatches per control step; > 1 needs advance_round()

    @property
    def done(self) -> bool: ...
    @property
    def idle(self) -> np.ndarray: ...  # (N,) int
    def reset(self, rng: np.random.Generator) -> None: ...
    def requests(self) -> np.ndarray: ...
    def carried_over(self) -> np.ndarray: ...  # (N, N) open now and still waiting at the next step
    def vehicles(self) -> int: ...
    # check=False: the flows are the coordinator's, feasible by construction (FleetSystem's validate flag)
    def apply_dispatch(self, x: np.ndarray, *, check: bool = True) -> float: ...
    def apply_rebalance(self, y: np.ndarray, *, check: bool = True) -> float: ...
    def advance(self) -> None: ...
    def advance_round(self) -> None: ...  # only called when dispatch_rounds > 1
    def finish(self) -> None: ...
    def close(self) -> None: ...  # ends what reset started (a SUMO run); reset may follow


def make_simulator(city: City, max_wait: int = 0) -> Simulator:
    """The simulator ``city.simulator`` names; ``max_wait`` as MacroSim's (steps), where a positive
    value also overrides a SUMO scenario's ``max_wait_min``."""
    spec = city.simulator
    if spec.kind == "macro":
        return MacroSim(city, max_wait=max_wait)
    max_wait = check_max_wait(max_wait, city)
    minutes = max_wait * city.tstep if max_wait > 0 else spec.sumo.max_wait_min
    sim = TaxiMesoSim if spec.kind == "taxi" else MesoSim
    return sim(city, spec.sumo, max_wait_min=minutes)
