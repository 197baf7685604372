"""AgileRL IPPO on marl_amod: the ParallelEnv through AgileRL's PettingZoo vector env, unmodified.

AgileRL groups agents by the prefix of their ids, so ``region_0 ... region_{N-1}`` share one
actor and one critic (parameter sharing) without configuration. The loop is AgileRL's own
on-policy loop (``agilerl.training.train_multi_agent_on_policy``) without its evolutionary
population, so one run is one agent. The learned actor is scored by ``marl_amod.evaluate``.

AgileRL pins pettingzoo 1.26.1 (the env passes PettingZoo's API tests there) and imports
``peft``, so it lives in its own environment (docs/ecosystem.md):

    python -m venv .venv-agilerl && . .venv-agilerl/bin/activate
    pip install "torch==2.13.0" && pip install agilerl peft "torch==2.13.0" marl-amod
    python examples/agilerl_ippo.py
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from agilerl.algorithms import IPPO
from agilerl.vector.pz_async_vec_env import AsyncPettingZooVecEnv

import marl_amod


@torch.no_grad()
def start_near_equal_distribution(actor: torch.nn.Module, std: float) -> None:
    """Every weight about 0.5 with small noise at the start, as the TorchRL MAPPO example does.

    AgileRL's Gaussian head starts at mean 0 with std >= 1 (``action_std_init`` is a log-std and
    must be >= 0): the env clips half the samples to weight 0 and the rest to random weights, far
    worse than equal distribution. Under weight actions only ratios matter, so a mean of 0.5 and a
    std of 0.1 is ED with a little exploration. The parameters are changed in place, so AgileRL's
    optimizer keeps them.
    """
    head = actor.head_net.wrapped.model
    out = head[-2] if isinstance(head[-1], torch.nn.Identity) else head[-1]  # the last Linear
    out.weight.mul_(0.1)
    out.bias.fill_(0.5)
    actor.head_net.log_std.fill_(float(np.log(std)))


def keep_action_dim(actor: torch.nn.Module) -> None:
    """Work around AgileRL 2.58's log-probs for one-dimensional Box actions (ours: ``Box(0, 1, (1,))``).

    ``IPPO.learn`` squeezes the (B, 1) minibatch of actions to (B,), and the Gaussian's log-prob
    then broadcasts the (B, 1) means against the (B,) actions and sums a B x B matrix: every sample
    gets the same log-prob, so the PPO ratio is meaningless (with a small std it overflows to NaN
    on the first update). Giving the action its dimension back fixes it; the instance is patched,
    AgileRL's code is not.
    """
    log_prob = actor.action_log_prob
    actor.action_log_prob = lambda action: log_prob(action.reshape(-1, 1) if action.dim() == 1 else action)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=60_000, help="env steps to train (all env copies together)")
    parser.add_argument("--time-limit", type=float, default=None, help="stop training after this many minutes")
    parser.add_argument("--envs", type=int, default=4, help="env copies in AgileRL's async vector env (worker processes)")
    parser.add_argument("--episodes-per-update", type=int, default=8, help="whole episodes per env copy between updates")
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--init-std", type=float, default=0.1, help="initial std of the Gaussian actor")
    parser.add_argument("--eval-episodes", type=int, default=10)
    args = parser.parse_args()
    torch.manual_seed(0)

    def make() -> marl_amod.env.AmodParallelEnv:
        return marl_amod.parallel_env(args.scenario, reward_scale="auto")

    vec = AsyncPettingZooVecEnv([make for _ in range(args.envs)])
    probe = make()
    agents = probe.possible_agents
    per_copy = max(1, min(probe.max_cycles * args.episodes_per_update, args.steps // args.envs))  # env steps per copy between updates
    agent = IPPO(
        observation_spaces=[probe.observation_space(a) for a in agents], action_spaces=[probe.action_space(a) for a in agents],
        agent_ids=agents, learn_step=per_copy * args.envs, batch_size=256, lr=args.lr, ent_coef=0.0, update_epochs=4,
    )  # fmt: skip
    for actor in agent.actors.values():  # one group, "region": every region shares this actor
        start_near_equal_distribution(actor, args.init_std)
        keep_action_dim(actor)
    start, done_steps = time.perf_counter(), 0
    obs, info = vec.reset(seed=1)
    while done_steps * args.envs < args.steps:
        if args.time_limit is not None and time.perf_counter() - start > 60 * args.time_limit:
            break
        states, actions, log_probs, rewards, dones, values = ({a: [] for a in agents} for _ in range(6))
        done = {a: np.zeros(args.envs) for a in agents}
        for _ in range(per_copy):
            action, log_prob, _, value = agent.get_action(obs=obs, infos=info)
            clipped = {a: np.clip(x, 0.0, 1.0) for a, x in action.items()}  # the env clips too; AgileRL's loop does
            next_obs, reward, term, trunc, info = vec.step(clipped)
            for a in obs:
                states[a].append(obs[a])
                actions[a].append(action[a])
                log_probs[a].append(log_prob[a])
                rewards[a].append(reward[a])
                values[a].append(value[a])
                dones[a].append(done[a])
            done = {a: np.logical_or(term[a], trunc[a]).astype(float) for a in term}
            obs = next_obs
        agent.learn((states, actions, log_probs, rewards, dones, values, obs, done))
        done_steps += per_copy
        team = float(np.mean(np.sum(rewards[agents[0]], axis=0)))
        print(f"{done_steps * args.envs:6d} env steps | {time.perf_counter() - start:6.1f} s | team reward per batch {team:.2f}", flush=True)
    vec.close()
    wall = time.perf_counter() - start

    actor = agent.actors["region"]

    @torch.no_grad()
    def ippo(o: dict[str, np.ndarray]) -> dict[str, np.ndarray]:  # the Gaussian's mean, clipped by the env
        x = torch.as_tensor(np.stack([o[a] for a in agents]), dtype=torch.float32)
        mean = actor.head_net.wrapped(actor.extract_features(x)).numpy()
        return {a: mean[i] for i, a in enumerate(agents)}

    ours = marl_amod.evaluate(ippo, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    ed = marl_amod.evaluate("equal-distribution", args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    print(
        f"{args.scenario}: AgileRL IPPO {ours['mean']:,.0f} ± {ours['std']:,.0f}  equal distribution {ed['mean']:,.0f} ± {ed['std']:,.0f}"
        f"  ({100 * (ours['mean'] / ed['mean'] - 1):+.1f}%), {done_steps * args.envs:,} env steps in {wall / 60:.1f} min"
    )


if __name__ == "__main__":
    main()
