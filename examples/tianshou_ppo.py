"""tianshou: its AEC ``PettingZooEnv`` takes ``marl_amod.env()``; its multi-agent PPO does not train on it unpatched.

What works: ``tianshou.env.PettingZooEnv(marl_amod.env(...))`` (reset, step, spaces) and
``MultiAgentOnPolicyAlgorithm`` with one PPO per region (here all sharing one actor and one
critic: parameter sharing); Gaussian samples below 0 are clipped by the env (since issue 18.1).
What breaks (tianshou 2.0.1): the first collection step. ``MultiAgentPolicy.forward`` strips
the ``Batch(agent_id, obs, mask)`` wrapper of agents without an action mask with
``hasattr(batch.obs_next, "obs")``, but the collector's forward batch has no ``obs_next``; the
attribute error is raised before ``hasattr`` can catch it. Every env without action masks (every
continuous-action env) hits it; tianshou's own multi-agent examples use masked discrete actions.
The script reports where it stops. See
docs/ecosystem.md for the patch this needs and the recommended route (TorchRL, BenchMARL, SB3).

    python -m venv .venv-tianshou && . .venv-tianshou/bin/activate
    pip install "torch==2.13.0" && pip install tianshou "torch==2.13.0" marl-amod
    python examples/tianshou_ppo.py
"""

from __future__ import annotations

import argparse
import traceback
from pathlib import Path

import numpy as np
import torch
from tianshou.algorithm import PPO
from tianshou.algorithm.modelfree.reinforce import ProbabilisticActorPolicy
from tianshou.algorithm.multiagent.marl import MultiAgentOnPolicyAlgorithm
from tianshou.algorithm.optim import AdamOptimizerFactory
from tianshou.data import Collector, VectorReplayBuffer
from tianshou.env import DummyVectorEnv, PettingZooEnv
from tianshou.utils.net.common import Net
from tianshou.utils.net.continuous import ContinuousActorProbabilistic, ContinuousCritic

import marl_amod


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="synthetic")
    parser.add_argument("--steps", type=int, default=19 * 16, help="agent steps to collect before the update")
    parser.add_argument("--eval-episodes", type=int, default=10)
    args = parser.parse_args()

    def make() -> PettingZooEnv:
        return PettingZooEnv(marl_amod.env(args.scenario, reward_scale="auto"))

    probe = make()
    obs_space = probe.observation_space
    obs_space = getattr(obs_space, "spaces", {}).get("observation", obs_space)
    act_space = probe.action_space
    net = Net(state_shape=obs_space.shape, hidden_sizes=[64, 64])
    actor = ContinuousActorProbabilistic(preprocess_net=net, action_shape=act_space.shape, unbounded=True)
    critic = ContinuousCritic(preprocess_net=Net(state_shape=obs_space.shape, hidden_sizes=[64, 64]))

    def dist(loc_scale: tuple[torch.Tensor, torch.Tensor]) -> torch.distributions.Distribution:
        loc, scale = loc_scale
        return torch.distributions.Independent(torch.distributions.Normal(loc, scale), 1)

    policy = ProbabilisticActorPolicy(actor=actor, dist_fn=dist, action_space=act_space, action_scaling=False, action_bound_method=None)
    algorithms = [PPO(policy=policy, critic=critic, optim=AdamOptimizerFactory(lr=3e-4)) for _ in probe.agents]  # shared modules
    marl = MultiAgentOnPolicyAlgorithm(algorithms=algorithms, env=probe)
    envs = DummyVectorEnv([make])
    try:
        collector = Collector(marl, envs, VectorReplayBuffer(args.steps, 1))
        collector.reset()
        stats = collector.collect(n_step=args.steps)
        print(f"collected {stats.n_collected_steps} agent steps from tianshou's PettingZooEnv")
        marl.update(buffer=collector.buffer, batch_size=64, repeat=1)
    except AttributeError as exc:  # the documented failure (tianshou 2.0.1): report it, do not hide it
        frames = traceback.extract_tb(exc.__traceback__)
        where = next((f for f in reversed(frames) if "multiagent" in f.filename), frames[-1])
        print(f"tianshou multi-agent PPO fails unpatched: {type(exc).__name__}: {exc} ({Path(where.filename).name}:{where.lineno}: {where.line})")
        return
    print("tianshou multi-agent PPO updated")

    def ppo(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        with torch.no_grad():
            x = torch.as_tensor(np.stack(list(obs.values())), dtype=torch.float32)
            loc = actor(x)[0][0].numpy()
        return {a: loc[i] for i, a in enumerate(obs)}

    score = marl_amod.evaluate(ppo, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    print(f"{args.scenario}: tianshou PPO {score['mean']:,.0f} ± {score['std']:,.0f}")


if __name__ == "__main__":
    main()
