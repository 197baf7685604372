"""What A2C and SAC share: rollouts in either mode, logging, evaluation, checkpoints, configs.

The algorithm files (:mod:`marl_amod.algos.a2c`, :mod:`marl_amod.algos.sac`) read top to bottom;
everything here is plumbing they would otherwise repeat.

Modes
-----
* ``centralised``: one learner sees the global graph (N, F) and acts for every region.
* ``decentralised``: every region acts from its own local observation (own features plus its
  in-neighbours' features and a mask), with one shared parameter set. Observations come through
  the PettingZoo env (``marl_amod.parallel_env``) when it is installed, else from
  :func:`marl_amod.env.observations.local_observations` on the same system (the same bytes).
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import json
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, Protocol

import numpy as np
import torch
from pydantic import BaseModel, ConfigDict, TypeAdapter, ValidationError

from marl_amod.data import read_yaml
from marl_amod.env import ENV_VERSION
from marl_amod.env.features import n_features as feature_count
from marl_amod.errors import ConfigError
from marl_amod.scenario import City
from marl_amod.system import FleetSystem

Mode = Literal["centralised", "decentralised"]
WEIGHT_DIVISOR = 1000.0  # Gamma weights / this constant fit the env's Box(0, 1) almost surely (alpha stays < 100)


@dataclass
class RunArgs:
    """What every training run has, whatever the algorithm; each algorithm's ``Args`` extends it.

    Each field is documented by the string under it, as in single-file RL scripts.
    """

    scenario: str = "synthetic"
    """scenario name or YAML path"""
    mode: Mode = "centralised"
    """centralised: one learner on the global graph; decentralised: shared actor on local observations"""
    actor: Literal["gnn", "mlp", "cnn"] = "gnn"
    """centralised actor architecture (decentralised always uses the local GNN actor)"""
    conv: Literal["gcn", "sage"] = "gcn"
    """message passing: gcn (the paper's) or sage (mean aggregation, what the local actor computes)"""
    hidden: int = 32
    """hidden units of the actor and critic MLPs"""
    central_critic: bool = True
    """decentralised mode only: critic on the global graph (env.state()) instead of sum of local values"""
    episodes: int = 1000
    """training episodes"""
    gamma: float = 0.97
    """discount factor (the paper's)"""
    reward_scale: float = 0.01
    """multiplies the money reward so returns are O(1..100)"""
    max_grad_norm: float = 10.0
    """gradient clipping (global L2 norm per network)"""
    lookahead: int = 6
    """look-ahead steps T of the node features (F = 1 + 2T)"""
    seed: int = 0
    """torch/numpy seed and training demand stream"""
    eval_every: int = 200
    """episodes between validation evaluations"""
    eval_episodes: int = 5
    """validation episodes (deterministic policy)"""
    eval_seed: int = 1000
    """validation demand seed; the best validation actor is kept (never the report seeds)"""
    final_eval_episodes: int = 10
    """episodes of the final report evaluation"""
    final_eval_seed: int = 0
    """report seed: same streams as `marl-amod evaluate --seed 0`"""
    threads: int = 1
    """torch CPU threads (the machine is shared)"""
    run_dir: str = "runs/train"
    """TensorBoard + CSV logs and the resumable training state"""
    policy_out: str = ""
    """where the final policy .pt (+ .json/.md cards) goes; empty: do not write one"""
    time_limit_s: float = 0.0
    """stop early after this much wall time (0: no limit)"""


# --------------------------------------------------------------------------------------------
# Observations and rollouts
# --------------------------------------------------------------------------------------------
@dataclass
class Obs:
    """One decision point. x (N, F) global node features; own (N, F), nbrs (N, K, F), mask (N, K) local."""

    x: torch.Tensor
    own: torch.Tensor | None = None
    nbrs: torch.Tensor | None = None
    mask: torch.Tensor | None = None


class Rollout:
    """Drives one city episode by episode; ``step(weights)`` takes (N,) non-negative weights."""

    def __init__(self, city: City, mode: Mode = "centralised", lookahead: int = 6, use_env: bool | None = None) -> None:
        from marl_amod.env.observations import neighbour_table

        self.city, self.mode, self.lookahead = city, mode, lookahead
        self.use_env = mode == "decentralised" and use_env is not False
        self.table = neighbour_table(city)
        if self.use_env:
            from marl_amod.env.parallel import parallel_env

            self.env = parallel_env(city, reward_mode="team", action_mode="weight", lookahead=lookahead)
            self.system = self.env.system
        else:
            self.env = None
            self.system = FleetSystem(city)
        self.done = False
        self.clipped = 0  # agent actions the env had to clip to its Box(0, 1)

    def _obs_from_system(self) -> Obs:
        from marl_amod.env.features import node_features
        from marl_amod.env.observations import local_observations, split_local

        x = torch.as_tensor(node_features(self.system, self.lookahead))
        if self.mode == "centralised":
            return Obs(x)
        own, _ctx, nbrs, mask = split_local(torch.as_tensor(local_observations(self.system, self.lookahead, table=self.table)), x.shape[1])
        return Obs(x, own, nbrs, mask)

    def _obs_from_env(self, obs: dict[str, np.ndarray]) -> Obs:
        from marl_amod.env.observations import split_local

        stacked = torch.as_tensor(np.stack([obs[a] for a in self.agents]))  # (N, D)
        x = torch.as_tensor(self.env.graph()["x"])  # (N, F): only the centralised critic reads it
        own, _ctx, nbrs, mask = split_local(stacked, x.shape[1])
        return Obs(x, own, nbrs, mask)

    def reset(self, seed: int | np.random.SeedSequence) -> Obs:
        self.done = False
        if self.env is not None:
            if isinstance(seed, np.random.SeedSequence):
                seed = int(seed.generate_state(1)[0])
            obs, _ = self.env.reset(seed=seed)
            self.agents = list(self.env.possible_agents)
            return self._obs_from_env(obs)
        self.system.reset(seed)
        return self._obs_from_system()

    def step(self, weights: np.ndarray) -> tuple[Obs, float]:
        """Apply (N,) weights; returns the next observation and the team reward (money)."""
        if self.env is not None:
            # The env's Box(0, 1) clips; weights are scale-free, so every agent divides by the same
            # constant. Counted so a clipped (law-changing) action never goes unnoticed.
            sent = np.asarray(weights, dtype=np.float64) / WEIGHT_DIVISOR
            self.clipped += int((sent > 1.0).sum())
            actions = {a: np.array([w], dtype=np.float32) for a, w in zip(self.agents, sent, strict=True)}
            obs, rewards, terms, truncs, _ = self.env.step(actions)
            reward = float(rewards[self.agents[0]])
            self.done = not self.env.agents
            if self.done:  # final obs is not used for bootstrapping past the horizon
                return self._obs_from_system(), reward
            return self._obs_from_env(obs), reward
        out = self.system.step(self.system.targets_from_weights(np.asarray(weights, dtype=np.float64)))
        self.done = self.system.done
        return self._obs_from_system(), out.reward


def train_seed(seed: int, episode: int) -> np.random.SeedSequence:
    """Training demand of episode k: never one of the evaluation streams (seed, k)."""
    return np.random.SeedSequence([seed, episode, 7919])


# --------------------------------------------------------------------------------------------
# Logging
# --------------------------------------------------------------------------------------------
class Logger:
    """TensorBoard scalars plus a long-format CSV (episode, metric, value) under ``run_dir``.

    Long format because validation rows are sparser than training rows; plots pivot it back.
    """

    def __init__(self, run_dir: str | Path, tensorboard: bool = True) -> None:
        self.dir = Path(run_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.writer = None
        if tensorboard:
            from torch.utils.tensorboard import SummaryWriter

            self.writer = SummaryWriter(str(self.dir))
        new = not (self.dir / "log.csv").exists()
        self._csv = open(self.dir / "log.csv", "a", newline="")  # noqa: SIM115 - closed in close()
        self._w = csv.writer(self._csv)
        if new:
            self._w.writerow(["episode", "metric", "value"])

    def log(self, step: int, **scalars: float) -> None:
        for k, v in scalars.items():
            self._w.writerow([step, k, float(v)])
            if self.writer is not None:
                self.writer.add_scalar(k, v, step)
        self._csv.flush()

    def close(self) -> None:
        self._csv.close()
        if self.writer is not None:
            self.writer.close()


def read_curve(run_dir: str | Path, metric: str) -> tuple[list[int], list[float]]:
    """(episodes, values) of one metric from a run's log.csv."""
    xs, ys = [], []
    path = Path(run_dir) / "log.csv"
    if path.exists():
        with open(path, newline="") as fh:
            for row in csv.DictReader(fh):
                if row["metric"] == metric:
                    xs.append(int(row["episode"]))
                    ys.append(float(row["value"]))
    return xs, ys


# --------------------------------------------------------------------------------------------
# Evaluation and checkpoints
# --------------------------------------------------------------------------------------------
def evaluate_actor(actor: torch.nn.Module, city: City, episodes: int, seed: int, lookahead: int = 6) -> dict[str, Any]:
    """Deterministic (Dirichlet mean) evaluation with the same loop and JSON as the baselines."""
    from marl_amod.checkpoints import ActorPolicy
    from marl_amod.evaluation import evaluate

    was_training = actor.training
    actor.eval()
    try:
        return evaluate(city, ActorPolicy(actor, city, lookahead), episodes=episodes, seed=seed)
    finally:
        actor.train(was_training)


class ValidationArgs(Protocol):
    """What validation reads from a run's args (native RunArgs and RLlib's args both have it)."""

    eval_episodes: int
    eval_seed: int
    lookahead: int


@dataclass
class BestActor:
    """The actor with the best validation profit so far: what a run keeps and ships, not the last one."""

    value: float
    state: dict[str, torch.Tensor]

    @classmethod
    def of(cls, actor: torch.nn.Module) -> BestActor:
        """Start from the untrained actor (kept if no validation ever beats -inf)."""
        return cls(-np.inf, copy.deepcopy(actor.state_dict()))

    def validate(self, actor: torch.nn.Module, city: City, args: ValidationArgs) -> float:
        """Mean profit of the deterministic actor on the validation seeds; kept when it is the best yet."""
        val = evaluate_actor(actor, city, args.eval_episodes, args.eval_seed, args.lookahead)["metrics"]["profit"]["mean"]
        if val > self.value:
            self.value, self.state = val, copy.deepcopy(actor.state_dict())
        return val


def close_episode(
    log: Logger, rollout: Rollout, ep: int, stats: dict[str, float], args: RunArgs, wall_s: float,
    progress: Callable[[int, int, dict], None] | None,
) -> bool:
    """Log one episode's stats and report progress; returns True when the time limit says stop."""
    stats["time/wall_s"] = wall_s
    if rollout.env is not None:
        stats["env/clipped_actions"] = rollout.clipped  # cumulative; should stay 0
    log.log(ep, **stats)
    if progress is not None:
        progress(ep, args.episodes, stats)
    return bool(args.time_limit_s) and wall_s > args.time_limit_s


def finish_run(
    args: Any, algorithm: str, actor: torch.nn.Module, city: City, wall_s: float, episodes_done: int
) -> dict[str, Any]:
    """Final evaluation on the report seeds, then the policy file and its cards."""
    from marl_amod.checkpoints import save_policy, write_card_markdown

    result = evaluate_actor(actor, city, args.final_eval_episodes, args.final_eval_seed, args.lookahead)
    profit = result["metrics"]["profit"]
    card = {
        "env_version": ENV_VERSION,
        "scenario": city.name,
        "algorithm": algorithm,
        "mode": args.mode,
        "actor": "local" if args.mode == "decentralised" else args.actor,
        "conv": "sage" if args.mode == "decentralised" else args.conv,
        "hidden": args.hidden,
        "n_features": feature_count(args.lookahead),
        "lookahead": args.lookahead,
        "seed": args.seed,
        "episodes_trained": episodes_done,
        "eval_episodes": args.final_eval_episodes,
        "eval_seed": args.final_eval_seed,
        "profit_mean": profit["mean"],
        "profit_std": profit["std"],
        "served_demand_mean": result["metrics"]["served_demand"]["mean"],
        "training_wall_s": round(wall_s, 1),
        "torch_threads": torch.get_num_threads(),
    }
    summary = {"card": card, "result": result}
    if args.policy_out:
        path = save_policy(args.policy_out, actor, card)
        write_card_markdown(path, card)
        summary["policy"] = str(path)
    run_dir = Path(args.run_dir)
    run_dir.mkdir(parents=True, exist_ok=True)
    (run_dir / "final_eval.json").write_text(json.dumps(result, indent=2))
    return summary


def save_state(path: str | Path, **state: Any) -> None:
    """Full training state (all networks and optimisers) for ``--resume``; lives under runs/."""
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    torch.save(state, path)


def load_state(path: str | Path) -> dict[str, Any]:
    if not Path(path).is_file():
        raise ConfigError(f"resume checkpoint {path} not found")
    return torch.load(path, map_location="cpu", weights_only=False)


def seed_everything(seed: int) -> None:
    np.random.seed(seed)
    torch.manual_seed(seed)


# --------------------------------------------------------------------------------------------
# Configs
# --------------------------------------------------------------------------------------------
class TrainConfig(BaseModel):
    """configs/<run>.yaml: which algorithm, and its Args (every key checked against the dataclass)."""

    model_config = ConfigDict(extra="forbid")
    algo: Literal["a2c", "sac"]
    args: dict[str, Any] = {}


def algo_module(algo: str):
    if algo == "a2c":
        from marl_amod.algos import a2c

        return a2c
    if algo == "sac":
        from marl_amod.algos import sac

        return sac
    raise ConfigError(f"unknown algorithm {algo!r}")


def make_args(algo: str, values: dict[str, Any], where: str = "config") -> Any:
    """Validate ``values`` strictly against the algorithm's Args dataclass: a typo is an error."""
    cls = algo_module(algo).Args
    known = {f.name for f in dataclasses.fields(cls)}
    unknown = sorted(set(values) - known)
    if unknown:
        raise ConfigError(f"{where}: unknown {algo} argument(s) {unknown}; known: {sorted(known)}")
    try:
        return TypeAdapter(cls).validate_python(values)
    except ValidationError as exc:
        raise ConfigError(f"{where}: {exc}") from None


def load_train_config(path: str | Path) -> tuple[str, Any]:
    """(algo, Args) from a YAML training config."""
    raw = read_yaml(path)
    try:
        cfg = TrainConfig.model_validate(raw)
    except ValidationError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return cfg.algo, make_args(cfg.algo, cfg.args, str(path))


def run_training(algo: str, args: Any, resume: str | None = None, progress: Callable[[int, int, dict], None] | None = None) -> dict:
    """Train with the chosen algorithm; returns the summary (card, final evaluation, policy path)."""
    return algo_module(algo).train(args, resume=resume, progress=progress)


class Timer:
    def __init__(self) -> None:
        self.start = time.perf_counter()

    def __call__(self) -> float:
        return time.perf_counter() - self.start
