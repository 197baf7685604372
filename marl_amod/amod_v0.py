"""``amod_v0``: the versioned env module, PettingZoo style (the version changes when results could).

    from marl_amod import amod_v0
    env = amod_v0.parallel_env("nyc_brooklyn", reward_mode="local")

Where PettingZoo has a registry (1.27+), the env is also registered as ``marl_amod/amod-v0``:
``pettingzoo.make("parallel", "marl_amod/amod-v0")``.
"""

from __future__ import annotations

from typing import Any

from pettingzoo.utils import parallel_to_aec
from pettingzoo.utils.env import AECEnv

from marl_amod.env.parallel import AmodParallelEnv
from marl_amod.scenario.types import City

ENV_ID = "marl_amod/amod-v0"


def parallel_env(scenario: str | City = "synthetic", **kwargs: Any) -> AmodParallelEnv:
    """The parallel env; keyword arguments as :class:`~marl_amod.env.parallel.AmodParallelEnv`."""
    return AmodParallelEnv(scenario, **kwargs)


def raw_env(scenario: str | City = "synthetic", **kwargs: Any) -> AECEnv:
    """The AEC env through PettingZoo's own conversion (agents act one after another)."""
    return parallel_to_aec(parallel_env(scenario, **kwargs))


env = raw_env


def _register() -> None:
    """Add the env to PettingZoo's registry once, where the installed version has one."""
    try:
        import pettingzoo
        from pettingzoo.env_registry.registration import parallel_registry
    except ImportError:
        return
    if not hasattr(pettingzoo, "register") or ENV_ID in parallel_registry:
        return
    pettingzoo.register("parallel", ENV_ID, entry_point="marl_amod.amod_v0:parallel_env")
    pettingzoo.register("aec", ENV_ID, entry_point="marl_amod.amod_v0:raw_env")


_register()
