"""marl_amod: robo-taxi fleet coordination as a multi-agent RL benchmark.

``parallel_env(...)`` makes the PettingZoo ParallelEnv (every region an agent), ``env(...)`` its
AEC version; see :mod:`marl_amod.env.parallel` for the documentation. ``vector_env(...)`` runs B
episodes of one city in lockstep with (B, N, ...) arrays (:mod:`marl_amod.env.vector`). Importing the package
loads numpy-level code only (no torch); the env's modules load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# ``marl_amod.env`` is the env subpackage, made callable: ``marl_amod.env(...)`` builds the AEC env.
from marl_amod import env

__version__ = "0.1.0"
__all__ = ["amod_v0", "env", "parallel_env", "vector_env"]

if TYPE_CHECKING:
    from marl_amod.env.parallel import AmodParallelEnv
    from marl_amod.env.vector import AmodVectorEnv
    from marl_amod.scenario.types import City


def parallel_env(scenario: str | City = "synthetic", **kwargs: Any) -> AmodParallelEnv:
    """The PettingZoo ParallelEnv: every region an agent (arguments: :mod:`marl_amod.env.parallel`).

    Keywords: reward_mode="team"|"local", action_mode="weight"|"logit", lookahead=6, max_wait=0,
    objective="profit", render_mode=None, and scenario overrides such as horizon=10.
    """
    from marl_amod.amod_v0 import parallel_env as make

    return make(scenario, **kwargs)


def vector_env(scenario: str | City = "synthetic", num_envs: int = 16, **kwargs: Any) -> AmodVectorEnv:
    """B episodes of one city in lockstep, arrays (B, N, ...) in and out (:mod:`marl_amod.env.vector`).

    Takes the ParallelEnv's keywords (reward_mode, action_mode, lookahead, max_wait, objective and
    scenario overrides); ``reset(seed=s)`` gives episode b the ParallelEnv's episode of seed s + b.
    """
    from marl_amod.env.vector import AmodVectorEnv

    return AmodVectorEnv(scenario, num_envs, **kwargs)


def __getattr__(name: str) -> Any:
    if name == "amod_v0":
        from importlib import import_module

        return import_module("marl_amod.amod_v0")
    raise AttributeError(f"module 'marl_amod' has no attribute {name!r}")
