"""The whole fleet as one gymnasium env: for single-agent libraries (tianshou, CleanRL, ...) with parameter sharing.

``joint_env(scenario, **env_kwargs)`` wraps :func:`marl_amod.parallel_env` so that one learner
acts for every region at once, as the paper's centralised policy does:

===========  ==========================  ===================================================
observation  (N, D) float32              row i is region i's local observation (the ParallelEnv's)
action       (N,) float32 in [0, 1]      entry i is region i's weight (finite values outside clipped)
reward       float                       the team reward: the system's step profit (times ``reward_scale``)
terminated   False                       episodes end by the horizon only ...
truncated    True at the horizon         ... so the last step is truncated
info         dict                        per-region keys (``served``, ``demand``, ...) as (N,) arrays,
                                         ``system_*`` episode metrics as numbers
===========  ==========================  ===================================================

Why it exists: tianshou's multi-agent PPO cannot train on a continuous-action PettingZoo env
(docs/ecosystem.md says where it breaks), while its single-agent PPO trains on this view with
an actor that runs one small network on every row (parameter sharing, decentralised execution)
and a critic on all rows (centralised). With ``reward_mode="local"`` the reward is still the
team's: local rewards sum to it.
"""

from __future__ import annotations

from typing import Any

import gymnasium
import numpy as np
from gymnasium import spaces

from marl_amod.env.actions import real_array
from marl_amod.env.parallel import AmodParallelEnv, parallel_env
from marl_amod.errors import ActionError


class JointEnv(gymnasium.Env):
    """A marl_amod ParallelEnv seen as one agent acting for all N regions (see module doc)."""

    metadata = {"render_modes": ["human", "rgb_array"], "name": "amod_joint_v0", "render_fps": AmodParallelEnv.metadata["render_fps"]}

    def __init__(self, env: AmodParallelEnv) -> None:
        self.parallel = env
        self.agents = list(env.possible_agents)
        self.render_mode = env.render_mode
        one = env.observation_space(self.agents[0])
        n = len(self.agents)
        self.observation_space = spaces.Box(
            np.broadcast_to(one.low, (n, *one.shape)), np.broadcast_to(one.high, (n, *one.shape)), dtype=np.float32
        )  # fmt: skip
        self.action_space = spaces.Box(0.0, 1.0, (n,), dtype=np.float32)

    def reset(self, *, seed: int | None = None, options: dict | None = None) -> tuple[np.ndarray, dict[str, Any]]:
        super().reset(seed=seed)
        obs, infos = self.parallel.reset(seed=seed, options=options)
        return self._stack(obs), self._info(infos)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        action = real_array(action, "the joint action")  # as given: a float32 cast first would turn 1e39 into inf, 1e-46 into 0
        n = len(self.agents)
        if action.shape not in ((n,), (n, 1)):
            raise ActionError(f"the joint action needs one value per region, shape ({n},) or ({n}, 1), got shape {action.shape}")
        action = action.reshape(n, 1)  # one (1,) action per region
        obs, rewards, terms, truncs, infos = self.parallel.step({a: action[i] for i, a in enumerate(self.agents)})
        reward = sum(rewards.values()) if self.parallel.reward_mode == "local" else rewards[self.agents[0]]
        return self._stack(obs), float(reward), all(terms.values()), all(truncs.values()), self._info(infos)

    def state(self) -> np.ndarray:
        """The ParallelEnv's global state (N * F + 3,), for a critic that wants it."""
        return self.parallel.state()

    def render(self) -> np.ndarray | None:
        return self.parallel.render()

    def close(self) -> None:
        self.parallel.close()

    def _stack(self, obs: dict[str, np.ndarray]) -> np.ndarray:
        return np.stack([obs[a] for a in self.agents])

    def _info(self, infos: dict[str, dict[str, Any]]) -> dict[str, Any]:
        first = infos[self.agents[0]]
        return {k: v if k.startswith("system_") else np.array([infos[a][k] for a in self.agents]) for k, v in first.items()}


def joint_env(scenario: Any = "synthetic", **kwargs: Any) -> JointEnv:
    """:class:`JointEnv` over ``marl_amod.parallel_env(scenario, **kwargs)`` (the same keywords)."""
    return JointEnv(parallel_env(scenario, **kwargs))
