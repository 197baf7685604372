"""Offline datasets: roll a behaviour policy and store its transitions in one ``.npz`` file.

Format (version 1). T transitions over all episodes, N regions (agents), F node features:

====================  ===============  ====================================================
key                   shape, dtype     meaning
====================  ===============  ====================================================
observation           (T, N, F) f32    :func:`marl_amod.env.features.node_features` after
                                       dispatch at step t (what the policy saw)
action                (T, N) f32       desired distribution: share of the idle fleet in each
                                       region once the coordinator has rebalanced (sums to 1;
                                       the current distribution when no vehicle is idle)
reward                (T,) f32         system reward of the step (next dispatch profit minus
                                       rebalancing cost)
region_reward         (T, N) f32       the same reward split by region (profit of trips and
                                       moves leaving each region); sums to ``reward``
next_observation      (T, N, F) f32    features after the next dispatch
done                  (T,) bool        True on the last step of an episode
episode, step         (T,) i64         episode index and control step t
edge_index            (2, E) i64       region adjacency (for graph policies)
feature_names         (F,) str
meta                  () str           JSON: format version, scenario, policy, seed, episodes
====================  ===============  ====================================================

:func:`agent_transitions` reads the same file as PettingZoo-style per-agent transitions keyed by
agent name ``region_{i}``.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from marl_amod.baselines.base import Policy
from marl_amod.env.features import feature_names, node_features
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import episode_seeds
from marl_amod.files import atomic_write, check_destination
from marl_amod.scenario.types import City
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_seed

FORMAT_VERSION = 1
ARRAY_KEYS = ("observation", "action", "reward", "region_reward", "next_observation", "done", "episode", "step")


@dataclass
class OfflineDataset:
    """Transitions in memory; ``save``/``load`` use the documented ``.npz`` layout."""

    observation: np.ndarray
    action: np.ndarray
    reward: np.ndarray
    region_reward: np.ndarray
    next_observation: np.ndarray
    done: np.ndarray
    episode: np.ndarray
    step: np.ndarray
    edge_index: np.ndarray
    feature_names: list[str]
    meta: dict

    def __len__(self) -> int:
        return int(self.reward.shape[0])

    def save(self, path: str | Path) -> Path:
        """Write atomically (a reader never sees half a dataset); a file handle keeps numpy from
        appending '.npz'."""
        path = check_destination(path, what="dataset")
        return atomic_write(path, lambda fh: np.savez_compressed(
            fh, **{k: getattr(self, k) for k in ARRAY_KEYS}, edge_index=self.edge_index,
            feature_names=np.array(self.feature_names), meta=np.array(json.dumps(self.meta)),
        ))  # fmt: skip

    @classmethod
    def load(cls, path: str | Path) -> OfflineDataset:
        path = Path(path)
        if not path.is_file():
            raise DataError(f"no dataset at {path}")
        with np.load(path, allow_pickle=False) as f:
            missing = [k for k in (*ARRAY_KEYS, "edge_index", "feature_names", "meta") if k not in f]
            if missing:
                raise DataError(f"{path} is not a marl_amod dataset: missing {', '.join(missing)}")
            meta = json.loads(str(f["meta"]))
            if meta.get("format_version") != FORMAT_VERSION:
                raise DataError(f"{path} has dataset format {meta.get('format_version')}, expected {FORMAT_VERSION}")
            return cls(
                **{k: f[k] for k in ARRAY_KEYS}, edge_index=f["edge_index"],
                feature_names=[str(s) for s in f["feature_names"]], meta=meta,
            )


def realised_distribution(system: FleetSystem, target: np.ndarray) -> np.ndarray:
    """(N,) share of idle vehicles per region after the coordinator meets ``target``.

    The coordinator is deterministic, so this is exactly what ``system.step(target)`` will do.
    """
    idle = system.sim.idle
    flows = system.coordinator.rebalance(idle, np.asarray(target))
    after = idle - flows.sum(axis=1) + flows.sum(axis=0)
    total = after.sum()
    return (after / total if total > 0 else np.full(idle.shape, 1.0 / idle.shape[0])).astype(np.float32)


def collect(
    city: City, policy: Policy, *, episodes: int, seed: int = 0, lookahead: int = 6,
    progress: Callable[[int], None] | None = None, **system_kwargs,
) -> OfflineDataset:
    """Roll ``policy`` for ``episodes`` episodes (seeded as in :func:`marl_amod.evaluation.evaluate`)."""
    if as_count(episodes, "episodes") < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    seed = as_seed(seed)
    system = FleetSystem(city, **system_kwargs)
    cols: dict[str, list] = {k: [] for k in ARRAY_KEYS}
    for ep in range(episodes):
        demand_seed, policy_rng = episode_seeds(seed, ep)
        system.reset(demand_seed)
        policy.reset(system, policy_rng)
        obs = node_features(system, lookahead)
        while not system.done:
            t = system.t
            target = policy.target(system)
            action = realised_distribution(system, target)
            outcome = system.step(target)
            next_obs = node_features(system, lookahead)
            cols["observation"].append(obs)
            cols["action"].append(action)
            cols["reward"].append(outcome.reward)
            cols["region_reward"].append(outcome.region_reward)
            cols["next_observation"].append(next_obs)
            cols["done"].append(system.done)
            cols["episode"].append(ep)
            cols["step"].append(t)
            obs = next_obs
        if progress is not None:
            progress(ep)
    dtypes = {"observation": np.float32, "action": np.float32, "reward": np.float32, "region_reward": np.float32,
              "next_observation": np.float32, "done": bool, "episode": np.int64, "step": np.int64}
    arrays = {k: np.asarray(v, dtype=dtypes[k]) for k, v in cols.items()}
    meta = {"format_version": FORMAT_VERSION, "scenario": city.name, "policy": getattr(policy, "name", "policy"),
            "seed": seed, "episodes": episodes, "lookahead": lookahead}
    return OfflineDataset(**arrays, edge_index=np.asarray(city.edge_index, dtype=np.int64),
                          feature_names=feature_names(lookahead), meta=meta)


def agent_transitions(dataset: OfflineDataset) -> dict[str, dict[str, np.ndarray]]:
    """Per-agent view: {"region_i": {observation (T, F), action (T, 1), reward (T,), next_observation, done}}.

    Each agent's reward is its region's share (``region_reward``); ``global_reward`` keeps the
    system reward for cooperative learners.
    """
    n = dataset.action.shape[1]
    return {
        f"region_{i}": {
            "observation": dataset.observation[:, i],
            "action": dataset.action[:, i : i + 1],
            "reward": dataset.region_reward[:, i],
            "global_reward": dataset.reward,
            "next_observation": dataset.next_observation[:, i],
            "done": dataset.done,
        }
        for i in range(n)
    }
