"""Which simulator runs a city, as data: a kind and its settings, never a factory.

A :class:`~marl_amod.scenario.types.City` carries a :class:`SimSpec`; the one place that turns it
into a running simulator is :func:`marl_amod.sim.base.make_simulator`. Scenarios build these
values and the simulators read them, so data flows one way (scenario -> simulator).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal, get_args

import numpy as np

SimKind = Literal["macro", "meso", "taxi"]  # region model; SUMO with one vehicle per leg; SUMO's taxi device
SumoMode = Literal["meso", "micro"]  # SUMO's mesoscopic (--mesosim) or microscopic model
SumoBackend = Literal["libsumo", "traci"]  # in-process (one simulation per process) or a subprocess


@dataclass(frozen=True, eq=False)
class SumoOptions:
    """How a city is simulated in SUMO: the built network and its region map, and SUMO's settings."""

    net_file: Path  # the built .net.xml (in the network cache)
    of_edge: np.ndarray = field(repr=False)  # (E,) int, region of every usable edge of the network
    mode: SumoMode = "meso"
    max_wait_min: float = 10.0  # a request leaves after waiting this long
    backend: SumoBackend = "libsumo"
    step_length: float = 1.0  # SUMO seconds per simulation step
    sumo_seed: int = 0
    begin_s: float = 0.0  # clock time of step 0, in seconds of the day
    time_to_teleport: float = 300.0
    refresh_travel_times: bool = True  # re-estimate region travel times from SUMO every step
    dispatch_every_min: float | None = None  # match requests this often inside a step (None: once)
    route_files: tuple[str, ...] = ()  # other traffic SUMO loads next to the fleet (ids not "fleet*"/"taxi*")
    region_seed: int = 0  # seeds the edges that region travel times average over
    sumo_router: bool = False  # route each fleet leg with SUMO's findRoute (slow; the fast table is checked against it)
    quiet: bool = True  # silence SUMO's warnings (pass extra_args=("--log", file) to keep them)
    extra_args: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.mode not in get_args(SumoMode):
            raise ValueError(f"SUMO mode must be one of {get_args(SumoMode)}, got {self.mode!r}")
        if self.backend not in get_args(SumoBackend):
            raise ValueError(f"SUMO backend must be one of {get_args(SumoBackend)}, got {self.backend!r}")
        if self.max_wait_min < 0:
            raise ValueError(f"max_wait_min must be >= 0, got {self.max_wait_min}")
        self.of_edge.setflags(write=False)


@dataclass(frozen=True)
class SimSpec:
    """A simulator kind and, for the SUMO kinds, its :class:`SumoOptions`."""

    kind: SimKind = "macro"
    sumo: SumoOptions | None = None  # required by "meso" and "taxi", absent for "macro"

    def __post_init__(self) -> None:
        if self.kind not in get_args(SimKind):
            raise ValueError(f"simulator kind must be one of {get_args(SimKind)}, got {self.kind!r}")
        if (self.kind == "macro") != (self.sumo is None):
            raise ValueError(f"simulator {self.kind!r} " + ("takes no SUMO options" if self.sumo else "needs SumoOptions"))


MACRO = SimSpec()
