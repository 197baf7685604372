"""BenchMARL on marl_amod: a Task class, then any algorithm of its zoo (MAPPO, IPPO, MASAC, ...).

BenchMARL runs tasks it knows by name; a new environment is a ``TaskClass`` (how to build the
env and read its specs) plus a ``Task`` enum (the names). The class reuses BenchMARL's own
PettingZoo spec handling and says how to build the env (marl_amod's batched TorchRL env; TorchRL's
``PettingZooWrapper`` around ``marl_amod.parallel_env`` works too, about ten times slower):
continuous actions, a global state, 19-step episodes.
The trained policy is then scored by ``marl_amod.evaluate`` on the README's seeds.

BenchMARL pins TorchRL 0.11, so it lives in its own environment. A plain ``pip install benchmarl``
pulls torch 2.14 with CUDA through torchvision; this keeps the CPU torch (see docs/ecosystem.md):

    python -m venv .venv-benchmarl && . .venv-benchmarl/bin/activate
    pip install "torch==2.13.0" && pip install benchmarl "torchvision==0.28.*" "torch==2.13.0" marl-amod
    python examples/benchmarl_task.py --algorithm mappo --scenario synthetic
"""

from __future__ import annotations

import argparse
import tempfile
import time
from collections.abc import Callable
from typing import Any

import numpy as np
import torch
from benchmarl.algorithms import IppoConfig, MappoConfig, MasacConfig
from benchmarl.environments import Task
from benchmarl.environments.common import TaskClass
from benchmarl.experiment import Experiment, ExperimentConfig
from benchmarl.models.mlp import MlpConfig
from tensordict import TensorDict
from torchrl.data import Composite
from torchrl.envs import EnvBase
from torchrl.envs.utils import ExplorationType, set_exploration_type

import marl_amod
from marl_amod.integrations.torchrl import torchrl_vector_env

ALGORITHMS = {"mappo": MappoConfig, "ippo": IppoConfig, "masac": MasacConfig}


class AmodClass(TaskClass):
    """A marl_amod scenario as a BenchMARL task; ``config`` holds the env keywords (``scenario``, ...).

    The env is :func:`~marl_amod.integrations.torchrl.torchrl_vector_env`: BenchMARL's
    ``num_envs`` episodes in one batched env (as it runs VMAS), about ten times the throughput
    of a ``SerialEnv`` of ``PettingZooWrapper`` envs. Specs are read unbatched, as BenchMARL's
    VMAS task does: group ``"agents"`` (observation, action, reward) and a global ``"state"``.
    """

    def get_env_fun(self, num_envs: int, continuous_actions: bool, seed: int | None, device: Any) -> Callable[[], EnvBase]:
        config = dict(self.config)

        def make() -> EnvBase:
            env = torchrl_vector_env(num_envs=num_envs, device=device, **config)
            env.set_seed(seed)
            return env

        return make

    def supports_continuous_actions(self) -> bool:
        return True

    def supports_discrete_actions(self) -> bool:
        return False

    def has_render(self, env: EnvBase) -> bool:
        return False

    def max_steps(self, env: EnvBase) -> int:
        return env.vector.max_cycles

    def group_map(self, env: EnvBase) -> dict[str, list[str]]:
        return {"agents": list(env.vector.possible_agents)}

    def observation_spec(self, env: EnvBase) -> Composite:
        spec = env.full_observation_spec_unbatched.clone()
        del spec["state"]
        return spec

    def state_spec(self, env: EnvBase) -> Composite:
        return Composite({"state": env.full_observation_spec_unbatched["state"].clone()})

    def action_spec(self, env: EnvBase) -> Composite:
        return env.full_action_spec_unbatched

    def action_mask_spec(self, env: EnvBase) -> None:
        return None

    def info_spec(self, env: EnvBase) -> None:
        return None  # per-step infos stay in the vector env (money, not rewards)

    @staticmethod
    def env_name() -> str:
        return "marl_amod"


class AmodTask(Task):
    """Task names; each one's config is given to ``get_task(config=...)`` (no YAML needed)."""

    SYNTHETIC = None
    NYC_BROOKLYN = None

    @staticmethod
    def associated_class() -> type[AmodClass]:
        return AmodClass


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--algorithm", default="mappo", choices=sorted(ALGORITHMS))
    parser.add_argument("--scenario", default="synthetic", choices=["synthetic", "nyc_brooklyn"])
    parser.add_argument("--frames", type=int, default=60_000, help="env steps to train")
    parser.add_argument("--frames-per-batch", type=int, default=608, help="env steps per batch (a multiple of --envs)")
    parser.add_argument("--envs", type=int, default=32, help="episodes stepped together in the batched env")
    parser.add_argument("--epochs", type=int, default=4, help="on-policy passes over each batch")
    parser.add_argument("--minibatch", type=int, default=152, help="env steps per on-policy minibatch")
    parser.add_argument("--lr", type=float, default=3e-4)
    parser.add_argument("--init-scale", type=float, default=0.3, help="initial std of the TanhNormal actor (before the tanh)")
    parser.add_argument("--eval-episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()

    task = AmodTask[args.scenario.upper()].get_task(config={"scenario": args.scenario, "reward_scale": "auto"})
    config = ExperimentConfig.get_from_yaml()
    config.max_n_frames = args.frames
    config.on_policy_collected_frames_per_batch = config.off_policy_collected_frames_per_batch = args.frames_per_batch
    config.on_policy_n_envs_per_worker = config.off_policy_n_envs_per_worker = args.envs
    config.on_policy_minibatch_size = min(args.minibatch, args.frames_per_batch)
    config.on_policy_n_minibatch_iters = args.epochs
    config.off_policy_n_optimizer_steps = 50
    config.off_policy_init_random_frames = 0
    config.lr = args.lr
    config.evaluation = False
    config.render = False
    config.loggers = []
    config.create_json = False
    config.checkpoint_at_end = False
    config.save_folder = tempfile.mkdtemp(prefix="benchmarl_")  # BenchMARL writes its run folder here
    algorithm = ALGORITHMS[args.algorithm].get_from_yaml()
    # Start near equal distribution: every weight about 0.5 with small noise (BenchMARL's default
    # std of 1 spreads the weights over [0, 1], far worse than ED; only their ratios matter).
    algorithm.scale_mapping = f"biased_softplus_{args.init_scale}"
    if hasattr(algorithm, "lmbda"):
        algorithm.lmbda = 0.95
    experiment = Experiment(
        task=task, algorithm_config=algorithm, model_config=MlpConfig.get_from_yaml(),
        critic_model_config=MlpConfig.get_from_yaml(), seed=args.seed, config=config,
    )  # fmt: skip
    start = time.perf_counter()
    experiment.run()
    wall = time.perf_counter() - start

    policy = experiment.policy
    n = len(experiment.group_map["agents"])
    agents = [f"region_{i}" for i in range(n)]

    @torch.no_grad()
    def learned(obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        x = torch.as_tensor(np.stack([obs[a] for a in agents]), dtype=torch.float32)
        td = TensorDict({"agents": TensorDict({"observation": x}, batch_size=[n])}, batch_size=[])
        with set_exploration_type(ExplorationType.DETERMINISTIC):
            action = policy(td)["agents", "action"].numpy()
        return {a: action[i] for i, a in enumerate(agents)}

    ours = marl_amod.evaluate(learned, args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    ed = marl_amod.evaluate("equal-distribution", args.scenario, episodes=args.eval_episodes, seed=0)["metrics"]["profit"]
    print(
        f"{args.scenario}: BenchMARL {args.algorithm.upper()} {ours['mean']:,.0f} ± {ours['std']:,.0f}  "
        f"equal distribution {ed['mean']:,.0f} ± {ed['std']:,.0f}  ({100 * (ours['mean'] / ed['mean'] - 1):+.1f}%), "
        f"{args.frames:,} env steps in {wall / 60:.1f} min ({args.frames / wall:,.0f} env steps/s)"
    )


if __name__ == "__main__":
    main()
