"""Where SUMO comes from: the pip-installed ``eclipse-sumo`` wheel, its binaries and its version.

Imported lazily by whoever needs SUMO, so the rest of marl_amod works without the extra and
fails, when a SUMO scenario is asked for, with the command that fixes it.
"""

from __future__ import annotations

import os
from pathlib import Path

from marl_amod.errors import ConfigError

INSTALL_HINT = 'pip install "marl-amod[sumo]"'


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
