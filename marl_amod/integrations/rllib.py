"""Ray RLlib (new API stack) with parameter sharing: every region agent acts with one shared GNN module.

* Env: RLlib's ``ParallelPettingZooEnv`` over :class:`RllibAmodEnv`, our small ParallelEnv wrapper
  that scales the team reward and, for the centralised critic, appends the env's global ``state()``
  to every agent's observation (RLlib's wrapper does not expose ``state()``). Each env runner builds
  its own env from the registered creator, so the solvers are created lazily on every worker.
* Policy: all ``region_*`` agents map to the one module ``"shared"`` (policy mapping +
  ``MultiRLModuleSpec``); the module is :class:`~marl_amod.integrations.rllib_module.AmodGNNModule`,
  marl_amod's :class:`~marl_amod.models.LocalActor` with a scaled-Gamma head (the joint action is the
  paper's Dirichlet) and a value head on the local observation or on the global state.
* Algorithm: PPO. SAC is not offered: RLlib's SAC module needs its own Q-network and
  squashed-Gaussian action heads, which this shared Gamma module does not provide.
* Output: the shared actor's weights go into the native ``policies/`` format (card ``actor:
  local``), so ``marl-amod evaluate --policy`` treats an RLlib policy like a native one.

Ray starts on loopback (``RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER=0`` is set before ``import ray``; the
``_node_ip_address`` argument alone is overridden), without the dashboard, with its temp folder and
results folder in places this run owns; or it joins a running cluster (``address="auto"`` or
``"ray://head:10001"``).

    pip install "marl-amod[rllib]"
"""

from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import tempfile
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pydantic import Field

from marl_amod.config import CommonArgs, load_config
from marl_amod.env.features import n_features as feature_count
from marl_amod.errors import ConfigError

EXTRA = 'pip install "marl-amod[rllib]"'
ENV_NAME = "marl_amod_amod_v0"
POLICY_ID = "shared"


def require_ray() -> Any:
    """Import Ray (and the module classes) on first use; a missing backend names the extra."""
    os.environ.setdefault("RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER", "0")  # else Ray listens on every interface
    if os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH"):
        # Ray 2.60 sends a token given by env var only in token mode, read when ray is imported
        os.environ.setdefault("RAY_AUTH_MODE", "token")
    try:
        import ray
        import ray.rllib  # noqa: F401
    except ImportError as exc:
        raise ConfigError(f"RLlib training needs the extra: {EXTRA} ({exc})") from exc
    return ray


# --------------------------------------------------------------------------------------------
# Config
# --------------------------------------------------------------------------------------------
class RllibArgs(CommonArgs):
    """``args`` of an RLlib config (configs/ppo_rllib/*.yaml): the native runs' common args, plus PPO's and Ray's."""

    central_critic: bool = True
    """critic on the env's global state() (centralised training, decentralised execution)"""
    critic_hidden: int = Field(64, ge=1)
    reward_scale: float = Field(0.001, gt=0)
    """multiplies the team profit per step so value targets stay O(1)"""
    iterations: int = Field(50, ge=1)
    target_profit: float = 0.0
    """stop early once a validation profit reaches this (0: never)"""
    lr: float = Field(3e-4, gt=0)
    lambda_: float = Field(0.95, ge=0, le=1)
    train_batch_env_steps: int = Field(304, ge=1)
    """env steps per iteration (x regions agent steps); 304 = 16 synthetic episodes"""
    minibatch_size: int = Field(304, ge=1)
    """rows of the shared module's batch per SGD step; RLlib caps it at train_batch_env_steps"""
    num_epochs: int = Field(4, ge=1)
    clip_param: float = Field(0.2, gt=0)
    vf_clip_param: float = Field(10.0, gt=0)
    vf_loss_coeff: float = Field(0.5, ge=0)
    entropy_coeff: float = Field(0.0, ge=0)
    grad_clip: float = Field(10.0, gt=0)
    num_env_runners: int = Field(1, ge=0)
    """remote env runners (0: sample in the driver); --num-env-runners overrides it"""
    num_cpus: int = Field(2, ge=1)
    """CPUs of the local Ray instance (ignored when joining a cluster)"""
    eval_every: int = Field(5, ge=0)
    """validate the deterministic policy every k iterations (0: only at the end)"""
    eval_episodes: int = Field(3, ge=1)
    run_dir: str = "runs/ppo_rllib"
    """log.csv, RLlib checkpoint (checkpoint/), results"""
    ray_temp_dir: str = ""
    """Ray's session folder (default: a fresh temp dir, removed at the end)"""


def load_rllib_config(path: str | Path) -> RllibArgs:
    """Strictly validated RLlib training args from a YAML config (``extends:`` resolved)."""
    from marl_amod.config import read_config

    algo = read_config(path).get("algo")
    if algo != "ppo" and isinstance(algo, str):
        raise ConfigError(f"{path}: algo: {algo} is a native algorithm; train it without --backend rllib")
    return load_config(path, {"ppo": RllibArgs})[1]  # type: ignore[return-value]


# --------------------------------------------------------------------------------------------
# Env
# --------------------------------------------------------------------------------------------
class RllibAmodEnv(ParallelEnv):
    """The AMoD ParallelEnv as RLlib trains on it: team reward x ``reward_scale``; obs (+ state()).

    With ``central_critic`` every agent's observation is ``[local obs (D), state() (S)]``: RLlib's
    PettingZoo wrapper has no ``state()``, and riding along in the observation is how the shared
    module's critic sees it. The actor reads the first D entries only.
    """

    metadata = {"name": "amod_v0_rllib", "render_modes": [], "is_parallelizable": True}

    def __init__(self, scenario: str = "synthetic", lookahead: int = 6, reward_scale: float = 1.0, central_critic: bool = True) -> None:
        from marl_amod.env.parallel import AmodParallelEnv

        self.env = AmodParallelEnv(scenario, reward_mode="team", action_mode="weight", lookahead=lookahead)
        self.reward_scale = float(reward_scale)
        self.central_critic = bool(central_critic)
        self.render_mode = None
        self.possible_agents = list(self.env.possible_agents)
        local = self.env.observation_space(self.possible_agents[0])
        self.local_dim = int(local.shape[0])
        if self.central_critic:
            state = self.env.state_space
            local = spaces.Box(np.concatenate([local.low, state.low]), np.concatenate([local.high, state.high]), dtype=np.float32)
        self._obs_space = local
        self.observation_spaces = {a: local for a in self.possible_agents}
        self.action_spaces = {a: self.env.action_space(a) for a in self.possible_agents}

    @property
    def agents(self) -> list[str]:
        return self.env.agents

    def observation_space(self, agent: str) -> spaces.Box:
        return self._obs_space

    def action_space(self, agent: str) -> spaces.Box:
        return self.env.action_space(agent)

    def state(self) -> np.ndarray:
        return self.env.state()

    def _augment(self, obs: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
        if not self.central_critic:
            return obs
        s = self.env.state()
        return {a: np.concatenate([o, s]) for a, o in obs.items()}

    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        obs, infos = self.env.reset(seed=seed, options=options)
        return self._augment(obs), infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        obs, rew, term, trunc, infos = self.env.step(actions)
        return self._augment(obs), {a: r * self.reward_scale for a, r in rew.items()}, term, trunc, infos

    def close(self) -> None:
        self.env.close()


def make_rllib_env(env_config: dict[str, Any]) -> Any:
    """Registered env creator: RLlib's ParallelPettingZooEnv over :class:`RllibAmodEnv`."""
    require_ray()
    from ray.rllib.env.wrappers.pettingzoo_env import ParallelPettingZooEnv

    return ParallelPettingZooEnv(RllibAmodEnv(**env_config))


def shared_policy(agent_id: str, episode: Any = None, **kwargs: Any) -> str:
    """Parameter sharing: every region agent acts with the one shared module."""
    return POLICY_ID


# --------------------------------------------------------------------------------------------
# Ray session and algorithm
# --------------------------------------------------------------------------------------------
@contextlib.contextmanager
def ray_session(address: str | None = None, num_cpus: int = 2, temp_dir: str | Path | None = None) -> Iterator[Any]:
    """Local Ray on loopback (or join ``address``); always shut down, own temp dir removed.

    Also points RLlib's results folder (otherwise ``~/ray_results``) into the temp dir. Ray 2.60
    enables token authentication for a new local cluster and would write its token to
    ``~/.ray/auth_token``; a local start gets a per-process token in ``RAY_AUTH_TOKEN`` instead
    (inherited by Ray's own processes, no file). Joining a cluster needs that cluster's token, as
    Ray documents (``RAY_AUTH_TOKEN``, ``RAY_AUTH_TOKEN_PATH`` or ``~/.ray/auth_token``).
    """
    ray = require_ray()
    import ray.tune.trainable.trainable as trainable_mod

    own_tmp = temp_dir is None
    tmp = Path(tempfile.mkdtemp(prefix="marl_amod_ray_")) if own_tmp else Path(temp_dir)
    tmp.mkdir(parents=True, exist_ok=True)
    old_results = trainable_mod.DEFAULT_STORAGE_PATH
    trainable_mod.DEFAULT_STORAGE_PATH = str(tmp / "results")
    try:
        if address:
            ray.init(address=address, log_to_driver=False, logging_level="ERROR")
        else:
            if not (os.environ.get("RAY_AUTH_TOKEN") or os.environ.get("RAY_AUTH_TOKEN_PATH")):
                os.environ["RAY_AUTH_TOKEN"] = secrets.token_hex(32)  # one per process: Ray caches it
            ray.init(
                num_cpus=num_cpus, include_dashboard=False, _temp_dir=str(tmp.resolve()),
                log_to_driver=False, logging_level="ERROR",
            )
        yield ray
    finally:
        ray.shutdown()
        trainable_mod.DEFAULT_STORAGE_PATH = old_results
        if own_tmp:
            shutil.rmtree(tmp, ignore_errors=True)


def env_config(args: RllibArgs) -> dict[str, Any]:
    return {"scenario": args.scenario, "lookahead": args.lookahead, "reward_scale": args.reward_scale, "central_critic": args.central_critic}


def build_ppo(args: RllibArgs, num_env_runners: int | None = None) -> Any:
    """An RLlib PPO algorithm with one shared :class:`AmodGNNModule` (Ray must be running)."""
    require_ray()
    from ray.rllib.algorithms.ppo import PPOConfig
    from ray.rllib.core.rl_module.multi_rl_module import MultiRLModuleSpec
    from ray.rllib.core.rl_module.rl_module import RLModuleSpec
    from ray.tune.registry import register_env

    from marl_amod.integrations.rllib_module import AmodGNNModule

    register_env(ENV_NAME, make_rllib_env)
    probe = RllibAmodEnv(**env_config(args))
    runners = args.num_env_runners if num_env_runners is None else num_env_runners
    model = {"local_dim": probe.local_dim, "n_features": feature_count(args.lookahead), "hidden": args.hidden, "critic_hidden": args.critic_hidden}
    config = (
        PPOConfig()
        .environment(ENV_NAME, env_config=env_config(args), normalize_actions=False, clip_actions=False)
        .framework("torch")
        .env_runners(num_env_runners=runners, num_envs_per_env_runner=1, num_cpus_per_env_runner=1, rollout_fragment_length="auto")
        .learners(num_learners=0)
        # RLlib's default restarts a failed env runner (max_restarts=1000), but it hands each runner its
        # config through the object store, which Ray cannot guarantee for a restart: Ray logs an error
        # (core_worker "max_restarts", ray-project/ray#53727) at every start. An env runner that fails here
        # fails for a reason a restart does not fix (the env is deterministic code), so fail the run instead.
        .fault_tolerance(restart_failed_env_runners=False)
        .multi_agent(policies={POLICY_ID}, policy_mapping_fn=shared_policy, policies_to_train=[POLICY_ID])
        .rl_module(
            rl_module_spec=MultiRLModuleSpec(rl_module_specs={POLICY_ID: RLModuleSpec(module_class=AmodGNNModule, model_config=model)})
        )
        .training(
            lr=args.lr, gamma=args.gamma, lambda_=args.lambda_, train_batch_size_per_learner=args.train_batch_env_steps,
            minibatch_size=min(args.minibatch_size, args.train_batch_env_steps), num_epochs=args.num_epochs,
            clip_param=args.clip_param, vf_clip_param=args.vf_clip_param, vf_loss_coeff=args.vf_loss_coeff,
            entropy_coeff=args.entropy_coeff, grad_clip=args.grad_clip, use_kl_loss=False,
        )
        .reporting(metrics_num_episodes_for_smoothing=max(1, args.train_batch_env_steps // (probe.env.city.horizon - 1)))
        .debugging(seed=args.seed, log_level="ERROR")
    )
    return config.build_algo()


# --------------------------------------------------------------------------------------------
# Conversion to the native policy format
# --------------------------------------------------------------------------------------------
def module_to_actor(module: Any, hidden: int, n_features: int) -> torch.nn.Module:
    """The shared module's actor as a native :class:`LocalActor` (a copy, eval mode)."""
    from marl_amod.models import LocalActor

    actor = LocalActor(n_features, hidden)
    actor.load_state_dict({k: v.detach().cpu().clone() for k, v in module.actor.state_dict().items()})
    return actor.eval()


def checkpoint_module_path(checkpoint: str | Path) -> Path:
    """Where an Algorithm checkpoint keeps the shared module's own checkpoint."""
    return Path(checkpoint).resolve() / "learner_group" / "learner" / "rl_module" / POLICY_ID  # pyarrow wants absolute paths


def actor_from_checkpoint(checkpoint: str | Path, hidden: int = 32, n_features: int = 13) -> torch.nn.Module:
    """Native :class:`LocalActor` from an RLlib Algorithm checkpoint (no running Ray needed)."""
    require_ray()
    from ray.rllib.core.rl_module.rl_module import RLModule

    path = checkpoint_module_path(checkpoint)
    if not path.is_dir():
        raise ConfigError(f"{checkpoint} is not an RLlib checkpoint with a {POLICY_ID!r} module ({path} missing)")
    return module_to_actor(RLModule.from_checkpoint(path), hidden, n_features)


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------
def _iteration_stats(result: dict[str, Any], n_agents: int, reward_scale: float) -> dict[str, float]:
    """Flat numbers per iteration: env steps, episode profit (team return back in money)."""
    runners = result.get("env_runners", {})
    timers = result.get("timers", {})
    ret = runners.get("episode_return_mean", float("nan"))
    return {
        "env_steps": float(runners.get("num_env_steps_sampled_lifetime", 0)),
        "env_steps_iter": float(runners.get("num_env_steps_sampled", 0)),
        # every agent gets the team reward; the profit of the reset's dispatch (step 0) is not in it
        "train/profit": float(ret) / (n_agents * reward_scale),
        "sample_s": float(timers.get("env_runner_sampling_timer", float("nan"))),  # RLlib's smoothed timers
        "learn_s": float(timers.get("learner_update_timer", float("nan"))),
    }


def train_rllib(
    args: RllibArgs,
    num_env_runners: int | None = None,
    address: str | None = None,
    progress: Callable[[int, int, dict], None] | None = None,
    config_path: str | None = None,
) -> dict[str, Any]:
    """Train PPO on Ray, checkpoint under ``run_dir``, convert, evaluate; returns the run summary."""
    from marl_amod.algos.common import BestActor, Logger, evaluate_actor, seed_everything
    from marl_amod.checkpoints import make_card, save_policy
    from marl_amod.files import write_json
    from marl_amod.models import LocalActor
    from marl_amod.scenario import load_city

    seed_everything(args.seed)
    city = load_city(args.scenario)
    n_features = feature_count(args.lookahead)
    runners = args.num_env_runners if num_env_runners is None else num_env_runners
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    log = Logger(run_dir, tensorboard=False)
    temp = args.ray_temp_dir or None
    best, best_iteration = BestActor.of(LocalActor(n_features, args.hidden)), 0
    history: list[dict[str, float]] = []
    start = time.perf_counter()
    try:
        with ray_session(address, args.num_cpus, temp):
            algo = build_ppo(args, runners)
            try:
                it = 0
                for it in range(1, args.iterations + 1):
                    t0 = time.perf_counter()
                    result = algo.train()
                    stats = _iteration_stats(result, city.n_regions, args.reward_scale)
                    stats["iter_s"] = time.perf_counter() - t0
                    stats["wall_s"] = time.perf_counter() - start
                    last = it == args.iterations or (args.time_limit_s and stats["wall_s"] >= args.time_limit_s)
                    if last or (args.eval_every and it % args.eval_every == 0):
                        actor = module_to_actor(algo.get_module(POLICY_ID), args.hidden, n_features)
                        before = best.value
                        stats["eval/profit"] = best.validate(actor, city, args)
                        if best.value > before:
                            best_iteration = it
                        if args.target_profit and stats["eval/profit"] >= args.target_profit:
                            last = True
                    log.log(it, **stats)
                    history.append({"iteration": it, **stats})
                    if progress is not None:
                        progress(it, args.iterations, stats)
                    if last:
                        break
                checkpoint = Path(algo.save_to_path(str((run_dir / "checkpoint").resolve())))
            finally:
                algo.stop()
    finally:
        log.close()
    wall = time.perf_counter() - start

    actor = LocalActor(n_features, args.hidden)
    actor.load_state_dict(best.state)  # the best validation actor, as the native trainers keep
    actor.eval()
    result = evaluate_actor(actor, city, args.final_eval_episodes, args.final_eval_seed, args.lookahead)
    profit = result["metrics"]["profit"]
    env_steps = history[-1]["env_steps"] if history else 0.0
    card = make_card(
        scenario=city.name, n_regions=city.n_regions, algorithm="rllib-ppo", mode="decentralised", actor="local", conv="sage",
        hidden=args.hidden, n_features=n_features, lookahead=args.lookahead, seed=args.seed,
        central_critic=args.central_critic, iterations=len(history), best_iteration=best_iteration, env_steps=int(env_steps),
        num_env_runners=runners, eval_episodes=args.final_eval_episodes, eval_seed=args.final_eval_seed,
        profit_mean=profit["mean"], profit_std=profit["std"], served_demand_mean=result["metrics"]["served_demand"]["mean"],
        training_wall_s=round(wall, 1), env_steps_per_s=round(env_steps / wall, 1) if wall > 0 else 0.0,
        config=str(config_path) if config_path else None, args=args.model_dump(mode="json"),
    ).to_dict()
    summary: dict[str, Any] = {"card": card, "result": result, "checkpoint": str(checkpoint), "history": history}
    if args.policy_out:
        summary["policy"] = str(save_policy(args.policy_out, actor, card))
    write_json(run_dir / "final_eval.json", result)
    return summary
