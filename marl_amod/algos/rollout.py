"""The rollout drivers both native algorithms share: one city, in either mode.

* ``centralised``: one learner sees the global graph (N, F) and acts for every region.
* ``decentralised``: every region acts from its own local observation (own features plus its
  in-neighbours' features and a mask), with one shared parameter set. Observations come through
  the PettingZoo env (``marl_amod.parallel_env``), exactly as a deployed agent would see them.

:class:`Rollout` runs one episode at a time (``num_envs: 1``, what the shipped policies were
trained with); :class:`BatchRollout` runs B episodes in lockstep on the batched simulator
(:mod:`marl_amod.batch_system`; decentralised through :func:`marl_amod.vector_env`, whose
observations are the ParallelEnv's, stacked), so every tensor gains a leading (B,) axis.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
import torch

from marl_amod.scenario import City
from marl_amod.system import FleetSystem

Mode = Literal["centralised", "decentralised"]
WEIGHT_DIVISOR = 1000.0  # Gamma weights / this constant fit the env's Box(0, 1) almost surely (alpha stays < 100)


@dataclass
class Obs:
    """One decision point. x (N, F) global node features; own (N, F), nbrs (N, K, F), mask (N, K) local;
    ctx (3,) time of day (sin, cos) and step fraction. A :class:`BatchRollout` adds a leading (B,) axis."""

    x: torch.Tensor
    own: torch.Tensor | None = None
    nbrs: torch.Tensor | None = None
    mask: torch.Tensor | None = None
    ctx: torch.Tensor | None = None


class Rollout:
    """Drives one city episode by episode; ``step(weights)`` takes (N,) non-negative weights."""

    def __init__(self, city: City, mode: Mode = "centralised", lookahead: int = 6, arrivals_now: bool = False) -> None:
        from marl_amod import parallel_env
        from marl_amod.env.features import n_features
        from marl_amod.env.observations import LocalLayout, neighbour_table

        self.city, self.mode, self.lookahead, self.arrivals_now = city, mode, lookahead, arrivals_now
        self.layout = LocalLayout(neighbour_table(city), n_features(lookahead, arrivals_now))
        if mode == "decentralised":  # agents act on their own PettingZoo observations
            self.env = parallel_env(city, reward_mode="team", action_mode="weight", lookahead=lookahead, arrivals_now=arrivals_now)
            self.system = self.env.system
        else:
            self.env = None
            self.system = FleetSystem(city)
        self.done = False
        self.clipped = 0  # agent actions the env had to clip to its Box(0, 1)
        self.num_envs = 1

    def _obs_from_system(self) -> Obs:
        from marl_amod.env.features import node_features
        from marl_amod.env.observations import local_observations, split_local, time_features

        x = torch.as_tensor(node_features(self.system, self.lookahead, arrivals_now=self.arrivals_now))
        ctx = torch.as_tensor(time_features(self.city, self.system.t))
        if self.mode == "centralised":
            return Obs(x, ctx=ctx)
        local = local_observations(self.system, self.lookahead, layout=self.layout, arrivals_now=self.arrivals_now)
        own, _ctx, nbrs, mask = split_local(torch.as_tensor(local), x.shape[1])
        return Obs(x, own, nbrs, mask, ctx)

    def _obs_from_env(self, obs: dict[str, np.ndarray]) -> Obs:
        from marl_amod.env.observations import split_local

        stacked = torch.as_tensor(np.stack([obs[a] for a in self.agents]))  # (N, D)
        x = torch.as_tensor(self.env.graph()["x"])  # (N, F): only the centralised critic reads it
        own, ctx, nbrs, mask = split_local(stacked, x.shape[1])
        return Obs(x, own, nbrs, mask, ctx[0])

    def reset(self, seed: int | np.random.SeedSequence) -> Obs:
        self.done = False
        if self.env is not None:
            if isinstance(seed, np.random.SeedSequence):
                seed = int(seed.generate_state(1)[0])
            obs, _ = self.env.reset(seed=seed)
            self.agents = list(self.env.possible_agents)
            return self._obs_from_env(obs)
        self.system.reset(seed)
        return self._obs_from_system()

    def step(self, weights: np.ndarray) -> tuple[Obs, float]:
        """Apply (N,) weights; returns the next observation and the team reward (money)."""
        if self.env is not None:
            # The env's Box(0, 1) clips; weights are scale-free, so every agent divides by the same
            # constant. Counted so a clipped (law-changing) action never goes unnoticed.
            sent = np.asarray(weights, dtype=np.float64) / WEIGHT_DIVISOR
            self.clipped += int((sent > 1.0).sum())
            actions = {a: np.array([w], dtype=np.float32) for a, w in zip(self.agents, sent, strict=True)}
            obs, rewards, terms, truncs, _ = self.env.step(actions)
            reward = float(rewards[self.agents[0]])
            self.done = not self.env.agents
            if self.done:  # final obs is not used for bootstrapping past the horizon
                return self._obs_from_system(), reward
            return self._obs_from_env(obs), reward
        out = self.system.step(self.system.targets_from_weights(np.asarray(weights, dtype=np.float64)))
        self.done = self.system.done
        return self._obs_from_system(), out.reward


class BatchRollout:
    """B episodes of one city in lockstep; ``step(weights)`` takes (B, N) non-negative weights.

    Episode b of a reset at ``first`` is training episode ``first + b``: its demand is drawn from
    :func:`train_seed` exactly as :class:`Rollout` would draw it.
    """

    def __init__(self, city: City, mode: Mode = "centralised", lookahead: int = 6, num_envs: int = 16, arrivals_now: bool = False) -> None:
        from marl_amod.batch_system import BatchFleetSystem
        from marl_amod.env.vector import AmodVectorEnv

        self.city, self.mode, self.lookahead, self.num_envs, self.arrivals_now = city, mode, lookahead, num_envs, arrivals_now
        if mode == "decentralised":  # agents act on their own observations, as the ParallelEnv gives them
            self.env: AmodVectorEnv | None = AmodVectorEnv(
                city, num_envs, reward_mode="team", action_mode="weight", lookahead=lookahead, arrivals_now=arrivals_now
            )
            self.system = self.env.system
        else:
            self.env = None
            self.system = BatchFleetSystem(city, num_envs)
        self.done = False
        self.clipped = 0

    def _obs(self, local: np.ndarray | None = None) -> Obs:
        from marl_amod.env.features import state_features
        from marl_amod.env.observations import split_local, time_features

        sim = self.system.sim
        x = torch.as_tensor(state_features(self.city, sim.t, sim.idle, sim.arrivals, self.lookahead, arrivals_now=self.arrivals_now))  # (B, N, F)
        ctx = torch.as_tensor(time_features(self.city, sim.t)).expand(self.num_envs, -1)  # (B, 3)
        if local is None:
            return Obs(x, ctx=ctx)
        own, _ctx, nbrs, mask = split_local(torch.as_tensor(local), x.shape[-1])
        return Obs(x, own, nbrs, mask, ctx)

    def reset(self, seed: int, first_episode: int) -> Obs:
        """Start training episodes first_episode .. first_episode + B - 1 of run seed ``seed``."""
        seeds = [train_seed(seed, first_episode + b) for b in range(self.num_envs)]
        self.done = False
        if self.env is not None:  # the env takes integer seeds; Rollout derives them the same way
            obs, _ = self.env.reset(seed=[int(s.generate_state(1)[0]) for s in seeds])
            return self._obs(obs)
        self.system.reset(seeds)
        return self._obs()

    def step(self, weights: np.ndarray) -> tuple[Obs, np.ndarray]:
        """Apply (B, N) weights; returns the next observations and the team rewards (B,) (money)."""
        weights = np.asarray(weights, dtype=np.float64)
        if self.env is not None:
            sent = (weights / WEIGHT_DIVISOR).astype(np.float32)  # as Rollout: float32 actions of the Box, clipping counted
            self.clipped += int((sent > 1.0).sum())
            obs, rewards, _terms, truncs, _ = self.env.step(sent)
            self.done = bool(truncs.all())
            return self._obs(obs), rewards[:, 0]
        out = self.system.step(self.system.targets_from_weights(weights))
        self.done = self.system.done
        return self._obs(), out.reward


def train_seed(seed: int, episode: int) -> np.random.SeedSequence:
    """Training demand of episode k: never one of the evaluation streams (seed, k)."""
    return np.random.SeedSequence([seed, episode, 7919])


