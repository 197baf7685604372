"""TorchRL: the batched env (:mod:`marl_amod.env.vector`) as an ``EnvBase`` with batch size (B,).

Keys follow TorchRL's multi-agent convention (as its VMAS wrapper does), one group ``"agents"``:

==========================  ================  ===============================================
key                         shape             meaning
==========================  ================  ===============================================
("agents", "observation")   (B, N, D) float32 local observations (:mod:`marl_amod.env.observations`)
("agents", "action")        (B, N, 1) float32 per-region action in [0, 1]
("agents", "reward")        (B, N, 1) float32 team or local reward, as the vector env gives it
"state"                     (B, N*F+3)        global state of each episode
"done", "terminated",       (B, 1) bool       every episode has the same horizon, so all end
"truncated"                                   together (truncated); the next reset restarts all
==========================  ================  ===============================================

``env.set_seed(s)`` makes the next reset seed episode b with s + b (the ParallelEnv's episode of
that seed). Rollouts that continue past the horizon reset all episodes at once; a ``_reset`` mask
that selects only some episodes is a ConfigError (they share one clock).

    pip install "marl-amod[torchrl]"
"""

from __future__ import annotations

from typing import Any

import numpy as np

from marl_amod.errors import ConfigError


def _backends() -> tuple[Any, Any, Any]:
    try:
        import torch
        import torchrl.data as specs
        from tensordict import TensorDict
        from torchrl.envs import EnvBase
    except ImportError as exc:  # pragma: no cover - exercised only without the extra
        raise ConfigError(f'TorchRL support needs the extra: pip install "marl-amod[torchrl]" ({exc})') from exc
    return torch, specs, (TensorDict, EnvBase)


def torchrl_vector_env(scenario: Any = "synthetic", num_envs: int = 16, device: Any = "cpu", **options: Any) -> Any:
    """A TorchRL ``EnvBase`` over ``marl_amod.vector_env(scenario, num_envs, **options)``."""
    torch, specs, (TensorDict, EnvBase) = _backends()
    from marl_amod.env.vector import AmodVectorEnv

    class AmodTorchRLEnv(EnvBase):
        """B lockstep episodes; see :mod:`marl_amod.integrations.torchrl` for the keys."""

        def __init__(self) -> None:
            self.vector = AmodVectorEnv(scenario, num_envs, **options)
            b, n = self.vector.num_envs, self.vector.num_agents
            super().__init__(batch_size=torch.Size([b]), device=device)
            obs, state = self.vector.observation_space, self.vector.state_space
            self.observation_spec = specs.Composite(
                agents=specs.Composite(
                    observation=specs.Bounded(
                        torch.as_tensor(obs.low).expand(b, n, -1), torch.as_tensor(obs.high).expand(b, n, -1),
                        shape=(b, n, obs.shape[0]), dtype=torch.float32, device=device,
                    ),
                    shape=(b, n), device=device,
                ),
                state=specs.Bounded(
                    torch.as_tensor(state.low).expand(b, -1), torch.as_tensor(state.high).expand(b, -1),
                    shape=(b, state.shape[0]), dtype=torch.float32, device=device,
                ),
                shape=(b,), device=device,
            )
            self.action_spec = specs.Composite(
                agents=specs.Composite(
                    action=specs.Bounded(0.0, 1.0, shape=(b, n, 1), dtype=torch.float32, device=device),
                    shape=(b, n), device=device,
                ),
                shape=(b,), device=device,
            )
            self.reward_spec = specs.Composite(
                agents=specs.Composite(reward=specs.Unbounded(shape=(b, n, 1), dtype=torch.float32, device=device), shape=(b, n), device=device),
                shape=(b,), device=device,
            )
            self.done_spec = specs.Composite(
                **{key: specs.Categorical(2, shape=(b, 1), dtype=torch.bool, device=device) for key in ("done", "terminated", "truncated")},
                shape=(b,), device=device,
            )
            self._seed: int | None = None

        def _out(self, obs: np.ndarray, done: bool) -> Any:
            b = self.batch_size[0]
            flag = torch.full((b, 1), done, dtype=torch.bool, device=self.device)
            return TensorDict(
                {
                    "agents": TensorDict({"observation": torch.as_tensor(obs, device=self.device)}, batch_size=obs.shape[:2]),
                    "state": torch.as_tensor(self.vector.state(), device=self.device),
                    "done": flag,
                    "terminated": torch.zeros_like(flag),
                    "truncated": flag.clone(),
                },
                batch_size=self.batch_size,
                device=self.device,
            )

        def _reset(self, tensordict: Any = None, **kwargs: Any) -> Any:
            mask = None if tensordict is None else tensordict.get("_reset", None)
            if mask is not None and not bool(mask.all()):  # restarting all would desync the others silently
                raise ConfigError(
                    f"the {self.batch_size[0]} episodes run in lockstep and reset together; got a _reset mask "
                    f"for {int(mask.sum())} of them (reset all, or step until every episode is done)"
                )
            seed, self._seed = self._seed, None
            obs, _ = self.vector.reset(seed=seed)
            return self._out(obs, False)

        def _step(self, tensordict: Any) -> Any:
            action = tensordict.get(("agents", "action")).detach().cpu().numpy()
            obs, rew, _, trunc, _ = self.vector.step(action)
            out = self._out(obs, bool(trunc.all()))
            out.set(("agents", "reward"), torch.as_tensor(rew, dtype=torch.float32, device=self.device).unsqueeze(-1))
            return out

        def _set_seed(self, seed: int | None) -> None:
            self._seed = None if seed is None else int(seed)

    return AmodTorchRLEnv()
