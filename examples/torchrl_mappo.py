"""MAPPO with TorchRL: one shared actor on local observations, a centralised critic, team reward.

``marl_amod.integrations.torchrl.torchrl_vector_env`` is a TorchRL ``EnvBase`` over B episodes
stepped together (batch size (B,), keys ``("agents", "observation")`` (B, N, D),
``("agents", "action")`` (B, N, 1) in [0, 1], ``("agents", "reward")``), about ten times the
throughput of TorchRL's ``PettingZooWrapper`` around one ParallelEnv (which works too, and groups
the agents as ``"region"``). The actor is a ``MultiAgentMLP`` shared by every region (a TanhNormal
squashed into [0, 1]); the critic sees every region's observation (``centralized=True``), which
makes it MAPPO (``--ippo``: each region's own). The learned policy is then scored by
``marl_amod.evaluate`` on the README's seeds, next to equal distribution (every region weight 1).
Measured numbers: docs/ecosystem.md.

    pip install "marl-amod[torchrl]"
    python examples/torchrl_mappo.py                      # nyc_brooklyn needs the data (MARL_AMOD_DATA)
    python examples/torchrl_mappo.py --scenario synthetic
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import torch
from tensordict import TensorDict
from tensordict.nn import NormalParamExtractor, TensorDictModule
from torch import nn
from torchrl.envs.utils import ExplorationType, set_exploration_type
from torchrl.modules import MultiAgentMLP, ProbabilisticActor, TanhNormal
from torchrl.objectives import ClipPPOLoss, ValueEstimators

import marl_amod
from marl_amod.integrations.torchrl import torchrl_vector_env

GROUP = "agents"  # the batched env's one group: every region


def build(n_agents: int, obs_dim: int, hidden: int, centralised: bool, init_scale: float) -> tuple[ProbabilisticActor, TensorDictModule]:
    """Shared-parameter actor (local observations) and critic (all observations when centralised).

    The actor starts near equal distribution (every weight about 0.5) with small noise: under weight
    actions only the ratios matter, and wide noise (weights all over [0, 1]) is far worse than ED.
    """
    actor_net = nn.Sequential(
        MultiAgentMLP(obs_dim, 2, n_agents, centralized=False, share_params=True, depth=2, num_cells=hidden),
        NormalParamExtractor(scale_mapping=f"biased_softplus_{init_scale}"),  # (loc, scale > 0), scale starts at init_scale
    )
    actor = ProbabilisticActor(
        TensorDictModule(actor_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "loc"), (GROUP, "scale")]),
        in_keys=[(GROUP, "loc"), (GROUP, "scale")],
        out_keys=[(GROUP, "action")],
        distribution_class=TanhNormal,
        distribution_kwargs={"low": 0.0, "high": 1.0},
        return_log_prob=True,
    )
    critic_net = MultiAgentMLP(obs_dim, 1, n_agents, centralized=centralised, share_params=True, depth=2, num_cells=hidden)
    critic = TensorDictModule(critic_net, in_keys=[(GROUP, "observation")], out_keys=[(GROUP, "state_value")])
    return actor, critic


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="nyc_brooklyn")
    parser.add_argument("--steps", type=int, default=200_000, help="env steps to train (one step of one episode, all regions)")
    parser.add_argument("--envs", type=int, default=32, help="episodes stepped together; one PPO batch = one episode of each")
    parser.add_argument("--epochs", type=int, default=4, help="PPO epochs per batch")
    parser.add_argument("--minibatch", type=int, default=152, help="env steps per minibatch")
    parser.add_argument("--hidden", type=int, default=64)
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--entropy", type=float, default=0.0, help="entropy bonus coefficient")
    parser.add_argument("--init-scale", type=float, default=0.3, help="initial std of the actor (before the tanh)")
    parser.add_argument("--time-limit", type=float, default=9.0, help="stop training after this many minutes")
    parser.add_argument("--ippo", action="store_true", help="each region's critic sees its own observation (IPPO)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    torch.manual_seed(args.seed)
    torch.set_num_threads(1)  # small networks: more threads only contend with the env for the cores

    # reward_scale="auto": team rewards near [-1, 1], so PPO's defaults fit without reward normalisation
    env = torchrl_vector_env(args.scenario, num_envs=args.envs, reward_scale="auto")
    env.set_seed(10_000 + args.seed)  # training episodes; evaluation below draws its own (seed, k) streams
    n_agents, obs_dim = env.observation_spec[GROUP, "observation"].shape[1:]
    actor, critic = build(n_agents, obs_dim, args.hidden, centralised=not args.ippo, init_scale=args.init_scale)

    loss = ClipPPOLoss(
        actor, critic, clip_epsilon=0.2, entropy_coeff=args.entropy, normalize_advantage=True, normalize_advantage_exclude_dims=(-2,)
    )  # advantages normalised per region (dim -2 of (..., N, 1))
    loss.set_keys(
        reward=(GROUP, "reward"), action=(GROUP, "action"), value=(GROUP, "state_value"),
        done=(GROUP, "done"), terminated=(GROUP, "terminated"), sample_log_prob=(GROUP, "action_log_prob"),
    )  # fmt: skip
    loss.make_value_estimator(ValueEstimators.GAE, gamma=0.99, lmbda=0.95)
    optim = torch.optim.Adam(loss.parameters(), args.lr)

    episode = env.vector.max_cycles  # every episode has this many steps; all B end together
    start, done_steps = time.perf_counter(), 0
    while done_steps < args.steps and time.perf_counter() - start < 60 * args.time_limit:
        with torch.no_grad(), set_exploration_type(ExplorationType.RANDOM):  # sample (rollout alone takes the mean)
            td = env.rollout(episode, actor)  # (B, T): one whole episode of each of the B envs
            for key in ("done", "terminated"):  # the env flags whole episodes; GAE wants them per region
                td.set(("next", GROUP, key), td.get(("next", key)).unsqueeze(-1).expand(*td.shape, n_agents, 1))
            loss.value_estimator(td, params=loss.critic_network_params, target_params=loss.target_critic_network_params)
        flat = td.reshape(-1)
        for _ in range(args.epochs):
            for idx in torch.randperm(flat.shape[0]).split(args.minibatch):
                out = loss(flat[idx])
                total = out["loss_objective"] + out["loss_critic"] + out["loss_entropy"]
                optim.zero_grad()
                total.backward()
                nn.utils.clip_grad_norm_(loss.parameters(), 1.0)
                optim.step()
        done_steps += flat.shape[0]
        ret = td["next", GROUP, "reward"][..., 0, 0].sum(-1).mean().item()
        print(f"{done_steps:7d} env steps | {time.perf_counter() - start:6.1f} s | team return {ret:.3f}", flush=True)
    wall = time.perf_counter() - start

    agents = [f"region_{i}" for i in range(n_agents)]

    @torch.no_grad()
    def mappo(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        """The deterministic actor (the squashed mean) on the env's observations dict."""
        x = torch.as_tensor(np.stack([obs[a] for a in agents]), dtype=torch.float32)
        td = TensorDict({GROUP: TensorDict({"observation": x}, batch_size=[n_agents])}, batch_size=[])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            action = actor(td)[GROUP, "action"].numpy()
        return {a: action[i] for i, a in enumerate(agents)}

    learned = marl_amod.evaluate(mappo, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    ed = marl_amod.evaluate("equal-distribution", args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    name = "IPPO" if args.ippo else "MAPPO"
    print(
        f"{args.scenario}: {name} {learned['mean']:,.0f} ± {learned['std']:,.0f}  equal distribution {ed['mean']:,.0f} ± {ed['std']:,.0f}"
        f"  ({100 * (learned['mean'] / ed['mean'] - 1):+.1f}%), {done_steps:,} env steps in {wall / 60:.1f} min"
        f" ({done_steps / wall:,.0f} env steps/s with training)"
    )


if __name__ == "__main__":
    main()
