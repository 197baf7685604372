"""Advantage actor-critic with a Dirichlet policy over the desired vehicle distribution (paper, sec. 4).

Read top to bottom: Args, the policy's act/value functions for both modes, then ``train``.

Centralised: alpha = actor(x, edge_index) (N,), action y ~ Dir(alpha), log pi = log Dir(y).
Decentralised: alpha_i = actor.forward_local(o_i) per agent, g_i ~ Gamma(alpha_i, 1), each agent
sends g_i and the env normalises; the joint law of g/sum(g) is the same Dirichlet, and
log pi = sum_i log Gamma(g_i; alpha_i). Deterministic evaluation uses alpha / sum(alpha).

Per control step the reward is dispatch profit minus rebalancing cost, times ``reward_scale``.
Each update uses ``episodes_per_update`` whole episodes: discounted returns, advantage = return
- V(s), policy loss -log pi * advantage, critic loss smooth-L1, clipped gradients.

``num_envs`` > 1 collects those episodes ``num_envs`` at a time in lockstep on the batched
simulator, every forward pass one (B, N, F) batch on the dense graph path; with 1 (the default)
the run is the episode-at-a-time one the shipped policies were trained with.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator

from marl_amod.algos import common as C
from marl_amod.algos.rollout import Obs, train_seed
from marl_amod.checkpoints import check_torch_file
from marl_amod.errors import DataError
from marl_amod.models import GNNValueCritic, LocalValueCritic, dirichlet, gamma, gamma_log_prob
from marl_amod.models.gnn import Graph
from marl_amod.scenario import City, load_city


class Args(C.RunArgs):
    hidden: int = Field(32, ge=1)
    """hidden units of the actor and critic MLPs (the paper's A2C uses 32)"""
    episodes: int = Field(2000, ge=1)
    """training episodes"""
    episodes_per_update: int = Field(4, ge=1)
    """whole episodes per gradient step (more: less noisy advantages)"""
    lr_actor: float = Field(1e-3, gt=0)
    """Adam learning rate of the actor"""
    lr_critic: float = Field(1e-3, gt=0)
    """Adam learning rate of the critic"""
    normalize_returns: bool = True
    """standardise the batch's returns before computing advantages (as RL4AMOD's A2C)"""
    entropy_coef: float = Field(0.0, ge=0)
    """weight of the policy entropy bonus"""
    critic_warmup: int = Field(0, ge=0)
    """first updates that train the critic only: a warm-started actor (``init_actor``) is not
    pushed around by the advantages of a critic that has not learnt the values yet"""
    action_concentration: float = Field(1.0, gt=0)
    """multiplies the actor's concentrations when sampling training actions; the played policy,
    alpha / sum(alpha), is unchanged. Behaviour cloning fits the mean and leaves the total
    concentration free (Luxembourg's clone: ~8 over 10 regions; synthetic's MPC-Forecast clone ~14,
    where A2C from scratch settles near 280), so its samples scatter far from what it plays and A2C
    learns from actions it never takes; a larger value explores near the clone's mean"""
    kl_coef: float = Field(0.0, ge=0)
    """weight of KL(pi || pi_start) at the visited states, pi_start the frozen ``init_actor``: an
    RL update that refines a clone instead of walking away from it (the meso fine-tune from the
    clone lost ~250 per episode to ED without it); needs ``init_actor``"""
    concentration_cap: float | None = Field(None, gt=0)
    """cap on the Dirichlet's total concentration sum(alpha) when sampling (alpha scaled down to it;
    the mean, which evaluation plays, is unchanged): an offline clone is ten times as concentrated
    as a fresh actor (109 vs 9 on PROP's states), so without a cap its samples barely explore"""
    init_critic: str | None = None
    """a state file of this run's critic (``torch.save`` of its ``state_dict``) to start from instead of
    a fresh one: fine-tuning with a critic pre-trained on the offline dataset
    (:func:`marl_amod.finetune.pretrain_critic`)"""
    run_dir: str = "runs/a2c"
    """TensorBoard + CSV logs and the resumable training state"""

    @model_validator(mode="after")
    def _whole_batches(self) -> Args:
        if self.episodes_per_update % self.num_envs:
            raise ValueError(f"episodes_per_update ({self.episodes_per_update}) must be a multiple of num_envs ({self.num_envs})")
        if self.kl_coef and not self.init_actor:
            raise ValueError("kl_coef keeps the actor near its start: it needs init_actor")
        return self

    def ignored_keys(self) -> dict[str, str]:
        ignored = super().ignored_keys()
        if self.mode == "decentralised" and not self.central_critic:
            ignored["conv"] = "decentralised A2C with local critics uses the local actor only (SAGE)"
        return ignored


def act(alpha: torch.Tensor, mode: str) -> tuple[np.ndarray, torch.Tensor, torch.Tensor]:
    """Sample an action from concentrations alpha (..., N); returns (weights (..., N), log pi (...), entropy (...)).

    Centralised: y ~ Dir(alpha). Decentralised: every agent draws its own g_i ~ Gamma(alpha_i)
    (alpha_i from its own observation only). Leading axes are episodes in lockstep.
    """
    if mode == "centralised":
        dist = dirichlet(alpha)
        y = dist.sample().clamp_min(1e-6)
        y = y / y.sum(-1, keepdim=True)
        return y.numpy(), dist.log_prob(y), dist.entropy()
    g = gamma(alpha).sample().clamp_min(1e-8)  # each agent draws its own weight
    return g.numpy(), gamma_log_prob(g, alpha), gamma(alpha).entropy().sum(-1)


def capped(alpha: torch.Tensor, cap: float) -> torch.Tensor:
    """alpha (..., N) scaled so that sum(alpha) <= cap: the same mean, wider samples (the scale is
    differentiated through, so the policy gradient moves the mean while the total stays at the cap)."""
    return alpha * (cap / alpha.sum(-1, keepdim=True)).clamp(max=1.0)


def sampling_concentrations(alpha: torch.Tensor, args: Args) -> torch.Tensor:
    """The concentrations training actions are drawn from: alpha times ``action_concentration``, then
    capped at ``concentration_cap``; the mean, which evaluation plays, is alpha's either way."""
    alpha = alpha * args.action_concentration
    return alpha if args.concentration_cap is None else capped(alpha, args.concentration_cap)


def kl_to(alpha: torch.Tensor, ref: torch.Tensor, mode: str) -> torch.Tensor:
    """KL(pi_alpha || pi_ref) (...,) of the policies act() samples from: the Dirichlet (centralised)
    or the agents' independent Gammas (decentralised, summed over agents)."""
    if mode == "centralised":
        return torch.distributions.kl_divergence(dirichlet(alpha), dirichlet(ref))
    return torch.distributions.kl_divergence(gamma(alpha), gamma(ref)).sum(-1)


def concentrations(actor: torch.nn.Module, obs: Obs, graph: Graph, mode: str, time: bool = False) -> torch.Tensor:
    """alpha (..., N): the global graph (centralised; with the time context on every node when
    ``time``) or each agent's local observation alone."""
    if mode == "centralised":
        return actor(C.with_time(obs.x, obs.ctx, time), graph)
    return actor.forward_local(obs.own, obs.nbrs, obs.mask)


def value(critic: torch.nn.Module, obs: Obs, graph: Graph, local: bool, time: bool) -> torch.Tensor:
    """V(s): a scalar for one episode, (B,) for episodes in lockstep."""
    if local:
        own, nbrs = C.with_time(obs.own, obs.ctx, time), C.with_time(obs.nbrs, obs.ctx.unsqueeze(-2) if time else None, time)
        if own.dim() == 2:  # one episode
            return critic.forward_local(own[None], nbrs[None], obs.mask[None])[0]
        return critic.forward_local(own, nbrs, obs.mask)
    return critic(C.with_time(obs.x, obs.ctx, time), graph)


def discounted_returns(rewards: np.ndarray, gamma_: float) -> np.ndarray:
    """Returns (T, ...) of rewards (T, ...) (leading axis: time; then episodes), in float64 as the money is booked."""
    rewards = np.asarray(rewards, dtype=np.float64)
    out, g = np.empty_like(rewards), np.zeros(rewards.shape[1:])
    for t in range(len(rewards) - 1, -1, -1):
        g = rewards[t] + gamma_ * g
        out[t] = g
    return out


def make_critic(args: Args, city: City) -> torch.nn.Module:
    """The run's value critic: local per agent (decentralised without ``central_critic``) or the GNN on the global graph."""
    critic_in = C.critic_features(C.run_features(args), args)
    if args.mode == "decentralised" and not args.central_critic:
        return LocalValueCritic(critic_in, args.hidden)
    return GNNValueCritic(critic_in, args.hidden, args.conv, args.readout, city.n_regions if args.agent_id else 0)


def load_critic_state(critic: torch.nn.Module, path: str) -> None:
    """``init_critic``: the weights of a critic of this run's shape, or a DataError that says which differ."""
    check_torch_file(Path(path), "init_critic")  # missing, empty, text or damaged: said plainly
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 - e.g. a training state (pickled objects): not a critic's weights
        state = None
    if not isinstance(state, dict) or {"card", "state_dict"} <= set(state):  # nothing readable, or a policy file
        raise DataError(f"init_critic {path}: no critic state there (a torch.save of a critic's state_dict, not a policy or training state)")
    try:
        critic.load_state_dict(state)
    except RuntimeError as exc:
        raise DataError(f"init_critic {path} does not fit this run's critic (hidden, conv, readout, critic_time): {C.load_error(exc)}") from None


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Train, keep the best validation actor, write its policy card; returns the run summary."""
    torch.set_num_threads(args.threads)
    C.seed_everything(args.seed)
    city = load_city(args.scenario)
    rollout = C.make_rollout(city, args)
    graph = C.make_graph(city, args)
    local_critic = args.mode == "decentralised" and not args.central_critic
    actor = C.make_actor(args, city)
    critic = make_critic(args, city)
    C.warm_start(actor, args, city)  # offline -> online: start from a trained policy
    if args.init_critic:
        load_critic_state(critic, args.init_critic)
    start = copy.deepcopy(actor).requires_grad_(False) if args.init_actor else None  # before resume: the init actor
    opt_a = torch.optim.Adam(actor.parameters(), lr=args.lr_actor)
    opt_c = torch.optim.Adam(critic.parameters(), lr=args.lr_critic)

    start_ep, prior_wall, best = 0, 0.0, C.BestActor.of(actor)
    if args.init_actor and not resume:  # fine-tuning: the start is validated first, so the kept
        best.validate(actor, city, args)  # actor is never worse on the validation seeds than it
    if resume:
        st = C.load_state(resume, "a2c", args)
        C.restore(resume, st, actor=actor, critic=critic, opt_a=opt_a, opt_c=opt_c)
        start_ep, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
    log = C.Logger(args.run_dir, resume_from=start_ep if resume else None)
    timer = C.Timer(prior_wall)
    done_ep = ep = start_ep  # done_ep: episodes whose update has been applied

    def save() -> tuple[Path, int]:
        path = C.state_path(args)
        C.save_state(
            path, args, algorithm="a2c", actor=actor.state_dict(), critic=critic.state_dict(), opt_a=opt_a.state_dict(),
            opt_c=opt_c.state_dict(), episode=done_ep, best_val=best.value, best_actor=best.state, wall_s=timer(),
        )
        return path, done_ep

    book = C.EpisodeBook(args, "a2c", actor, city, rollout, log, timer, best, save, progress)
    with C.interruptible(save):
        while ep < args.episodes:
            # ---- collect a batch of whole episodes, num_envs at a time ----
            logps, values, returns, ents, kls, ep_rewards, ep_money = [], [], [], [], [], [], []
            for _ in range(args.episodes_per_update // rollout.num_envs):
                obs = rollout.reset(train_seed(args.seed, ep)) if rollout.num_envs == 1 else rollout.reset(args.seed, ep)
                steps: list[tuple[torch.Tensor, ...]] = []
                rewards = []
                while not rollout.done:
                    alpha = sampling_concentrations(concentrations(actor, obs, graph, args.mode, args.actor_time), args)
                    w, logp, ent = act(alpha, args.mode)
                    if start is not None:
                        kl = kl_to(alpha, sampling_concentrations(concentrations(start, obs, graph, args.mode, args.actor_time), args), args.mode)
                    else:
                        kl = torch.zeros_like(logp)
                    steps.append((logp, value(critic, obs, graph, local_critic, args.critic_time), ent, kl))
                    obs, r = rollout.step(w)
                    rewards.append(np.asarray(r, dtype=np.float64) * args.reward_scale)
                # (T, E) -> episode-major rows, as one episode after the other
                logp_t, v_t, ent_t, kl_t = (torch.stack(k).reshape(len(steps), -1).T.reshape(-1) for k in zip(*steps, strict=True))
                r_te = np.stack(rewards).reshape(len(rewards), -1)
                logps.append(logp_t), values.append(v_t), ents.append(ent_t), kls.append(kl_t)
                returns.append(torch.tensor(discounted_returns(r_te, args.gamma).T.reshape(-1), dtype=torch.float32))
                ep_rewards.extend(r_te.sum(0) / args.reward_scale)
                totals = rollout.system.sim.totals  # the episodes' books: revenue and rebalancing cost apart
                ep_money.append((totals.revenue.sum(-1), totals.rebalancing_cost.sum(-1)))
                ep += rollout.num_envs
            ret = torch.cat(returns)  # (E*T,)
            if args.normalize_returns:
                ret = (ret - ret.mean()) / (ret.std() + 1e-8)
            v = torch.cat(values)  # (E*T,)
            adv = ret - v.detach()

            # ---- one actor and one critic step ----
            kl = torch.cat(kls).mean()
            loss_pi = -(torch.cat(logps) * adv).mean() - args.entropy_coef * torch.cat(ents).mean() + args.kl_coef * kl
            loss_v = F.smooth_l1_loss(v, ret)
            if ep > args.critic_warmup * args.episodes_per_update:  # after the critic-only warm-up
                opt_a.zero_grad()
                loss_pi.backward()
                torch.nn.utils.clip_grad_norm_(actor.parameters(), args.max_grad_norm)
                opt_a.step()
            opt_c.zero_grad()
            loss_v.backward()
            torch.nn.utils.clip_grad_norm_(critic.parameters(), args.max_grad_norm)
            opt_c.step()
            done_ep = ep

            revenue, reb_cost = (float(np.mean(np.concatenate([np.atleast_1d(m[i]) for m in ep_money]))) for i in (0, 1))
            stats = {"train/episode_reward": float(np.mean(ep_rewards)), "train/revenue": revenue, "train/rebalancing_cost": reb_cost,
                     "loss/policy": loss_pi.item(), "loss/value": loss_v.item(), "loss/kl_start": kl.item()}  # fmt: skip
            # ---- periodic validation, best-actor selection, resumable state ----
            if book.close(ep, args.episodes_per_update, stats):
                break

    return book.finish(ep, config_path)
