"""Implicit Q-learning (Kostrikov et al. 2022) with the GNN actor and GNN critics.

Read top to bottom: Args, then ``train``. IQL never queries Q at actions outside the dataset:

* V(s) -> the tau-expectile of min Q_targ(s, a) over logged actions (tau > 0.5: an upper
  expectile, i.e. close to the best action the data shows in s);
* Q(s, a) -> r + gamma (1 - done) V(s') (twin Q critics, Polyak-averaged targets);
* actor: advantage-weighted regression, loss exp(beta (Q_targ(s, a) - V(s))) times the
  imitation loss of the logged action (:func:`marl_amod.algos.offline.imitation_loss`; the
  cross-entropy of the logged action under the policy's mean, in place of -log pi(a|s)), weights clipped at
  ``max_weight``: behaviour cloning that leans towards the better actions.

Critics read the global graph with the action as a node feature (as SAC's); the actor is the
paper's GNN (centralised) or the local one (decentralised, per-agent Gamma; see
:mod:`marl_amod.algos.offline`). The horizon ends every return (done = termination or truncation).
The policy file carries the target twin Q (what the advantage weights read), so the policy can
also play by it (``selection``: :mod:`marl_amod.selection`).
"""

from __future__ import annotations

import copy
from typing import Any

import torch
import torch.nn.functional as F
from pydantic import Field

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.models import GNNValueCritic, TwinQ


class Args(O.CriticArgs):
    hidden: int = Field(32, ge=1)
    """hidden units of the actor MLP"""
    critic_hidden: int = Field(128, ge=1)
    """hidden units of the Q and V critics"""
    lr_critic: float = Field(1e-3, gt=0)
    """Adam learning rate of the Q and V critics"""
    expectile: float = Field(0.7, gt=0, lt=1)
    """tau of the V regression (0.5: the mean, SARSA-like; higher: closer to the best logged action)"""
    beta: float = Field(3.0, ge=0)
    """inverse temperature of the advantage weights (0: behaviour cloning)"""
    max_weight: float = Field(100.0, gt=0)
    """clip of exp(beta * advantage)"""
    polyak: float = Field(0.995, ge=0, le=1)
    """target-network averaging factor"""
    run_dir: str = "runs/iql"
    """TensorBoard + CSV logs and the resumable training state"""

    def ignored_keys(self) -> dict[str, str]:
        return {**super().ignored_keys(), "central_critic": "IQL's critics always read the global graph"}


def expectile_loss(diff: torch.Tensor, tau: float) -> torch.Tensor:
    """Asymmetric L2: |tau - 1(diff < 0)| diff^2, averaged."""
    return (torch.abs(tau - (diff < 0).float()) * diff.pow(2)).mean()


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Learn from the dataset with IQL; keep the best validation actor; write its card."""
    city, data, local, graph, gen = O.setup(args)
    f = C.run_features(args)
    conv = "sage" if local else args.conv
    actor = C.make_actor(args, city)
    q = TwinQ(f, args.critic_hidden, conv)
    q_targ = copy.deepcopy(q).requires_grad_(False)
    v = GNNValueCritic(f, args.critic_hidden, conv)
    opt_a = torch.optim.Adam(actor.parameters(), lr=args.lr_actor)
    opt_q = torch.optim.Adam(q.parameters(), lr=args.lr_critic)
    opt_v = torch.optim.Adam(v.parameters(), lr=args.lr_critic)

    def step_on(opt: torch.optim.Optimizer, loss: torch.Tensor, net: torch.nn.Module) -> None:
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(net.parameters(), args.max_grad_norm)
        opt.step()

    def update(b: O.Batch, step: int) -> dict[str, float]:
        # ---- V: expectile of the target Q over the logged actions ----
        with torch.no_grad():
            q_min = torch.min(*q_targ(b["x"], graph, b["action"]))  # (B,)
        v_s = v(b["x"], graph)  # (B,)
        loss_v = expectile_loss(q_min - v_s, args.expectile)
        step_on(opt_v, loss_v, v)
        # ---- Q: one-step backup through V(s') (no action outside the data) ----
        with torch.no_grad():
            backup = b["reward"] + args.gamma * (1 - b["done"]) * v(b["next_x"], graph)
        q1, q2 = q(b["x"], graph, b["action"])
        loss_q = F.mse_loss(q1, backup) + F.mse_loss(q2, backup)
        step_on(opt_q, loss_q, q)
        # ---- actor: advantage-weighted log-likelihood of the logged action ----
        weight = torch.exp(args.beta * (q_min - v_s.detach())).clamp(max=args.max_weight)  # (B,)
        imitation = O.imitation_loss(actor, b, graph, local, args.actor_time, kind=args.imitation,
                                     shortfall=args.shortfall_weight, surplus=data.surplus)  # fmt: skip
        loss_pi = (weight * imitation).mean()
        step_on(opt_a, loss_pi, actor)
        with torch.no_grad():
            for p, pt in zip(q.parameters(), q_targ.parameters(), strict=True):
                pt.mul_(args.polyak).add_((1 - args.polyak) * p)
        return {"loss/v": loss_v.item(), "loss/q": loss_q.item(), "loss/policy": loss_pi.item(), "adv_weight": weight.mean().item()}

    parts = {"actor": actor, "q": q, "q_targ": q_targ, "v": v, "opt_a": opt_a, "opt_q": opt_q, "opt_v": opt_v}
    return O.fit(args, "iql", city, data, actor, update, parts, gen, resume=resume, progress=progress, config_path=config_path,
                 critic=(q_targ, args.critic_hidden, conv))  # fmt: skip
