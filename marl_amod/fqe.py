"""Fitted Q evaluation: a policy's episode profit estimated from a dataset alone, with no env episode.

Why: an offline run that keeps its last actor (``keep: last``) is offline RL proper, but choosing
*which* run or checkpoint to ship still took validation episodes in the env (``keep: best``). FQE
(Le, Voloshin and Yue 2019) scores a policy from the logged transitions: it regresses a critic on

    Q(s, a) <- r + (1 - done) Q_targ(s', pi(s'))

with the policy's own (deterministic: the Dirichlet mean, as evaluation plays) action at the next
state, and reads the estimate as the mean of Q(s0, pi(s0)) over the dataset's first states. The
episode is finite and ``done`` ends each, so no discount is needed and the estimate is in money: the
profit of the policy's decisions (the first dispatch, before any decision, is the same for every
policy and not included). The critic reads the time values beside the node features, since what
is left to earn depends on the steps left.

The policy's actions are computed once for every logged state (they do not change while Q is
fitted), so an FQE update costs one critic regression step. How well the estimates rank policies on
the benchmark's datasets is measured by ``benchmarks/offline_fqe.py`` (docs/offline).
"""

from __future__ import annotations

import copy
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.datasets import OfflineDataset
from marl_amod.errors import DataError
from marl_amod.models import GNNQCritic
from marl_amod.models.dense import DenseGraph, city_graph
from marl_amod.scenario import City, load_city

REWARD_SCALE = 1e-3  # a step earns a few thousand in Brooklyn; the critic regresses thousands of $
CONVERGED_WITHIN = 0.1  # the behaviour's own estimate this close to its logged return (relative), or the fits are too short


@dataclass(frozen=True)
class FQESettings:
    """How the critic is fitted (the defaults are what ``benchmarks/offline_fqe.py`` measured)."""

    updates: int = 3000
    batch_size: int = 256
    hidden: int = 128
    lr: float = 1e-3
    polyak: float = 0.99
    seed: int = 0


@dataclass(frozen=True)
class Transitions:
    """What FQE reads: the logged states with their time values (x, next_x: (T, N, F + 3)), the logged
    action on the simplex (T, N), the team reward in money (T,), done (T,), the policy's action at
    every next state (T, N), and the first states of the episodes with the policy's action there."""

    x: torch.Tensor
    action: torch.Tensor
    reward: torch.Tensor
    done: torch.Tensor
    next_x: torch.Tensor
    next_action: torch.Tensor
    start_x: torch.Tensor
    start_action: torch.Tensor


@dataclass(frozen=True)
class Estimate:
    """FQE's estimate of a policy's episode profit (money) and what it rests on."""

    profit: float
    per_start: np.ndarray  # Q(s0, pi(s0)) of each logged episode's first state, money
    final_loss: float  # the last updates' mean squared Bellman error, in money^2 x REWARD_SCALE^2

    def to_dict(self) -> dict[str, Any]:
        return {"profit": self.profit, "profit_std_over_starts": float(self.per_start.std()), "episodes": len(self.per_start),
                "final_loss": self.final_loss}  # fmt: skip


def fit(t: Transitions, graph: DenseGraph, settings: FQESettings = FQESettings()) -> Estimate:
    """Fit Q^pi on the transitions and read its value at the first states (:class:`Estimate`)."""
    gen = torch.Generator().manual_seed(settings.seed)
    torch.manual_seed(settings.seed)
    q = GNNQCritic(t.x.shape[-1], settings.hidden, "sage")
    q_targ = copy.deepcopy(q).requires_grad_(False)
    opt = torch.optim.Adam(q.parameters(), lr=settings.lr)
    reward, losses = t.reward * REWARD_SCALE, []
    for _ in range(settings.updates):
        idx = torch.randint(0, len(reward), (settings.batch_size,), generator=gen)
        with torch.no_grad():
            backup = reward[idx] + (1 - t.done[idx]) * q_targ(t.next_x[idx], graph, t.next_action[idx])
        loss = F.mse_loss(q(t.x[idx], graph, t.action[idx]), backup)
        opt.zero_grad()
        loss.backward()
        opt.step()
        losses.append(loss.item())
        with torch.no_grad():
            for p, pt in zip(q.parameters(), q_targ.parameters(), strict=True):
                pt.mul_(settings.polyak).add_((1 - settings.polyak) * p)
    with torch.no_grad():
        per_start = (q(t.start_x, graph, t.start_action) / REWARD_SCALE).numpy().astype(np.float64)
    return Estimate(float(per_start.mean()), per_start, float(np.mean(losses[-100:])))


def transitions(dataset: OfflineDataset, next_action: torch.Tensor, start_action: torch.Tensor) -> Transitions:
    """The dataset's transitions for a policy whose actions at the next states and at the episodes'
    first states are given (one row per logged transition, one per first state: :func:`first_rows`)."""
    view = dataset.global_view()
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    x, next_x = C.with_time(t(view["x"]), t(view["ctx"]), True), C.with_time(t(view["next_x"]), t(view["next_ctx"]), True)
    starts = first_rows(dataset)
    return Transitions(x, t(view["action"]), t(view["reward"]), t(view["done"]), next_x, next_action, x[starts], start_action)


def first_rows(dataset: OfflineDataset) -> np.ndarray:
    """The rows of each episode's first decision (step 0)."""
    rows = np.flatnonzero(np.asarray(dataset.step_ids) == 0)
    if not len(rows):
        raise DataError("the dataset holds no episode's first step (step_ids 0): FQE reads the policy's value there")
    return rows


def behaviour_actions(dataset: OfflineDataset) -> tuple[torch.Tensor, torch.Tensor]:
    """The logged policy's own actions at every next state and first state: what FQE of the behaviour
    itself reads, whose estimate the logged returns (:func:`logged_returns`) check. A next state that
    ends its episode gets zeros (``done`` drops it)."""
    action = torch.as_tensor(dataset.global_view()["action"], dtype=torch.float32)
    episode, step = np.asarray(dataset.episode_ids), np.asarray(dataset.step_ids)
    row_of = {(int(e), int(k)): i for i, (e, k) in enumerate(zip(episode, step, strict=True))}
    following = np.array([row_of.get((int(e), int(k) + 1), -1) for e, k in zip(episode, step, strict=True)])
    next_action = torch.where(torch.as_tensor(following >= 0)[:, None], action[np.maximum(following, 0)], torch.zeros_like(action))
    return next_action, action[first_rows(dataset)]


def logged_returns(dataset: OfflineDataset) -> np.ndarray:
    """Each logged episode's sum of team rewards (money): the behaviour's own return, as FQE counts it."""
    episodes, inverse = np.unique(np.asarray(dataset.episode_ids), return_inverse=True)
    return np.bincount(inverse, weights=np.asarray(dataset.team_rewards, dtype=np.float64), minlength=len(episodes))


def policy_actions(path: str | Path, dataset: OfflineDataset, dataset_path: str | Path, city: City) -> tuple[torch.Tensor, torch.Tensor]:
    """The deterministic action (the Dirichlet mean, on the simplex) of the policy file ``path`` at
    every next state of the dataset and at every episode's first state, from the view its actor
    reads (the global graph, with the time values if it was trained with them, or each agent's
    own observation)."""
    from marl_amod.checkpoints import load_actor

    actor, card = load_actor(path, city)
    args = O.OfflineArgs(scenario=city.name, dataset=str(dataset_path), lookahead=card["lookahead"],
                         arrivals_now=bool(card.get("arrivals_now")), mode=card.get("mode", "centralised"))  # fmt: skip
    data = O.Data(args, city, loaded=dataset, reader="policy")
    local, time = args.mode == "decentralised", bool(card.get("time_context"))
    graph = city_graph(city)
    batch = O.Batch(data.tensors)
    with torch.no_grad():
        mean = lambda prefix: F.normalize(O.concentrations(actor, batch, graph, local, prefix, time), p=1, dim=-1)  # noqa: E731
        return mean("next_"), mean("")[torch.as_tensor(first_rows(dataset))]


def estimate(policy: str | Path | None, dataset_path: str | Path, city: City | str | None = None,
             settings: FQESettings = FQESettings(), loaded: OfflineDataset | None = None) -> Estimate:  # fmt: skip
    """FQE's estimate of the episode profit of the policy file ``policy`` (None: the logged behaviour
    itself) from the dataset ``dataset_path`` (``loaded``: already read, as a caller scoring several
    policies on it has it), on ``city`` (default: the dataset's scenario by name)."""
    dataset = loaded if loaded is not None else OfflineDataset.load(dataset_path)
    city = city if isinstance(city, City) else load_city(city or dataset.meta["scenario"])
    O.check_fits(dataset, dataset_path, city)  # the behaviour's estimate reads no policy: the city is checked here
    actions = behaviour_actions(dataset) if policy is None else policy_actions(policy, dataset, dataset_path, city)
    return fit(transitions(dataset, *actions), city_graph(city), settings)
