"""Starting and stopping SUMO runs through libsumo (in-process) or TraCI (a ``sumo`` subprocess).

SUMO is imported lazily here, so the rest of marl_amod works without the extra and fails, when a
SUMO scenario is run, with the command that fixes it.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
from typing import Any

from marl_amod.errors import ConfigError
from marl_amod.scenario.simspec import SumoBackend
from marl_amod.scenario.sumo.install import INSTALL_HINT, binary

_labels = itertools.count()
_libsumo_owner: list[object | None] = [None]  # token of whoever started the one in-process libsumo run


def owns(owner: object) -> bool:
    """Whether ``owner`` started the libsumo simulation that is running now."""
    return _libsumo_owner[0] is owner


def start(args: list[str], backend: SumoBackend, owner: object) -> Any:
    """Start a simulation; returns an object with ``.vehicle``, ``.simulation``, ``.route``,
    ``simulationStep`` and ``close`` (the libsumo module, or one labelled TraCI connection).

    libsumo runs in-process (about 100x cheaper per call) but allows one simulation per process:
    starting one ends the previous one, and ``owner`` (any object; compared by identity) marks
    whose it is now. TraCI runs SUMO as a subprocess and allows several side by side.
    """
    cmd = [binary("sumo"), *args]
    if backend == "libsumo":
        try:
            # libsumo prints a pyarrow version warning on import when Ray's pyarrow is installed;
            # it concerns SUMO's parquet output, which marl_amod never writes
            with contextlib.redirect_stdout(io.StringIO()):
                import libsumo
        except ImportError as exc:
            raise ConfigError(f"backend 'libsumo' needs the SUMO extra: {INSTALL_HINT}") from exc
        if libsumo.simulation.isLoaded():
            libsumo.close()
        libsumo.start(cmd)
        _libsumo_owner[0] = owner
        return libsumo
    if backend == "traci":
        try:
            import traci
        except ImportError as exc:
            raise ConfigError(f"backend 'traci' needs the SUMO extra: {INSTALL_HINT}") from exc
        label = f"marl_amod_{os.getpid()}_{next(_labels)}"
        traci.start(cmd, label=label)
        return traci.getConnection(label)
    raise ConfigError(f"backend must be 'libsumo' or 'traci', got {backend!r}")


def stop(api: Any, backend: SumoBackend, owner: object) -> None:
    """End a run that ``owner`` started: a TraCI connection and its ``sumo`` process (waited
    for), or the libsumo simulation unless another owner has replaced it since. Safe to call
    from a finalizer: it holds no reference to the simulator."""
    if backend == "libsumo":
        if owns(owner):
            _libsumo_owner[0] = None
            if api.simulation.isLoaded():
                api.close()
        return
    from traci.exceptions import FatalTraCIError

    with contextlib.suppress(FatalTraCIError, OSError):  # its sumo already died: nothing left to end
        api.close()
