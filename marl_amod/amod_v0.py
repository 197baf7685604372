"""``amod_v0``: the versioned env module, PettingZoo style (the version changes when results could).

    from marl_amod import amod_v0
    env = amod_v0.parallel_env("nyc_brooklyn", reward_mode="local")

Importing it registers the env as ``marl_amod/amod-v0`` where PettingZoo has a registry (1.27+):
``pettingzoo.make("parallel", "marl_amod/amod-v0")``. Documentation: :mod:`marl_amod.env.parallel`.
"""

from marl_amod.env import ENV_ID, ENV_VERSION
from marl_amod.env.parallel import env, parallel_env, raw_env, register

__all__ = ["ENV_ID", "ENV_VERSION", "env", "parallel_env", "raw_env"]

register()
