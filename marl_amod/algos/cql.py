"""Conservative Q-learning (Kumar et al. 2020) on SAC with the GNN actor and twin GNN critics.

Read top to bottom: Args, then ``train``. SAC's losses (:mod:`marl_amod.algos.sac`) plus a
penalty that pushes Q down on actions the data does not show and up on the logged ones:

    loss_Q = Bellman(SAC backup) + cql_alpha * (logsumexp_k Q(s, a_k) - log K - Q(s, a_data)),

a_k: ``n_actions`` draws from the uniform distribution on the simplex (Dir(1)) and as many from
the current policy at s (the CQL(H) penalty without importance weights). The actor maximises
min Q - alpha log pi; its first ``bc_steps`` updates are behaviour cloning instead (CORL's
warm start), so the critic's first, poor estimates do not drag it off the data.

Critics read the global graph; the actor is centralised or local (decentralised, per-agent
Gamma: :func:`marl_amod.algos.sac.policy_sample`). The horizon ends every return. The policy file
carries the twin Q critic the actor follows, so the policy can also play by it (``selection``:
:mod:`marl_amod.selection`).
"""

from __future__ import annotations

import copy
import math
from typing import Any

import torch
import torch.nn.functional as F
from pydantic import Field

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.algos.sac import policy_sample
from marl_amod.models import TwinQ, dirichlet


class Args(O.CriticArgs):
    hidden: int = Field(32, ge=1)
    """hidden units of the actor MLP"""
    critic_hidden: int = Field(128, ge=1)
    """hidden units of the twin Q critics"""
    lr_actor: float = Field(1e-4, gt=0)
    """Adam learning rate of the actor (after the BC warm start)"""
    lr_critic: float = Field(1e-3, gt=0)
    """Adam learning rate of the critics"""
    alpha: float = Field(0.01, ge=0)
    """entropy temperature of the SAC actor loss and backup"""
    cql_alpha: float = Field(1.0, ge=0)
    """weight of the conservative penalty (0: plain offline SAC)"""
    n_actions: int = Field(4, ge=1)
    """uniform and policy actions per state in the penalty's logsumexp (each)"""
    bc_steps: int = Field(1000, ge=0)
    """first actor updates that clone the logged action instead of maximising Q"""
    polyak: float = Field(0.995, ge=0, le=1)
    """target-network averaging factor"""
    run_dir: str = "runs/cql"
    """TensorBoard + CSV logs and the resumable training state"""

    def ignored_keys(self) -> dict[str, str]:
        return {**super().ignored_keys(), "central_critic": "CQL's critics always read the global graph",
                "actor_time": "CQL's policy samples read node features only (A2C, BC and IQL feed the actor the time context)"}  # fmt: skip


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Learn from the dataset with CQL; keep the best validation actor; write its card."""
    city, data, local, graph, gen = O.setup(args)
    n, k = city.n_regions, args.n_actions
    actor = C.make_actor(args, city)
    conv = "sage" if local else args.conv
    critic = TwinQ(C.run_features(args), args.critic_hidden, conv)
    critic_targ = copy.deepcopy(critic).requires_grad_(False)
    opt_a = torch.optim.Adam(actor.parameters(), lr=args.lr_actor)
    opt_c = torch.optim.Adam(critic.parameters(), lr=args.lr_critic)
    uniform = dirichlet(torch.ones(n))

    def update(b: O.Batch, step: int) -> dict[str, float]:
        bsz = b["x"].shape[0]
        # ---- twin Q: soft Bellman backup ----
        with torch.no_grad():
            y2, logp2 = policy_sample(actor, b, "next_", graph, local)
            q_next = torch.min(*critic_targ(b["next_x"], graph, y2))  # (B,)
            backup = b["reward"] + args.gamma * (1 - b["done"]) * (q_next - args.alpha * logp2)
            # ---- actions for the penalty: K uniform on the simplex, K from pi(.|s) ----
            rep = O.Batch({key: val.repeat_interleave(k, 0) for key, val in b.items()})  # (B*K, ...)
            y_pi, _ = policy_sample(actor, rep, "", graph, local)  # (B*K, N)
            y_rand = uniform.sample((bsz * k,))  # (B*K, N)
        q1, q2 = critic(b["x"], graph, b["action"])
        loss_bellman = F.mse_loss(q1, backup) + F.mse_loss(q2, backup)
        x_all = torch.cat([rep["x"], rep["x"]])  # (2*B*K, N, F)
        q1_all, q2_all = critic(x_all, graph, torch.cat([y_rand, y_pi]))  # (2*B*K,)
        penalty = 0.0
        for q_all, q_data in ((q1_all, q1), (q2_all, q2)):
            per_state = torch.cat([q_all[: bsz * k].view(bsz, k), q_all[bsz * k :].view(bsz, k)], 1)  # (B, 2K)
            penalty = penalty + (torch.logsumexp(per_state, 1) - math.log(2 * k) - q_data).mean()
        loss_q = loss_bellman + args.cql_alpha * penalty
        opt_c.zero_grad()
        loss_q.backward()
        torch.nn.utils.clip_grad_norm_(critic.parameters(), args.max_grad_norm)
        opt_c.step()
        # ---- actor: BC warm start, then min Q - alpha log pi (critics frozen) ----
        if step < args.bc_steps:
            loss_pi = O.imitation_loss(actor, b, graph, local, kind=args.imitation,
                                       shortfall=args.shortfall_weight, surplus=data.surplus).mean()  # fmt: skip
        else:
            critic.requires_grad_(False)
            y, logp = policy_sample(actor, b, "", graph, local)
            loss_pi = (args.alpha * logp - torch.min(*critic(b["x"], graph, y))).mean()
            critic.requires_grad_(True)
        opt_a.zero_grad()
        loss_pi.backward()
        torch.nn.utils.clip_grad_norm_(actor.parameters(), args.max_grad_norm)
        opt_a.step()
        with torch.no_grad():
            for p, pt in zip(critic.parameters(), critic_targ.parameters(), strict=True):
                pt.mul_(args.polyak).add_((1 - args.polyak) * p)
        return {"loss/q": loss_bellman.item(), "loss/cql": penalty.item(), "loss/policy": loss_pi.item()}

    parts = {"actor": actor, "critic": critic, "critic_targ": critic_targ, "opt_a": opt_a, "opt_c": opt_c}
    return O.fit(args, "cql", city, data, actor, update, parts, gen, resume=resume, progress=progress, config_path=config_path,
                 critic=(critic, args.critic_hidden, conv))  # fmt: skip
