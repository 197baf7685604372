"""Behaviour cloning: imitate the logged joint action with the Dirichlet policy.

Read top to bottom: Args, then ``train``. The loss is :func:`marl_amod.algos.offline.imitation_loss`
over minibatches of the dataset: the cross-entropy of the logged action under the Dirichlet mean
alpha / sum(alpha), which is what the deterministic policy plays, or (``imitation: l1``) the
absolute error of that mean's shares (:mod:`marl_amod.algos.offline` has the data, both modes and
the loop).
"""

from __future__ import annotations

from typing import Any

import torch
from pydantic import Field

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.errors import ConfigError


class Args(O.OfflineArgs):
    hidden: int = Field(32, ge=1)
    """hidden units of the actor MLP (the paper's A2C actor size)"""
    run_dir: str = "runs/bc"
    """TensorBoard + CSV logs and the resumable training state"""
    sink_margin: float = Field(0.0, ge=0)
    """vehicles added to the logged target of every region that receives vehicles, taken from the
    others (:func:`~marl_amod.algos.offline.sink_margin_targets`): the env floors the clone's share,
    and a planner's logged targets leave no margin under it (centralised runs only)"""

    def ignored_keys(self) -> dict[str, str]:
        return {**super().ignored_keys(), "central_critic": "BC has no critic", "gamma": "BC has no return", "critic_time": "BC has no critic"}


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Clone the dataset's behaviour policy; keep the best validation actor; write its card."""
    city, data, local, graph, gen = O.setup(args)
    if args.sink_margin:
        if local:
            raise ConfigError("sink_margin reshapes the global target shares: centralised runs only")
        data.tensors["action"] = O.sink_margin_targets(data.tensors["x"], data.tensors["action"], args.sink_margin)
    actor = C.make_actor(args, city)
    opt = torch.optim.Adam(actor.parameters(), lr=args.lr_actor)

    def update(b: O.Batch, step: int) -> dict[str, float]:
        loss = O.imitation_loss(actor, b, graph, local, args.actor_time, kind=args.imitation,
                                shortfall=args.shortfall_weight, surplus=data.surplus)  # fmt: skip
        loss = loss.mean()
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(actor.parameters(), args.max_grad_norm)
        opt.step()
        return {"loss/bc": loss.item()}

    return O.fit(args, "bc", city, data, actor, update, {"actor": actor, "opt": opt}, gen,
                 resume=resume, progress=progress, config_path=config_path)  # fmt: skip
