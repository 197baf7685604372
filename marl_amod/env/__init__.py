"""The multi-agent environment: every region an agent of a PettingZoo ParallelEnv (see :mod:`.parallel`).

Names load on first use, so ``marl_amod.env.features`` stays importable without PettingZoo.

The package is also callable: ``marl_amod.env(...)`` is the AEC env (PettingZoo names its AEC
constructor ``env``, and a function of that name could not coexist with this subpackage, which
Python binds to the attribute ``marl_amod.env`` as soon as any of its modules is imported).
"""

from __future__ import annotations

import sys
from importlib import import_module
from types import ModuleType
from typing import Any

ENV_VERSION = "amod_v0"  # PettingZoo-style versioned name; policy cards record it
ENV_ID = "marl_amod/amod-v0"  # the name in PettingZoo's registry (1.27+)

_LAZY = {
    "AmodParallelEnv": "marl_amod.env.parallel",
    "parallel_env": "marl_amod.env.parallel",
    "raw_env": "marl_amod.env.parallel",
    "local_observations": "marl_amod.env.observations",
    "split_local": "marl_amod.env.observations",
    "write_episode_gif": "marl_amod.env.render",
    "record_episode": "marl_amod.env.render",
}
__all__ = ["ENV_ID", "ENV_VERSION", *sorted(_LAZY)]


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'marl_amod.env' has no attribute {name!r}")


class _CallableEnvPackage(ModuleType):
    def __call__(self, scenario: Any = "synthetic", **kwargs: Any) -> Any:
        """The AEC env: ``parallel_to_aec(parallel_env(scenario, **kwargs))``."""
        from marl_amod.env.parallel import raw_env

        return raw_env(scenario, **kwargs)


sys.modules[__name__].__class__ = _CallableEnvPackage
