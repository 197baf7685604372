"""tianshou PPO on marl_amod: its single-agent PPO on the joint view, one actor shared by every region.

tianshou's multi-agent PPO does not train on a continuous-action PettingZoo env (tianshou 2.0.1;
docs/ecosystem.md says where it breaks and why a patch is more than one line), so this recipe
uses :func:`marl_amod.integrations.joint.joint_env`: the ParallelEnv as one gymnasium env whose
observation stacks the N regions' observations (N, D) and whose action is the N weights. The
actor runs one small MLP on every row (parameter sharing, each region acts on its own
observation), the critic reads all rows (centralised), the reward is the team reward: MAPPO in
tianshou's single-agent machinery. The actor's Gaussian starts near equal distribution (every
weight about 0.5, std 0.1; the env clips samples into [0, 1]); the learned actor is scored by
``marl_amod.evaluate`` on the README's seeds.

    python -m venv .venv-tianshou && . .venv-tianshou/bin/activate
    pip install "torch==2.13.0" && pip install tianshou "torch==2.13.0" marl-amod
    python examples/tianshou_ppo.py
"""

from __future__ import annotations

import argparse
import time
from typing import Any

import numpy as np
import torch
from tianshou.algorithm import PPO
from tianshou.algorithm.modelfree.reinforce import ProbabilisticActorPolicy
from tianshou.algorithm.optim import AdamOptimizerFactory
from tianshou.data import Collector, VectorReplayBuffer
from tianshou.env import DummyVectorEnv
from tianshou.utils.net.common import MLP, Net
from tianshou.utils.net.continuous import AbstractContinuousActorProbabilistic, ContinuousCritic
from tianshou.utils.torch_utils import policy_within_training_step

import marl_amod
from marl_amod.integrations.joint import joint_env


class SharedRegionActor(AbstractContinuousActorProbabilistic):
    """(B, N, D) observations -> Gaussian (mean, std) of shape (B, N): one MLP applied to every region's row."""

    def __init__(self, n_regions: int, obs_dim: int, hidden: int, init_std: float) -> None:
        super().__init__(output_dim=n_regions)
        self.net = MLP(input_dim=obs_dim, output_dim=1, hidden_sizes=[hidden, hidden], flatten_input=False)
        with torch.no_grad():  # mean 0.5 + small: equal distribution with a little exploration
            last = [m for m in self.net.modules() if isinstance(m, torch.nn.Linear)][-1]
            last.weight.mul_(0.1)
            last.bias.zero_()
        self.log_std = torch.nn.Parameter(torch.full((1, 1), float(np.log(init_std))))

    def get_preprocess_net(self) -> torch.nn.Module:
        return torch.nn.Identity()

    def forward(self, obs: Any, state: Any = None, info: Any = None) -> tuple[tuple[torch.Tensor, torch.Tensor], Any]:
        mean = 0.5 + self.net(torch.as_tensor(obs, dtype=torch.float32)).squeeze(-1)  # (B, N)
        return (mean, self.log_std.exp().expand_as(mean)), state


def gaussian(mean_std: tuple[torch.Tensor, torch.Tensor]) -> torch.distributions.Distribution:
    """Independent Gaussians over the N weights: one joint log-prob per step."""
    return torch.distributions.Independent(torch.distributions.Normal(*mean_std), 1)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=60_000, help="env steps to train (all env copies together)")
    parser.add_argument("--time-limit", type=float, default=None, help="stop training after this many minutes")
    parser.add_argument("--envs", type=int, default=8, help="env copies in tianshou's DummyVectorEnv")
    parser.add_argument("--episodes-per-update", type=int, default=4, help="whole episodes per env copy between updates")
    parser.add_argument("--epochs", type=int, default=4, help="PPO passes over each batch")
    parser.add_argument("--minibatch", type=int, default=152, help="env steps per minibatch")
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--init-std", type=float, default=0.1, help="initial std of the Gaussian actor")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)

    def make() -> marl_amod.integrations.joint.JointEnv:
        return joint_env(args.scenario, reward_scale="auto")  # team rewards near [-1, 1]: PPO's defaults fit

    probe = make()
    n, obs_dim = probe.observation_space.shape
    actor = SharedRegionActor(n, obs_dim, hidden=64, init_std=args.init_std)
    critic = ContinuousCritic(preprocess_net=Net(state_shape=n * obs_dim, hidden_sizes=[128, 128]))  # all rows: centralised
    policy = ProbabilisticActorPolicy(
        actor=actor, dist_fn=gaussian, action_space=probe.action_space, action_scaling=False, action_bound_method=None
    )  # raw samples go to the env, which clips them into [0, 1]
    ppo = PPO(policy=policy, critic=critic, optim=AdamOptimizerFactory(lr=args.lr), ent_coef=0.0, max_grad_norm=1.0)

    envs = DummyVectorEnv([make for _ in range(args.envs)])
    envs.seed([args.seed + 1 + i for i in range(args.envs)])
    per_update = min(probe.parallel.max_cycles * args.episodes_per_update * args.envs, max(args.steps, args.envs))
    collector = Collector(ppo, envs, VectorReplayBuffer(-(-per_update // args.envs) * args.envs, args.envs))  # whole rows per env
    collector.reset()
    start, done_steps = time.perf_counter(), 0
    with policy_within_training_step(policy):  # tianshou's trainer does the same: sampled actions while training
        while done_steps < args.steps:
            if args.time_limit is not None and time.perf_counter() - start > 60 * args.time_limit:
                break
            stats = collector.collect(n_step=per_update)
            ppo.update(buffer=collector.buffer, batch_size=args.minibatch, repeat=args.epochs)
            collector.reset_buffer(keep_statistics=True)
            done_steps += stats.n_collected_steps
            returns = f"{stats.returns_stat.mean:.2f}" if stats.returns_stat is not None else "-"
            print(f"{done_steps:7d} env steps | {time.perf_counter() - start:6.1f} s | team return per episode {returns}", flush=True)
    envs.close()
    wall = time.perf_counter() - start

    @torch.no_grad()
    def shared_actor(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # the Gaussian's mean; the env clips
        mean = actor(np.stack([obs[a] for a in probe.agents])[None])[0][0][0].numpy()
        return {a: mean[i : i + 1] for i, a in enumerate(probe.agents)}

    ours = marl_amod.evaluate(shared_actor, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    ed = marl_amod.evaluate("equal-distribution", args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    print(
        f"{args.scenario}: tianshou PPO (joint view, shared actor) {ours['mean']:,.0f} ± {ours['std']:,.0f}  equal distribution "
        f"{ed['mean']:,.0f} ± {ed['std']:,.0f}  ({100 * (ours['mean'] / ed['mean'] - 1):+.1f}%), {done_steps:,} env steps in {wall / 60:.1f} min"
    )


if __name__ == "__main__":
    main()
