"""Stable-Baselines3 with parameter sharing: every region of every env copy is one row of one policy.

SuperSuit turns the ParallelEnv's N agents into N rows of a vector env. SB3 seeds a vector env
with ``venv.seed(s)``, which SuperSuit's ``ConcatVecEnv`` lacks (and its SB3 wrapper drops the
seed on reset); :class:`SeedForwarding` keeps the seed and hands it to the next reset, so
``PPO(..., seed=0)`` gives reproducible runs.

    pip install "marl-amod[sb3]"
"""

from __future__ import annotations

from typing import Any

from marl_amod.errors import ConfigError
from marl_amod.validation import as_count


def _import_backends() -> tuple[Any, Any]:
    try:
        import supersuit as ss
        from stable_baselines3.common.vec_env import VecEnvWrapper
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise ConfigError(f'Stable-Baselines3 support needs the extra: pip install "marl-amod[sb3]" ({exc})') from exc
    return ss, VecEnvWrapper


def sb3_vec_env(env: Any, copies: int = 1) -> Any:
    """An SB3 ``VecEnv`` with ``copies`` x N rows over a marl_amod ParallelEnv, seeds forwarded."""
    copies = as_count(copies, "copies", lower=1)
    ss, vec_env_wrapper = _import_backends()

    class SeedForwarding(vec_env_wrapper):
        """Keeps the seed SB3 gives and passes it to the underlying ConcatVecEnv's reset."""

        def __init__(self, venv: Any) -> None:
            super().__init__(venv)
            self._seed: int | None = None

        def seed(self, seed: int | None = None) -> list[int | None]:
            self._seed = seed
            return [seed]

        def reset(self) -> Any:
            seed, self._seed = self._seed, None
            if seed is None:
                return self.venv.reset()
            obs, self.venv.reset_infos = self.venv.venv.reset(seed=seed)  # the ConcatVecEnv under SB3's wrapper
            return obs

        def step_wait(self) -> Any:
            return self.venv.step_wait()

    vec = ss.pettingzoo_env_to_vec_env_v1(env)  # one row per region
    vec = ss.concat_vec_envs_v1(vec, copies, num_cpus=0, base_class="stable_baselines3")
    return SeedForwarding(vec)
