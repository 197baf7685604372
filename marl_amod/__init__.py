"""marl_amod: robo-taxi fleet coordination as a multi-agent RL benchmark.

``parallel_env(...)`` makes the PettingZoo ParallelEnv (every region an agent), ``env(...)`` its
AEC version; see :mod:`marl_amod.env.parallel` for the documentation. Importing the package
loads numpy-level code only (no torch); the env's modules load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# ``marl_amod.env`` is the env subpackage, made callable: ``marl_amod.env(...)`` builds the AEC env.
from marl_amod import env

__version__ = "0.1.0"
__all__ = ["amod_v0", "env", "parallel_env"]

if TYPE_CHECKING:
    from marl_amod.env.parallel import AmodParallelEnv
    from marl_amod.scenario.types import City


def parallel_env(scenario: str | City = "synthetic", **kwargs: Any) -> AmodParallelEnv:
    """The PettingZoo ParallelEnv: every region an agent (arguments: :mod:`marl_amod.env.parallel`).

    Keywords: reward_mode="team"|"local", action_mode="weight"|"logit", lookahead=6, max_wait=0,
    objective="profit", reward_scale=1.0|"auto", strict_actions=False, max_cycles=None,
    render_mode=None, and scenario overrides such as horizon=10.
    """
    from marl_amod.env.parallel import parallel_env as make

    return make(scenario, **kwargs)


def __getattr__(name: str) -> Any:
    if name == "amod_v0":
        from importlib import import_module

        return import_module("marl_amod.amod_v0")
    raise AttributeError(f"module 'marl_amod' has no attribute {name!r}")
