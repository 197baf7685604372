"""The multi-agent environment: every region an agent of a PettingZoo ParallelEnv (see :mod:`.parallel`).

Names load on first use, so ``marl_amod.env.features`` stays importable without PettingZoo.
"""

from __future__ import annotations

from importlib import import_module
from typing import Any

_LAZY = {
    "AmodParallelEnv": "marl_amod.env.parallel",
    "local_observations": "marl_amod.env.observations",
    "split_local": "marl_amod.env.observations",
    "write_episode_gif": "marl_amod.env.render",
    "record_episode": "marl_amod.env.render",
}
__all__ = sorted(_LAZY)


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'marl_amod.env' has no attribute {name!r}")
