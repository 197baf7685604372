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


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=19 * 200, help="env steps to train (per env copy)")
    parser.add_argument("--envs", type=int, default=2, help="env copies in AgileRL's async vector env")
    parser.add_argument("--eval-episodes", type=int, default=10)
    args = parser.parse_args()
    torch.manual_seed(0)

    def make() -> marl_amod.env.AmodParallelEnv:
        return marl_amod.parallel_env(args.scenario, reward_scale="auto")

    vec = AsyncPettingZooVecEnv([make for _ in range(args.envs)])
    probe = make()
    agents = probe.possible_agents
    learn_step = min(19 * 8, args.steps)  # env steps per copy between updates: whole episodes
    agent = IPPO(
        observation_spaces=[probe.observation_space(a) for a in agents], action_spaces=[probe.action_space(a) for a in agents],
        agent_ids=agents, learn_step=learn_step * args.envs, batch_size=256, lr=3e-4, action_std_init=0.3,
    )  # fmt: skip
    start, done_steps = time.perf_counter(), 0
    obs, info = vec.reset(seed=1)
    while done_steps < args.steps:
        states, actions, log_probs, rewards, dones, values = ({a: [] for a in agents} for _ in range(6))
        done = {a: np.zeros(args.envs) for a in agents}
        for _ in range(learn_step):
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
        done_steps += learn_step
        team = float(np.mean(np.sum(rewards[agents[0]], axis=0)))
        print(f"{done_steps * args.envs:6d} env steps | {time.perf_counter() - start:6.1f} s | team reward per batch {team:.2f}", flush=True)
    vec.close()
    wall = time.perf_counter() - start

    def ippo(o: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        batch = {a: x[None] for a, x in o.items()}
        agent.set_training_mode(False)
        action = agent.get_action(obs=batch)[0]
        return {a: np.clip(np.asarray(action[a])[0], 0.0, 1.0) for a in o}

    def equal_distribution(o: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        return {a: np.ones(1, dtype=np.float32) for a in o}

    ours = marl_amod.evaluate(ippo, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    ed = marl_amod.evaluate(equal_distribution, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    print(
        f"{args.scenario}: AgileRL IPPO {ours['mean']:,.0f} ± {ours['std']:,.0f}  equal distribution {ed['mean']:,.0f} ± {ed['std']:,.0f}"
        f"  ({100 * (ours['mean'] / ed['mean'] - 1):+.1f}%), {done_steps * args.envs:,} env steps in {wall / 60:.1f} min"
    )


if __name__ == "__main__":
    main()
