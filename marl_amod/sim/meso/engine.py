"""Where SUMO comes from: the pip-installed ``eclipse-sumo`` binaries and libsumo / TraCI.

Everything SUMO is imported lazily here, so the rest of marl_amod works without the extra and
fails, when a SUMO scenario is asked for, with the command that fixes it.
"""

from __future__ import annotations

import contextlib
import io
import itertools
import os
from pathlib import Path
from typing import Any, Literal

from marl_amod.errors import ConfigError

Backend = Literal["libsumo", "traci"]
INSTALL_HINT = 'pip install "marl-amod[sumo]"'
_labels = itertools.count()


def sumo_home() -> Path:
    """SUMO_HOME of the ``eclipse-sumo`` wheel (importing ``sumo`` sets the variable)."""
    try:
        import sumo
    except ImportError as exc:
        raise ConfigError(f"SUMO scenarios need the SUMO extra: {INSTALL_HINT}") from exc
    os.environ.setdefault("SUMO_HOME", sumo.SUMO_HOME)
    return Path(sumo.SUMO_HOME)


def binary(name: str) -> str:
    """Path of a SUMO tool (``sumo``, ``netconvert``, ``netgenerate``) shipped with the wheel."""
    path = sumo_home() / "bin" / name
    if not path.exists():
        raise ConfigError(f"SUMO tool {name!r} not found at {path}; reinstall with {INSTALL_HINT}")
    return str(path)


def version() -> str:
    """Version of the installed SUMO, part of every cache key (a new SUMO rebuilds networks)."""
    from importlib.metadata import PackageNotFoundError
    from importlib.metadata import version as pkg_version

    try:
        return pkg_version("eclipse-sumo")
    except PackageNotFoundError as exc:
        raise ConfigError(f"SUMO scenarios need the SUMO extra: {INSTALL_HINT}") from exc


_libsumo_owner: list[object | None] = [None]  # who started the one in-process libsumo simulation


def owns(owner: object) -> bool:
    """Whether ``owner`` started the libsumo simulation that is running now."""
    return _libsumo_owner[0] is owner


def start(args: list[str], backend: Backend, owner: object = None) -> Any:
    """Start a simulation; returns an object with ``.vehicle``, ``.simulation``, ``.route``,
    ``simulationStep`` and ``close`` (the libsumo module, or one labelled TraCI connection).

    libsumo runs in-process (about 100x cheaper per call) but allows one simulation per process;
    TraCI runs SUMO as a subprocess and allows several side by side.
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
