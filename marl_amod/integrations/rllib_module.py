"""The RLlib pieces that import Ray: the scaled Gamma action distribution and the shared GNN RLModule.

Kept apart from :mod:`marl_amod.integrations.rllib` so that module imports without Ray (and names
the extra when it is missing), while these classes stay importable by reference on every Ray worker.
Import it only through :func:`marl_amod.integrations.rllib.require_ray`, which sets Ray's
environment first.

Why a scaled Gamma. Agent i samples g_i ~ Gamma(alpha_i, 1) and sends a_i = g_i / c into the
env's ``Box(0, 1)`` (c = :data:`marl_amod.algos.rollout.WEIGHT_DIVISOR`, exactly what the native
decentralised actor sends); the env normalises the weights, so the joint action is the paper's
Dirichlet(alpha). RLlib stores a_i and asks for ``logp(a_i)`` later (PPO's ratio), so the density
is that of a_i itself: log Gamma(c a_i; alpha_i) + log c. Nothing is clipped or squashed on the
way (the config turns RLlib's action normalisation and clipping off), so the stored action is
the one that was sampled and the ratio is exact. The deterministic action is the mean alpha_i / c,
which the env normalises into the Dirichlet mean, as ``marl-amod evaluate`` does.
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import torch
from ray.rllib.core.columns import Columns
from ray.rllib.core.distribution.torch.torch_distribution import TorchDeterministic, TorchDistribution
from ray.rllib.core.rl_module.apis import InferenceOnlyAPI, ValueFunctionAPI
from ray.rllib.core.rl_module.torch import TorchRLModule

from marl_amod.algos.rollout import WEIGHT_DIVISOR
from marl_amod.env.observations import split_local
from marl_amod.models.gnn import mlp_head
from marl_amod.models.local import LocalActor

_LOG_C = math.log(WEIGHT_DIVISOR)


class ScaledGamma(TorchDistribution):
    """a = g / c with g ~ Gamma(alpha, 1); inputs are the concentrations alpha (..., 1) > 0."""

    def __init__(self, concentration: torch.Tensor) -> None:
        self.concentration = concentration
        super().__init__(concentration=concentration)

    def _get_torch_distribution(self, concentration: torch.Tensor) -> torch.distributions.Gamma:
        return torch.distributions.Gamma(concentration, torch.ones_like(concentration), validate_args=False)

    def logp(self, value: torch.Tensor, **kwargs: Any) -> torch.Tensor:
        g = (value * WEIGHT_DIVISOR).clamp_min(1e-30)  # a float32 draw of a tiny alpha can underflow to 0
        return (self._dist.log_prob(g) + _LOG_C).sum(-1)

    def entropy(self) -> torch.Tensor:
        return (self._dist.entropy() - _LOG_C).sum(-1)

    def kl(self, other: ScaledGamma) -> torch.Tensor:
        return torch.distributions.kl_divergence(self._dist, other._dist).sum(-1)  # scale-invariant

    def sample(self, *, sample_shape: Any = None) -> torch.Tensor:
        return self._dist.sample(sample_shape or torch.Size()) / WEIGHT_DIVISOR

    def rsample(self, *, sample_shape: Any = None) -> torch.Tensor:
        return self._dist.rsample(sample_shape or torch.Size()) / WEIGHT_DIVISOR

    @staticmethod
    def required_input_dim(space: gym.Space, **kwargs: Any) -> int:
        return 1

    @classmethod
    def from_logits(cls, logits: torch.Tensor, **kwargs: Any) -> ScaledGamma:
        """The module already emits concentrations (softplus + eps in :class:`LocalActor`)."""
        return cls(concentration=logits)

    def to_deterministic(self) -> TorchDeterministic:
        return TorchDeterministic(loc=self.concentration / WEIGHT_DIVISOR)


class AmodGNNModule(TorchRLModule, ValueFunctionAPI, InferenceOnlyAPI):
    """One region's policy: marl_amod's :class:`LocalActor` on the local observation, plus a value head.

    ``model_config``: ``local_dim`` (D of the env's local observation), ``n_features`` (F),
    ``hidden`` (actor MLP), ``critic_hidden``. The observation is the local one, followed by the
    env's global ``state()`` when the env was made with ``central_critic=True``: the actor only
    ever reads the first D entries (so it stays decentralised and converts to a native policy), the
    critic reads everything it is given (the global state with a centralised critic).
    """

    def setup(self) -> None:
        cfg = self.model_config
        self.local_dim = int(cfg["local_dim"])
        self.n_features = int(cfg.get("n_features", 13))
        self.actor = LocalActor(self.n_features, int(cfg.get("hidden", 32)))
        if not self.inference_only:
            self.critic = mlp_head(int(self.observation_space.shape[0]), int(cfg.get("critic_hidden", 64)))
        self.action_dist_cls = ScaledGamma

    def concentration(self, obs: torch.Tensor) -> torch.Tensor:
        """(B, D[+S]) observations -> (B, 1) Gamma concentrations, from the local part only."""
        own, _ctx, nbrs, mask = split_local(obs[..., : self.local_dim], self.n_features)
        return self.actor.forward_local(own, nbrs, mask).unsqueeze(-1)

    def _forward(self, batch: dict[str, Any], **kwargs: Any) -> dict[str, Any]:
        return {Columns.ACTION_DIST_INPUTS: self.concentration(batch[Columns.OBS])}

    def compute_values(self, batch: dict[str, Any], embeddings: Any = None) -> torch.Tensor:
        return self.critic(batch[Columns.OBS]).squeeze(-1)

    def get_non_inference_attributes(self) -> list[str]:
        """Env runners only act: they build the module without the critic."""
        return ["critic"]
