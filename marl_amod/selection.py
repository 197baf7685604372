"""Q-guided action selection for offline policies (EMaQ, Ghasemipour et al. 2021; SfBC/IDQL-style).

An offline actor fitted to a near-deterministic expert plays the mean of its Dirichlet; the twin
Q critic that IQL or CQL trained beside it can pick among actions near that mean instead. At
each step the policy draws ``candidates`` share vectors from Dir(c * mean) (c: ``concentration``),
adds the mean itself, scores all of them with the critic (min or mean of the twins) and plays
the best. The candidates come from the behaviour-fitted actor, so the critic is only asked about
actions near the data; with ``candidates: 0`` the policy is exactly the deterministic one.

Why Dir(c * mean) and not the actor's own Dirichlet: the offline imitation loss fits only the
mean (:func:`marl_amod.algos.offline.imitation_loss`), so the actor's total concentration is
whatever the descent left (about 11 on MPC-Forecast's states: draws 38 vehicles a region
apart); c sets the spread explicitly (std of share i: sqrt(m_i (1 - m_i) / (c + 1))).

Reproducible by seed: the draws at a step come from a generator seeded by ``seed`` and the bytes
of the step's node features, so the policy is a fixed function of what it observes (the same
action on the simulator and through the env's observations, in any episode order).

A policy file opts in with a card field ``selection: {candidates, concentration, seed, reduce}``
and carries the critic's weights beside the actor's (IQL and CQL policies do); a card that asks
for selection without them is refused with a :class:`~marl_amod.errors.DataError`.
"""

from __future__ import annotations

import zlib
from typing import Literal

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, Field

from marl_amod.models import TwinQ
from marl_amod.models.dense import city_graph
from marl_amod.scenario import City


class Selection(BaseModel):
    """How a policy picks its action among sampled candidates (the policy card's ``selection``)."""

    model_config = ConfigDict(extra="forbid")

    candidates: int = Field(ge=0)
    """Dirichlet draws scored beside the mean (0: the mean only, the deterministic policy)"""
    concentration: float = Field(gt=0)
    """total concentration c of the draws Dir(c * mean): larger is closer to the mean"""
    seed: int = 0
    """seeds the draws (with the step's features)"""
    reduce: Literal["min", "mean"] = "min"
    """how the twin critics' values combine into a candidate's score"""


class QSelector:
    """Plays the candidate with the highest Q: the mean of the actor's Dirichlet or one of
    ``selection.candidates`` draws around it, scored by a twin Q critic on the global graph."""

    def __init__(self, critic: TwinQ, city: City, selection: Selection) -> None:
        self.critic, self.selection = critic.eval(), selection
        self.graph = city_graph(city)

    def candidates(self, features: np.ndarray, mean: np.ndarray) -> np.ndarray:
        """(K + 1, N): the mean first, then K draws from Dir(c * mean) seeded by the features."""
        s = self.selection
        rng = np.random.default_rng([s.seed, zlib.crc32(np.ascontiguousarray(features, dtype=np.float32).tobytes())])
        draws = rng.dirichlet(np.maximum(s.concentration * mean, 1e-6), size=s.candidates) if s.candidates else np.empty((0, mean.size))
        return np.concatenate([mean[None], draws])

    @torch.no_grad()
    def scores(self, features: np.ndarray, candidates: np.ndarray) -> np.ndarray:
        """The critic's value (K + 1,) of every candidate at the state with node features (N, F)."""
        k = len(candidates)
        x = torch.as_tensor(features, dtype=torch.float32).expand(k, -1, -1)  # (K+1, N, F)
        q1, q2 = self.critic(x, self.graph, torch.as_tensor(candidates, dtype=torch.float32))
        q = torch.min(q1, q2) if self.selection.reduce == "min" else (q1 + q2) / 2
        return q.numpy()

    def __call__(self, features: np.ndarray, mean: np.ndarray) -> np.ndarray:
        """The action (N,) to play: the highest-scoring candidate (ties: the mean)."""
        if self.selection.candidates == 0:
            return mean
        cands = self.candidates(features, mean)
        return cands[int(np.argmax(self.scores(features, cands)))]
