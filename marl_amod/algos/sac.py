"""Soft actor-critic with a Dirichlet policy and twin GNN Q critics (paper, sec. 4; RL4AMOD's SAC).

Read top to bottom: Args, the replay buffer, the reparameterised policy sample for both modes,
the :class:`Learner` (networks, optimisers and one gradient update), then ``train``.

The action is the desired distribution y (N,) on the simplex. Centralised: y = rsample of
Dir(actor(x)). Decentralised: every agent draws g_i ~ Gamma(alpha_i(o_i), 1) (reparameterised)
from its local observation and y = g / sum(g), the same Dirichlet law; its log-density is the
Gamma one, sum_i log Gamma(g_i; alpha_i). The twin critics Q(s, y) always see the global graph
with y appended as a node feature (centralised training, decentralised execution).

Losses: Q -> r + gamma (1 - done) (min Q_targ(s', y') - a log pi(y'|s')), policy ->
a log pi(y|s) - min Q(s, y); Polyak-averaged targets; clipped gradients.

``num_envs`` > 1 steps that many episodes in lockstep on the batched simulator, adds their
transitions to the buffer together and runs ``updates_per_step`` gradient steps per transition
on the dense graph path (one matmul per layer for the whole (batch, N, F) sample), with the twin
critics as one :class:`~marl_amod.models.gnn.StackedTwinQ` (both critics' weights stacked: one
batched matmul per layer for the pair); ``critic_time`` gives the critics the time context;
``auto_entropy`` tunes the temperature. On these small graphs an update is dominated by per-op
overhead, so the update does each thing once: one replay gather, fused Adam, no critic weight
gradients in the policy step, the target side in inference mode. ``precision: bf16`` runs the update's network passes in bfloat16
(twice as fast at 256 hidden units on CPUs with AMX; :func:`~marl_amod.algos.common.autocast`).
"""

from __future__ import annotations

import contextlib
import copy
import math
import warnings
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator
from torch.distributions import Dirichlet

from marl_amod.algos import common as C
from marl_amod.algos.rollout import Obs, train_seed
from marl_amod.models import TwinQ, dirichlet, gamma, gamma_log_prob
from marl_amod.models.dense import DenseGraph
from marl_amod.models.gnn import Graph, StackedTwinQ
from marl_amod.scenario import City, load_city


class Args(C.RunArgs):
    hidden: int = Field(256, ge=1)
    """hidden units of the actor and critic MLPs (the paper's SAC uses 256)"""
    batch_size: int = Field(100, ge=1)
    """transitions per gradient step"""
    buffer_size: int = Field(100_000, ge=1)
    """replay capacity (transitions)"""
    warmup_steps: int = Field(1000, ge=0)
    """transitions collected before the first update (an untrained critic misleads the actor)"""
    updates_per_step: float = Field(1.0, gt=0)
    """gradient steps per transition (update-to-data ratio; fractions allowed: 0.25 is one step
    per four transitions, counted across the episodes of a batched run)"""
    lr_actor: float = Field(1e-4, gt=0)
    """Adam learning rate of the actor (1e-3 collapsed the policy within 100 episodes here)"""
    lr_critic: float = Field(1e-3, gt=0)
    """Adam learning rate of the twin critics"""
    lr_alpha: float = Field(1e-3, gt=0)
    """Adam learning rate of the entropy temperature (auto_entropy only)"""
    alpha: float = Field(0.3, gt=0)
    """entropy temperature (fixed unless auto_entropy); its effect scales inversely with reward_scale"""
    auto_entropy: bool = False
    """tune the temperature towards ``target_entropy``"""
    target_entropy: float | None = None
    """entropy the temperature is tuned towards, per region (None: -1 per region, i.e. -N)"""
    polyak: float = Field(0.995, ge=0, le=1)
    """target-network averaging factor"""
    precision: C.Precision = "fp32"
    """arithmetic of the gradient update's network passes. bf16: the actor's and critics' matmuls
    and activations in bfloat16 (``torch.autocast``; on CPUs with AMX or AVX512-BF16 units several
    times faster at 256 hidden units), with float32 weights, optimisers, Q heads, targets, losses
    and Dirichlet log-densities; acting and validation stay float32. Batched path only (num_envs > 1)"""
    eval_every: int = Field(50, ge=1)
    """episodes between validation evaluations"""
    run_dir: str = "runs/sac"
    """TensorBoard + CSV logs and the resumable training state"""

    @model_validator(mode="after")
    def _bf16_on_the_dense_path(self) -> Args:
        if self.precision != "fp32" and self.num_envs == 1:
            raise ValueError(f"precision {self.precision} needs the batched path (num_envs > 1); one episode at a time runs in fp32")
        return self

    def ignored_keys(self) -> dict[str, str]:
        ignored = {**super().ignored_keys(), "central_critic": "SAC's Q critics always read the global graph",
                   "actor_time": "SAC's actor reads node features only (A2C, BC and IQL feed the actor the time context)"}  # fmt: skip
        if self.mode == "decentralised":
            ignored["conv"] = "decentralised SAC uses the local actor and SAGE critics"
        if not self.auto_entropy:
            ignored["lr_alpha"] = "the temperature is fixed unless auto_entropy: true"
            ignored["target_entropy"] = "the temperature is fixed unless auto_entropy: true"
        return ignored


class Replay:
    """Fixed-size ring buffer of (obs, action y, reward, next obs, done).

    One (capacity, D) float tensor whose column blocks are the fields (``data[k]`` are views of
    it), so a sample is one row gather and every field of it a view: no per-field copies.
    """

    def __init__(self, capacity: int) -> None:
        self.capacity, self.size, self.ptr = capacity, 0, 0
        self.shapes: dict[str, tuple[int, ...]] = {}
        self.storage = torch.zeros(0, 0)
        self.data: dict[str, torch.Tensor] = {}

    def _allocate(self, shapes: dict[str, tuple[int, ...]]) -> None:
        self.shapes = dict(shapes)
        self.storage = torch.zeros(self.capacity, sum(math.prod(s) for s in self.shapes.values()))
        self.data = self._fields(self.storage)

    def _fields(self, rows: torch.Tensor) -> dict[str, torch.Tensor]:
        """The fields of rows (M, D) as views (M, *shape)."""
        out, col = {}, 0
        for k, shape in self.shapes.items():
            width = math.prod(shape)
            out[k] = rows[:, col : col + width].view(rows.shape[0], *shape)
            col += width
        return out

    def add(self, rows: int | None = None, **item: torch.Tensor) -> None:
        """One transition, or ``rows`` of them stacked on a leading axis (episodes in lockstep)."""
        if rows is None:
            item = {k: torch.as_tensor(v, dtype=torch.float32)[None] for k, v in item.items()}
            rows = 1
        item = {k: torch.as_tensor(v, dtype=torch.float32).expand(rows, *torch.as_tensor(v).shape[1:]) for k, v in item.items()}
        if not self.shapes:
            self._allocate({k: tuple(v.shape[1:]) for k, v in item.items()})
        idx = (self.ptr + torch.arange(rows)) % self.capacity
        for k, v in item.items():
            self.data[k][idx] = v
        self.ptr = (self.ptr + rows) % self.capacity
        self.size = min(self.size + rows, self.capacity)

    def state_dict(self) -> dict[str, Any]:
        """The filled part only, field by field (a resumed run continues with the same transitions)."""
        return {"capacity": self.capacity, "size": self.size, "ptr": self.ptr, "data": {k: v[: self.size].clone() for k, v in self.data.items()}}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        self.size, self.ptr = state["size"], state["ptr"]
        self.shapes, self.data = {}, {}
        if state["data"]:
            self._allocate({k: tuple(v.shape[1:]) for k, v in state["data"].items()})
            for k, v in state["data"].items():
                self.data[k][: self.size] = v

    def sample(self, batch: int, gen: torch.Generator) -> dict[str, torch.Tensor]:
        idx = torch.randint(0, self.size, (batch,), generator=gen)
        return self._fields(self.storage[idx])


def _obs_items(obs: Obs, prefix: str, local: bool, time: bool) -> dict[str, torch.Tensor]:
    items = {f"{prefix}x": obs.x}
    if time:
        items[f"{prefix}ctx"] = obs.ctx
    if local:
        items.update({f"{prefix}own": obs.own, f"{prefix}nbrs": obs.nbrs, f"{prefix}mask": obs.mask})
    return items


def policy_sample(
    actor, b: dict[str, torch.Tensor], prefix: str, edge_index: Graph, local: bool, amp: C.Autocast = contextlib.nullcontext,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Reparameterised action y (B, N) on the simplex and log pi (B,); the actor runs under
    ``amp``, its concentrations and the distribution in float32."""
    if local:
        with amp():
            alpha = actor.forward_local(b[f"{prefix}own"], b[f"{prefix}nbrs"], b[f"{prefix}mask"])  # (B, N)
        g = gamma(alpha).rsample().clamp_min(1e-8)
        return g / g.sum(-1, keepdim=True), gamma_log_prob(g, alpha)
    with amp():
        alpha = actor(b[f"{prefix}x"], edge_index)  # (B, N)
    # one distribution for both calls, unvalidated: alpha > 0 by construction, y on the simplex
    law = Dirichlet(alpha, validate_args=False)
    y = law.rsample().clamp_min(1e-6)
    y = y / y.sum(-1, keepdim=True)
    return y, law.log_prob(y)


def stack_twin_state(state: dict[str, Any], twin: TwinQ) -> dict[str, Any]:
    """A dense-path training state saved with TwinQ's two critics, in StackedTwinQ's layout.

    Critic, target and the critic optimiser's Adam moments are stacked the way
    :class:`StackedTwinQ` stacks weights (``twin`` is overwritten on the way), so a run started
    before the critics were stacked resumes with the same numbers.
    """
    state = dict(state)
    for key in ("critic", "critic_targ"):
        twin.load_state_dict(state[key])
        state[key] = StackedTwinQ(twin).state_dict()
    opt, params = state["opt_c"], list(twin.parameters())
    moments: dict[str, list[torch.Tensor]] = {}
    if opt["state"]:
        for m in ("exp_avg", "exp_avg_sq"):
            with torch.no_grad():
                for i, p in enumerate(params):
                    p.copy_(opt["state"][i][m])
            moments[m] = [t.detach().clone() for t in StackedTwinQ(twin).parameters()]
    n = len(list(StackedTwinQ(twin).parameters()))
    state["opt_c"] = {
        "state": {i: {"step": opt["state"][0]["step"].clone(), "exp_avg": moments["exp_avg"][i], "exp_avg_sq": moments["exp_avg_sq"][i]} for i in range(n)} if moments else {},
        "param_groups": [{**opt["param_groups"][0], "params": list(range(n)), "foreach": None, "fused": True}],
    }
    return state


def _no_mark(part: str) -> None:
    """The default part marker of :meth:`Learner.update`: nothing (benchmarks time the parts)."""


class Learner:
    """SAC's networks, optimisers and temperature, and one gradient step on a replay sample.

    Built in the order ``train`` always used (actor, then the critics: the same initial weights
    for a seed). :meth:`update` calls ``mark(part)`` after each part of the step, so
    ``benchmarks/sac_update.py`` times the real update part by part.
    """

    def __init__(self, args: Args, city: City, edge_index: Graph) -> None:
        self.args, self.edge_index = args, edge_index
        self.local = local = args.mode == "decentralised"
        n_features = C.run_features(args)
        self.actor = C.make_actor(args, city)  # (SAC's actor reads no time context: actor_time is not a SAC key)
        C.warm_start(self.actor, args, city)  # offline -> online: start from a trained policy
        self.twin = TwinQ(C.critic_features(n_features, args), args.hidden, "sage" if local else args.conv)
        # the dense path stacks the twin critics' weights: one batched matmul per layer for both
        self.critic = StackedTwinQ(self.twin) if isinstance(edge_index, DenseGraph) else self.twin
        self.critic_targ = copy.deepcopy(self.critic).requires_grad_(False)
        self.actor_params, self.critic_params = list(self.actor.parameters()), list(self.critic.parameters())
        self.targ_params = list(self.critic_targ.parameters())
        self.opt_a = torch.optim.Adam(self.actor_params, lr=args.lr_actor, fused=True)  # one kernel per step for all tensors
        self.opt_c = torch.optim.Adam(self.critic_params, lr=args.lr_critic, fused=True)
        self.log_alpha = torch.tensor(float(np.log(args.alpha)), requires_grad=True)
        self.opt_alpha = torch.optim.Adam([self.log_alpha], lr=args.lr_alpha)
        self.target_entropy = (-1.0 if args.target_entropy is None else args.target_entropy) * city.n_regions
        self.amp = C.autocast(args.precision)

    def update(self, b: dict[str, torch.Tensor], mark: Callable[[str], None] = _no_mark) -> dict[str, torch.Tensor]:
        """One critic and one actor step (and the temperature's with auto_entropy) on the sample ``b``."""
        args, actor, critic, edge_index, local, amp = self.args, self.actor, self.critic, self.edge_index, self.local, self.amp
        a = self.log_alpha.detach().exp()
        # the policy loss's actions, then the target's next actions without a graph (the actor does
        # not change in between; one pass over both halves ran the backward over both, 5-10% slower)
        # (inference mode: no autograd bookkeeping at all; its tensors cannot be saved for a
        # backward, so the Bellman target leaves it as a copy)
        y, logp = policy_sample(actor, b, "", edge_index, local, amp)
        with torch.inference_mode():
            y2, logp2 = policy_sample(actor, b, "next_", edge_index, local, amp)
        mark("actor")
        # ---- twin Q regression towards the soft Bellman target ----
        with torch.inference_mode():
            with amp():  # (the critics' Q heads are float32 under autocast)
                q_targ = torch.min(*self.critic_targ(C.with_time(b["next_x"], b.get("next_ctx"), args.critic_time), edge_index, y2))  # (B,)
            backup = b["reward"] + args.gamma * (1 - b["done"]) * (q_targ - a * logp2)
        backup = backup.clone()  # (B,)
        mark("target critics")
        x = C.with_time(b["x"], b.get("ctx"), args.critic_time)  # (B, N, F [+ 3])
        with amp():
            q1, q2 = critic(x, edge_index, b["action"])
        loss_q = F.mse_loss(q1, backup) + F.mse_loss(q2, backup)
        self.opt_c.zero_grad()
        loss_q.backward()
        mark("critic loss")
        torch.nn.utils.clip_grad_norm_(self.critic_params, args.max_grad_norm, foreach=True)
        self.opt_c.step()
        mark("critic step")
        # ---- policy: maximise min Q minus entropy cost (gradients reach the actor only) ----
        with amp():
            q_pi = torch.min(*critic(x, edge_index, y))
        loss_pi = (a * logp - q_pi).mean()
        self.opt_a.zero_grad()
        loss_pi.backward(inputs=self.actor_params)  # no critic weight gradients computed
        mark("policy loss")
        torch.nn.utils.clip_grad_norm_(self.actor_params, args.max_grad_norm, foreach=True)
        self.opt_a.step()
        if args.auto_entropy:
            loss_alpha = -(self.log_alpha * (logp.detach() + self.target_entropy)).mean()
            self.opt_alpha.zero_grad()
            loss_alpha.backward()
            self.opt_alpha.step()
        with torch.no_grad():  # Polyak averaging: targ <- polyak targ + (1 - polyak) critic
            torch._foreach_lerp_(self.targ_params, self.critic_params, 1 - args.polyak)
        mark("actor step, Polyak")
        return {"loss/q": loss_q.detach(), "loss/policy": loss_pi.detach(), "alpha": a}  # read once per episode


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Train, keep the best validation actor, write its policy card; returns the run summary."""
    torch.set_num_threads(args.threads)
    C.retain_freed_memory()  # the update's activations are reused, not faulted in anew each step
    C.seed_everything(args.seed)
    gen = torch.Generator().manual_seed(args.seed)
    city = load_city(args.scenario)
    local = args.mode == "decentralised"
    rollout = C.make_rollout(city, args)
    edge_index = C.make_graph(city, args)
    learner = Learner(args, city, edge_index)
    actor, critic, critic_targ, twin = learner.actor, learner.critic, learner.critic_targ, learner.twin
    opt_a, opt_c, opt_alpha, log_alpha = learner.opt_a, learner.opt_c, learner.opt_alpha, learner.log_alpha
    buffer = Replay(args.buffer_size)

    transitions = args.episodes * (city.horizon - 1)  # one per control step of every episode
    if args.warmup_steps >= transitions:  # a smoke test may mean it; a real run would ship its untrained start
        warnings.warn(f"warmup_steps ({args.warmup_steps}) is at least the run's {transitions} transitions ({args.episodes} episodes x "
                      f"{city.horizon - 1} steps on {city.name}): SAC will make no update; lower warmup_steps or run more episodes",
                      stacklevel=2)  # fmt: skip
    start_ep, prior_wall, n_steps, credit, best = 0, 0.0, 0, 0.0, C.BestActor.of(actor)
    if args.init_actor and not resume:  # fine-tuning: the start is validated first, so the kept actor is
        best.validate(actor, city, args)  # never worse on the validation seeds than the one it began from (as A2C)
    if resume:
        st = C.load_state(resume, "sac", args)
        if critic is not twin and "q1.value.out.weight" in st["critic"]:
            st = stack_twin_state(st, twin)  # saved before the critics were stacked
        C.restore(resume, st, actor=actor, critic=critic, critic_targ=critic_targ, opt_a=opt_a, opt_c=opt_c, opt_alpha=opt_alpha)
        start_ep, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
        log_alpha.data.fill_(st["log_alpha"])
        buffer.load_state_dict(st["replay"])
        gen.set_state(st["gen"])
        n_steps, credit = st["n_steps"], st.get("credit", 0.0)
    log = C.Logger(args.run_dir, resume_from=start_ep if resume else None)
    timer = C.Timer(prior_wall)
    ep = start_ep

    def save() -> tuple[Path, int]:
        path = C.state_path(args)
        C.save_state(
            path, args, algorithm="sac", actor=actor.state_dict(), critic=critic.state_dict(), critic_targ=critic_targ.state_dict(),
            opt_a=opt_a.state_dict(), opt_c=opt_c.state_dict(), opt_alpha=opt_alpha.state_dict(), log_alpha=log_alpha.item(),
            replay=buffer.state_dict(), gen=gen.get_state(), n_steps=n_steps, credit=credit, episode=ep, best_val=best.value,
            best_actor=best.state, wall_s=timer(),
        )
        return path, ep

    book = C.EpisodeBook(args, "sac", actor, city, rollout, log, timer, best, save, progress)
    with C.interruptible(save):
        while ep < args.episodes:
            # B = rollout.num_envs episodes in lockstep (1: the episode-at-a-time run)
            obs = rollout.reset(train_seed(args.seed, ep)) if rollout.num_envs == 1 else rollout.reset(args.seed, ep)
            ep_reward, last = 0.0, {}
            while not rollout.done:
                with torch.no_grad():
                    if local:
                        alpha_i = actor.forward_local(obs.own, obs.nbrs, obs.mask)  # (..., N), each row from its own obs
                        w = gamma(alpha_i).sample().clamp_min(1e-8)  # agents' Gamma weights
                        y = w / w.sum(-1, keepdim=True)
                    else:
                        y = dirichlet(actor(obs.x, edge_index)).sample().clamp_min(1e-6)
                        y = w = y / y.sum(-1, keepdim=True)
                nxt, r = rollout.step(w.numpy())
                ep_reward = ep_reward + r
                rows = None if rollout.num_envs == 1 else rollout.num_envs
                buffer.add(rows, **_obs_items(obs, "", local, args.critic_time), action=y, reward=torch.as_tensor(r * args.reward_scale),
                           done=torch.tensor(float(rollout.done)), **_obs_items(nxt, "next_", local, args.critic_time))
                obs = nxt
                n_steps += rollout.num_envs
                if buffer.size >= max(args.warmup_steps, args.batch_size):
                    credit += args.updates_per_step * rollout.num_envs
                    while credit >= 1:
                        last = learner.update(buffer.sample(args.batch_size, gen))
                        credit -= 1
            ep += rollout.num_envs
            stats = {k: float(v) for k, v in last.items()}
            stats["train/episode_reward"] = float(np.mean(ep_reward))
            if book.close(ep, rollout.num_envs, stats):
                break

    return book.finish(ep, config_path)
