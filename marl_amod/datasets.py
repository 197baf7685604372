"""Offline datasets: what the env's agents saw and did under a behaviour policy, in one ``.npz``.

Format version 2. T transitions over all episodes, N agents (regions), D = F + 3 + K(F + 1) the
length of one agent's local observation (:mod:`marl_amod.env.observations`), S = N*F + 3 the
global state, F node features:

=====================  ===============  ===================================================
key                    shape, dtype     meaning
=====================  ===============  ===================================================
observations           (T, N, D) f32    each agent's local observation, as the env gave it
actions                (T, N) f32       each agent's action as the env took it: a weight in
                                        [0, 1] (``action_mode="weight"``); see below
rewards                (T, N) f32       each region's booked reward of the step
                                        (``reward_mode="local"``: its dispatch profit minus
                                        the cost of the vehicles it sent away)
team_rewards           (T,) f32         the system reward (sum of ``rewards``; money)
states                 (T, S) f32       ``env.state()``: every region's F features, then time
next_observations      (T, N, D) f32    observations after the step
next_states            (T, S) f32       ``env.state()`` after the step
terminations           (T,) bool        always False (the env never terminates an agent)
truncations            (T,) bool        True on the episode's last step (the horizon)
episode_ids, step_ids  (T,) i64         episode index and control step t
edge_index             (2, E) i64       region adjacency, source -> target
edge_attr              (E, 2) f32       rebalancing steps and cost of each edge
meta                   () str           JSON: format version, scenario, policy, seeds, ...
=====================  ===============  ===================================================

Actions. The env reads the joint action as weights w and targets floor(w_i / sum(w) * M) idle
vehicles in region i (M idle in all). A policy that outputs weights (PROP, ED, a trained actor)
is recorded as its normalised weights. A policy that outputs targets u (INF, DTV, MPC) is recorded
as u_i / 2^k with 2^k the smallest power of two >= M: proportional to the target share u_i / M,
and exact in float32, so the env turns it back into the same targets (:func:`collect` counts
steps where it would not, ``target_mismatch`` in ``meta``: 0 for the bundled policies); "no
wish" targets (-1) become the region's idle vehicles (stay); with no idle vehicle the action is
uniform. The behaviour score on the card is that of this env-action policy.

Views: :meth:`OfflineDataset.global_view` gives the centralised learner's graph batch (node
features (T, N, F), the action as a distribution on the simplex, the team reward);
:meth:`OfflineDataset.agent_view` gives PettingZoo-style per-agent transitions keyed by agent.
Episodes bootstrap nowhere past the horizon: ``terminations | truncations`` ends the return.

Seeds: episode k of a dataset seeded s draws demand from
:func:`marl_amod.algos.rollout.train_seed` (s, k), never one of the evaluation streams (s', k'),
so a policy trained on a dataset is scored on demand it has not seen. ``meta["streams"]`` lists
the episodes held as ``[seed, first k, count]`` ranges: a collection is one range (``first_episode``
resumes a seed's streams where an earlier piece stopped), :func:`merge` joins pieces collected in
parallel or across sessions into one dataset after checking they are the same collection and hold
no episode twice. Pieces with different seeds never share a stream. :func:`mix` joins collections
of different behaviours on one city (D4RL's medium-expert kind). The card (same name,
``.json``) holds the behaviour policy's score and the reference scores ED and MPC-Oracle on the
evaluation seeds, for normalised scores (:func:`normalised_score`: 0 = ED, 100 = MPC-Oracle).
"""

from __future__ import annotations

import json
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod import metrics
from marl_amod.baselines.base import Policy, WeightPolicy
from marl_amod.errors import ConfigError, DataError
from marl_amod.files import atomic_write, check_destination, file_sha256, write_json
from marl_amod.scenario.types import City
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_seed

FORMAT_VERSION = 2
ARRAY_KEYS = (
    "observations", "actions", "rewards", "team_rewards", "states", "next_observations", "next_states",
    "terminations", "truncations", "episode_ids", "step_ids",
)  # fmt: skip
DTYPES = {"terminations": np.bool_, "truncations": np.bool_, "episode_ids": np.int64, "step_ids": np.int64}
REFERENCES = metrics.SCORE_ANCHORS  # the reference scores a card holds: normalised score 0 and 100


@dataclass
class OfflineDataset:
    """Transitions in memory; ``save``/``load`` use the documented ``.npz`` layout."""

    observations: np.ndarray
    actions: np.ndarray
    rewards: np.ndarray
    team_rewards: np.ndarray
    states: np.ndarray
    next_observations: np.ndarray
    next_states: np.ndarray
    terminations: np.ndarray
    truncations: np.ndarray
    episode_ids: np.ndarray
    step_ids: np.ndarray
    edge_index: np.ndarray
    edge_attr: np.ndarray
    meta: dict[str, Any]

    def __len__(self) -> int:
        return int(self.team_rewards.shape[0])

    @property
    def n_agents(self) -> int:
        return int(self.actions.shape[1])

    @property
    def n_features(self) -> int:
        return int(self.meta["n_features"])

    def save(self, path: str | Path) -> Path:
        """Write atomically (a reader never sees half a dataset); a file handle keeps numpy from
        appending '.npz'."""
        path = dataset_destination(path, what="dataset")
        return atomic_write(path, lambda fh: np.savez_compressed(
            fh, **{k: getattr(self, k) for k in ARRAY_KEYS}, edge_index=self.edge_index, edge_attr=self.edge_attr,
            meta=np.array(json.dumps(self.meta)),
        ))  # fmt: skip

    @classmethod
    def load(cls, path: str | Path) -> OfflineDataset:
        path = Path(path)
        if not path.is_file():
            raise DataError(f"no dataset at {path} (make one with `marl-amod collect` or `marl-amod datasets`)")
        try:
            archive = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError, zipfile.BadZipFile) as exc:  # numpy's own advice is to unpickle it
            card = f" ({path.name} is a dataset card: load {path.with_suffix('.npz').name} beside it)" if path.suffix == ".json" else ""
            why = "" if isinstance(exc, ValueError) else f": {exc}"  # numpy's ValueError suggests unpickling the file
            raise DataError(f"{path} is not a marl_amod dataset (an .npz written by `marl-amod collect`){card}{why}") from None
        if not isinstance(archive, np.lib.npyio.NpzFile):  # a bare .npy array
            raise DataError(f"{path} is not a marl_amod dataset (an .npz written by `marl-amod collect`)")
        with archive as f:
            if "meta" not in f:
                raise DataError(f"{path} is not a marl_amod dataset: no meta")
            meta = json.loads(str(f["meta"]))
            if meta.get("format_version") != FORMAT_VERSION:
                raise DataError(
                    f"{path} has dataset format {meta.get('format_version')}, this version reads {FORMAT_VERSION}; "
                    "collect it again with `marl-amod collect`"
                )
            missing = [k for k in (*ARRAY_KEYS, "edge_index", "edge_attr") if k not in f]
            if missing:
                raise DataError(f"{path} is not a marl_amod dataset: missing {', '.join(missing)}")
            return cls(**{k: f[k] for k in ARRAY_KEYS}, edge_index=f["edge_index"], edge_attr=f["edge_attr"], meta=meta)

    # ------------------------------------------------------------------ views
    def global_view(self) -> dict[str, np.ndarray]:
        """The centralised learner's view: x, next_x (T, N, F) node features, ctx, next_ctx (T, 3) time
        values, action (T, N) on the simplex (the env's normalised weights), reward (T,) team reward,
        done (T,), edge_index."""
        t, n, f = len(self), self.n_agents, self.n_features
        return {
            "x": self.states[:, : n * f].reshape(t, n, f),
            "next_x": self.next_states[:, : n * f].reshape(t, n, f),
            "ctx": self.states[:, n * f :],
            "next_ctx": self.next_states[:, n * f :],
            "action": action_share(self.actions),
            "reward": self.team_rewards,
            "done": self.terminations | self.truncations,
            "edge_index": self.edge_index,
        }

    def agent_view(self) -> dict[str, dict[str, np.ndarray]]:
        """PettingZoo-style per-agent transitions: {"region_i": {observation (T, D), action (T, 1),
        reward (T,) its region's, team_reward, next_observation, termination, truncation}}."""
        return {
            f"region_{i}": {
                "observation": self.observations[:, i],
                "action": self.actions[:, i : i + 1],
                "reward": self.rewards[:, i],
                "team_reward": self.team_rewards,
                "next_observation": self.next_observations[:, i],
                "termination": self.terminations,
                "truncation": self.truncations,
            }
            for i in range(self.n_agents)
        }


def concatenate(parts: list[OfflineDataset]) -> OfflineDataset:
    """One dataset of several collected on the same city and features (DAgger's aggregate):
    episodes renumbered one part after the other, ``meta["parts"]`` keeps each part's meta."""
    if not parts:
        raise DataError("nothing to concatenate")
    first = parts[0].meta
    for p in parts[1:]:
        for key in ("scenario", "n_agents", "lookahead", "max_wait", "arrivals_now"):
            if p.meta.get(key) != first.get(key):
                raise DataError(f"datasets differ in {key}: {first.get(key)!r} and {p.meta.get(key)!r}")  # older metas lack arrivals_now
    arrays = _stack(parts)
    policies = sorted({p.meta["policy"] for p in parts})
    meta = {
        **{k: v for k, v in first.items() if k not in ("rollout_policy", "parts", "first_episode")},
        "policy": policies[0] if len(policies) == 1 else "+".join(policies),
        "streams": [r for p in parts for r in streams(p.meta)],  # DAgger rounds may revisit a stream
        "episodes": int(sum(p.meta["episodes"] for p in parts)), "transitions": int(len(arrays["team_rewards"])),
        "parts": [p.meta for p in parts],
    }  # fmt: skip
    return OfflineDataset(**arrays, edge_index=parts[0].edge_index, edge_attr=parts[0].edge_attr, meta=meta)


def _stack(parts: list[OfflineDataset]) -> dict[str, np.ndarray]:
    """The parts' arrays one after the other, episodes renumbered 0, 1, ... in that order."""
    arrays = {k: np.concatenate([getattr(p, k) for p in parts]) for k in ARRAY_KEYS}
    ids, offset = [], 0
    for p in parts:
        _, local = np.unique(p.episode_ids, return_inverse=True)  # a resumed piece's ids start at its first k
        ids.append(local.reshape(-1) + offset)
        offset += int(local.max()) + 1 if len(p) else 0
    arrays["episode_ids"] = np.concatenate(ids).astype(np.int64)
    return arrays


# What makes two pieces one collection: the same behaviour (name, options, noise, DAgger roll-out)
# logged the same way on the same city. Seeds and episode counts are what may differ.
SAME_COLLECTION = (
    "format_version", "scenario", "policy", "policy_options", "rollout_policy", "noise", "lookahead", "max_wait",
    "n_agents", "n_features", "arrivals_now",
)  # fmt: skip


def streams(meta: dict[str, Any]) -> list[list[int]]:
    """The demand streams a dataset holds, as ``[seed, first episode, count]`` ranges (older
    datasets, which lack the key, hold episodes 0..episodes-1 of their seed)."""
    if "streams" in meta:
        return [list(map(int, r)) for r in meta["streams"]]
    return [[int(meta["seed"]), int(meta.get("first_episode", 0)), int(meta["episodes"])]]


def _overlap(held: list[tuple[int, int, int]], start: int, count: int, part: int) -> tuple[int, int, int] | None:
    """(other part's index, first, last episode) shared by episodes [start, start + count) of part
    ``part`` and a range ``held`` by another part, or None. Parts are told apart by their place in
    the list, not their names (one file given twice is two parts). A part's own ranges never clash: a
    DAgger aggregate may revisit its streams, and a collection's ranges are disjoint anyway."""
    for a, b, other in held:
        if other != part and start < b and a < start + count:
            return other, max(a, start), min(b, start + count) - 1
    return None


def merge(parts: list[OfflineDataset], names: list[str] | None = None) -> OfflineDataset:
    """One dataset of pieces of the same collection (collected in parallel, or resumed later).

    Refuses (DataError) pieces that differ in what they logged (:data:`SAME_COLLECTION`, the
    graph) or that hold an episode stream twice: a duplicated episode would weigh twice in
    training and make the card's counts wrong. Pieces are ordered by their streams, so the
    order given does not matter and seed s's pieces 0..k-1, k..n-1 merge into exactly what one
    ``collect`` of n episodes of s gives. ``names`` (file names) make the errors say which piece."""
    if not parts:
        raise DataError("nothing to merge")
    names = names or [f"piece {i}" for i in range(len(parts))]
    for p, name in zip(parts, names, strict=True):
        if "parts" in p.meta:  # its own record is of several collections, and its streams may repeat
            raise DataError(f"{name} is a concatenation of {len(p.meta['parts'])} datasets (e.g. a DAgger aggregate), not a piece "
                            "of one collection: merge the pieces it was made of, or join it to others with mix-datasets")  # fmt: skip
    first = parts[0].meta
    for p, name in zip(parts[1:], names[1:], strict=True):
        for key in SAME_COLLECTION:
            if key == "policy_options" and (key in p.meta) != (key in first):  # older (or Python-API) pieces lack it
                lacking = name if key in first else names[0]
                raise DataError(f"{lacking} does not record {key} (collected by an older version or through the Python API), "
                                "so it cannot be checked to be the same collection: collect it again with `marl-amod collect`")  # fmt: skip
            if p.meta.get(key) != first.get(key):
                raise DataError(f"{names[0]} and {name} are not one collection: {key} {first.get(key)!r} != {p.meta.get(key)!r}")
        if not (np.array_equal(p.edge_index, parts[0].edge_index) and np.array_equal(p.edge_attr, parts[0].edge_attr)):
            raise DataError(f"{names[0]} and {name} are not one collection: their region graphs differ")
    held: dict[int, list[tuple[int, int, int]]] = {}  # seed -> (first, end, piece's index)
    for i, (p, name) in enumerate(zip(parts, names, strict=True)):
        for seed, start, count in streams(p.meta):
            if clash := _overlap(held.setdefault(seed, []), start, count, i):
                raise DataError(
                    f"{names[clash[0]]} and {name} both hold episodes {clash[1]}..{clash[2]} of seed "
                    f"{seed}: collect pieces with different --seed, or resume one with --first-episode"
                )
            held[seed].append((start, start + count, i))
    order = sorted(range(len(parts)), key=lambda i: streams(parts[i].meta))
    parts = [parts[i] for i in order]
    ranges = sorted(r for p in parts for r in streams(p.meta))
    joined = [ranges[0]]
    for seed, start, count in ranges[1:]:  # adjacent ranges of a seed read as one
        last = joined[-1]
        if last[0] == seed and last[1] + last[2] == start:
            last[2] += count
        else:
            joined.append([seed, start, count])
    arrays = _stack(parts)
    n = np.array([p.meta["episodes"] for p in parts], dtype=np.float64)
    mean = np.array([p.meta["episode_profit_mean"] for p in parts])
    std = np.array([p.meta["episode_profit_std"] for p in parts])
    total = float(np.average(mean, weights=n))
    steps = np.array([len(p) for p in parts], dtype=np.float64)
    seeds = sorted({r[0] for r in joined})
    meta = {
        **{k: v for k, v in parts[0].meta.items() if k not in ("first_episode", "streams")},
        "seed": seeds[0] if len(seeds) == 1 else seeds, "streams": joined,
        "episodes": int(n.sum()), "transitions": int(len(arrays["team_rewards"])),
        "episode_profit_mean": total,  # pooled mean and (population) std of the pieces' episodes
        "episode_profit_std": float(np.sqrt(max(np.average(std**2 + mean**2, weights=n) - total**2, 0.0))),
        "target_mismatch": float(np.average([p.meta["target_mismatch"] for p in parts], weights=np.maximum(steps, 1))),
    }  # fmt: skip
    return OfflineDataset(**arrays, edge_index=parts[0].edge_index, edge_attr=parts[0].edge_attr, meta=meta)


def mix(parts: list[OfflineDataset], names: list[str] | None = None) -> OfflineDataset:
    """One dataset of collections that different behaviours logged on the same city (D4RL's
    "medium-expert" kind: a good policy's episodes beside weaker or exploratory ones).

    Unlike :func:`merge`, the parts may hold the same demand streams, acted on differently; what is
    refused (DataError) is the same behaviour's episode twice (it would weigh double) and parts of
    other cities or logging (:func:`concatenate`). ``meta["policy"]`` names every behaviour (" & "),
    ``meta["parts"]`` keeps each part's meta, and no single ``noise`` is left: each part has its own."""
    if len(parts) < 2:
        raise DataError(f"a mixture needs at least two datasets, got {len(parts)}: to use one, train on it directly")
    names = names or [f"part {i}" for i in range(len(parts))]
    held: dict[tuple[str, int], list[tuple[int, int, int]]] = {}  # (behaviour, seed) -> (first, end, part's index)
    for i, (p, name) in enumerate(zip(parts, names, strict=True)):
        for behaviour, policy, seed, start, count in _behaviour_streams(p.meta):
            if clash := _overlap(held.setdefault((behaviour, seed), []), start, count, i):
                raise DataError(f"{names[clash[0]]} and {name} both hold {policy}'s episodes {clash[1]}..{clash[2]} of seed {seed}: "
                                "they would weigh twice")  # fmt: skip
            held[(behaviour, seed)].append((start, start + count, i))
    data = concatenate(parts)
    data.meta["policy"] = " & ".join(dict.fromkeys(p.meta["policy"] for p in parts))
    data.meta.pop("noise", None)
    return data


def _behaviour_streams(meta: dict[str, Any]) -> list[tuple[str, str, int, int, int]]:
    """(behaviour key, policy, seed, first episode, count) of every stream a dataset holds, read
    through a mixture or aggregate to the collections it was made of (their ``parts``)."""
    if "parts" in meta:
        return [row for part in meta["parts"] for row in _behaviour_streams(part)]
    behaviour = str(meta["policy"])  # its noise too ("mpc-forecast+noise0.005")
    if meta.get("policy_options"):
        behaviour += json.dumps(meta["policy_options"], sort_keys=True)
    return [(behaviour, str(meta["policy"]), seed, start, count) for seed, start, count in streams(meta)]


def action_share(actions: np.ndarray) -> np.ndarray:
    """(..., N) env weights -> the distribution the env normalises them to (all zeros: uniform)."""
    actions = np.asarray(actions, dtype=np.float32)
    s = actions.sum(-1, keepdims=True)
    n = actions.shape[-1]
    return np.where(s > 0, actions / np.where(s > 0, s, 1.0), np.float32(1.0 / n)).astype(np.float32)


def env_action(policy: Policy, system: FleetSystem) -> tuple[np.ndarray, np.ndarray | None]:
    """(N,) float32 action in [0, 1] that makes the env do what ``policy`` asks (module docstring),
    and the targets the policy asked for (None for a weight policy, whose action is exact)."""
    idle = system.sim.idle.astype(np.float64)
    m = idle.sum()
    n = idle.shape[0]
    if isinstance(policy, WeightPolicy):
        w = np.asarray(policy.weights(system), dtype=np.float64)
        if m <= 0:
            return np.full(n, 1.0 / n, dtype=np.float32), None
        return ((w / w.sum()) if w.sum() > 0 else idle / m).astype(np.float32), None  # all zeros: stay
    target = np.asarray(policy.target(system), dtype=np.float64)
    target = np.where(target < 0, idle, target)  # no wish: keep what is there
    if m <= 0:
        return np.full(n, 1.0 / n, dtype=np.float32), target
    # over the power of two >= M: float32 holds u / 2^k exactly, so the env's floor gives u back
    return (target / 2.0 ** np.ceil(np.log2(m))).astype(np.float32), target


class EnvActionPolicy(Policy):
    """A behaviour policy as the env takes it: its :func:`env_action` through the env's action rule.

    ``noise`` > 0 logs exploratory data: the joint action is drawn from a Dirichlet with mean the
    policy's action share and total concentration 1 / noise (plus 0.01 per region, so every region
    is sometimes asked for). The dataset's score is this policy's, so offline learners are
    compared with what they saw.
    """

    def __init__(self, policy: Policy, noise: float = 0.0) -> None:
        if not noise >= 0:
            raise ConfigError(f"action noise must be >= 0, got {noise}")
        self.policy, self.noise = policy, float(noise)
        self.name = getattr(policy, "name", "policy") + (f"+noise{noise:g}" if noise else "")

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        super().reset(system, rng)
        self.policy.reset(system, rng)

    def action(self, system: FleetSystem) -> tuple[np.ndarray, np.ndarray | None]:
        """(action, the targets the policy asked for or None); with noise, the perturbed share."""
        action, wanted = env_action(self.policy, system)
        if not self.noise:
            return action, wanted
        share = action_share(action).astype(np.float64)
        return self.rng.dirichlet(share / self.noise + 0.01).astype(np.float32), None

    def target(self, system: FleetSystem) -> np.ndarray:
        return system.targets_from_weights(self.action(system)[0].astype(np.float64))


def collection_seed(seed: int, episode: int) -> int:
    """The env seed of episode ``episode`` of a dataset seeded ``seed`` (disjoint from evaluation's)."""
    from marl_amod.algos.rollout import train_seed

    return int(train_seed(seed, episode).generate_state(1)[0])


def collect(
    city: City, policy: Policy, *, episodes: int, seed: int = 0, lookahead: int = 6, max_wait: int = 0, noise: float = 0.0,
    labeller: Policy | None = None, progress: Callable[[int], None] | None = None, first_episode: int = 0, arrivals_now: bool = False,
) -> OfflineDataset:
    """Roll ``policy`` through the PettingZoo env for ``episodes`` episodes on the collection seeds
    (``noise``: exploratory actions around the policy's, see :class:`EnvActionPolicy`).

    ``labeller`` (DAgger): the env still steps with ``policy``'s action, but the dataset records
    the labeller's env action at the same state, so an imitation learner sees the expert's answer
    on the states its own policy reaches. Rewards stay those of the steps taken; ``meta["policy"]``
    names the labeller (whose actions are logged), ``meta["rollout_policy"]`` the policy driven.

    ``first_episode`` k0 collects the seed's episodes k0..k0+episodes-1 (their ``episode_ids``),
    the same demand and policy draws as one longer collection: a piece that resumes another.
    ``arrivals_now`` logs the env's opt-in node column of the vehicles arriving now (the meta
    records it, and an offline run must set the same)."""
    from marl_amod import parallel_env
    from marl_amod.env.features import n_features

    as_count(episodes, "episodes", lower=1)
    seed, first_episode = as_seed(seed), as_count(first_episode, "first_episode")
    env = parallel_env(city, reward_mode="local", action_mode="weight", lookahead=lookahead, max_wait=max_wait, arrivals_now=arrivals_now)
    behaviour = EnvActionPolicy(policy, noise)
    expert = EnvActionPolicy(labeller) if labeller is not None else None
    agents = list(env.possible_agents)
    cols: dict[str, list] = {k: [] for k in ARRAY_KEYS}
    mismatch = steps = 0
    returns = []
    for ep in range(first_episode, first_episode + episodes):
        obs, _ = env.reset(seed=collection_seed(seed, ep))
        behaviour.reset(env.system, np.random.default_rng([seed, ep, 2]))
        if expert is not None:
            expert.reset(env.system, np.random.default_rng([seed, ep, 3]))
        state, ep_return = env.state(), env.last_outcome.reward
        while env.agents:
            t = env.system.t
            action, wanted = behaviour.action(env.system)
            logged = action
            if expert is not None:  # DAgger: the expert's answer on the learner's state
                logged, wanted = expert.action(env.system)
            if wanted is not None and env.system.sim.idle.sum() > 0:
                mismatch += int(not np.array_equal(env.system.targets_from_weights(logged.astype(np.float64)), wanted))
            steps += 1
            nxt, rew, terms, truncs, _ = env.step({a: action[i : i + 1] for i, a in enumerate(agents)})
            team = env.last_outcome.reward
            ep_return += team
            cols["observations"].append(np.stack([obs[a] for a in agents]))
            cols["actions"].append(logged)
            cols["rewards"].append([rew[a] for a in agents])
            cols["team_rewards"].append(team)
            cols["states"].append(state)
            state = env.state()
            cols["next_observations"].append(np.stack([nxt[a] for a in agents]))
            cols["next_states"].append(state)
            cols["terminations"].append(terms[agents[0]])
            cols["truncations"].append(truncs[agents[0]])
            cols["episode_ids"].append(ep)
            cols["step_ids"].append(t)
            obs = nxt
        returns.append(ep_return)
        if progress is not None:
            progress(ep)
    arrays = {k: np.asarray(v, dtype=DTYPES.get(k, np.float32)) for k, v in cols.items()}
    graph = env.graph()
    meta = {
        "format_version": FORMAT_VERSION, "scenario": city.name, "policy": expert.name if expert else behaviour.name, "noise": noise,
        "seed": seed, "first_episode": first_episode, "streams": [[seed, first_episode, episodes]], "episodes": episodes, "transitions": int(len(arrays["team_rewards"])), "lookahead": lookahead,
        "max_wait": max_wait, "n_agents": len(agents), "n_features": n_features(lookahead, arrivals_now),
        "observation_dim": int(arrays["observations"].shape[-1]), "state_dim": int(arrays["states"].shape[-1]),
        "agents": agents, "demand_seeds": "episode k: marl_amod.datasets.collection_seed(seed, k)",
        "episode_profit_mean": float(np.mean(returns)), "episode_profit_std": float(np.std(returns)),
        "target_mismatch": mismatch / max(steps, 1),
    }  # fmt: skip
    if expert is not None:
        meta["rollout_policy"] = behaviour.name
    if arrivals_now:  # absent: the default features (every older dataset)
        meta["arrivals_now"] = True
    return OfflineDataset(**arrays, edge_index=graph["edge_index"], edge_attr=graph["edge_attr"], meta=meta)


# --------------------------------------------------------------------------------------------
# The dataset card: behaviour and reference scores on the evaluation seeds
# --------------------------------------------------------------------------------------------
def card_path(path: str | Path) -> Path:
    return Path(path).with_suffix(".json")


def dataset_destination(path: str | Path, what: str = "--output") -> Path:
    """``path`` checked as a place to write a dataset, whose card goes beside it as ``.json``: a
    dataset named ``*.json`` would be overwritten by its own card."""
    path = check_destination(path, what=what)
    if path.suffix == ".json":
        raise ConfigError(f"{what} {path}: a dataset is an .npz ({path.with_suffix('.npz')}); its card goes beside it as {path.name}")
    return path


def reference_scores(city: City, episodes: int, seed: int, cache: dict | None = None) -> dict[str, dict[str, float]]:
    """ED and MPC-Oracle profit (mean, std) on the evaluation seeds; ``cache`` shares them across datasets."""
    from marl_amod.evaluation import evaluate

    key = (city.name, episodes, seed)
    if cache is not None and key in cache:
        return cache[key]
    out = {}
    for name in REFERENCES:
        p = evaluate(name, city, episodes, seed)["metrics"]["profit"]
        out[name] = {"mean": float(p["mean"]), "std": float(p["std"])}
    if cache is not None:
        cache[key] = out
    return out


def normalised_score(profit: float, references: dict[str, dict[str, float]]) -> float:
    """D4RL-style: 0 = equal distribution, 100 = MPC-Oracle (same evaluation seeds): :func:`marl_amod.metrics.normalised_score`
    with a dataset card's ``reference_scores``."""
    return metrics.normalised_score(profit, *(references[name]["mean"] for name in REFERENCES))


def write_card(
    path: str | Path, data: OfflineDataset, city: City, policy: Policy, *, eval_episodes: int = 10, eval_seed: int = 0,
    cache: dict | None = None,
) -> dict[str, Any]:
    """Score the behaviour policy (as the env takes it) and the references; write ``<dataset>.json``."""
    from marl_amod.evaluation import evaluate

    refs = reference_scores(city, eval_episodes, eval_seed, cache)
    behaviour = evaluate(EnvActionPolicy(policy, data.meta.get("noise", 0.0)), city, eval_episodes, eval_seed)["metrics"]["profit"]
    return _write_card(path, data, {
        "evaluation": {"episodes": eval_episodes, "seed": eval_seed, "note": "marl-amod evaluate --seed {seed} streams"},
        "behaviour_score": {"mean": float(behaviour["mean"]), "std": float(behaviour["std"]),
                            "normalised": normalised_score(float(behaviour["mean"]), refs)},
        "reference_scores": refs,
    })  # fmt: skip


SCORES = ("evaluation", "behaviour_score", "reference_scores")  # the card's part that is the policy's, not the data's


def _write_card(path: str | Path, data: OfflineDataset, scores: dict[str, Any]) -> dict[str, Any]:
    from marl_amod.checkpoints import env_version, git_commit

    path = Path(path)
    card = {
        "dataset": path.name, "sha256": file_sha256(path), **data.meta,
        "env_version": env_version(), "git_commit": git_commit(), **scores,
    }  # fmt: skip
    write_json(card_path(path), card)
    return card


def _own_cards(files: list[str | Path]) -> dict[str, dict[str, Any]]:
    """The cards beside ``files`` (those that have one), each checked to be its file's by sha256."""
    cards = {str(p): read_card(p) for p in files if card_path(p).is_file()}
    for name, card in cards.items():  # a card left by what was collected at that path before scores another policy
        if card.get("sha256") != file_sha256(name):
            raise DataError(f"{card_path(name)} is not the card of {name} (its sha256 is another file's): delete it, "
                            "or collect the piece again with --eval-episodes")  # fmt: skip
    return cards


def _agreeing(cards: dict[str, dict[str, Any]], keys: tuple[str, ...], what: str) -> dict[str, Any]:
    """``keys`` of the first card, after checking every other card has the same values."""
    (name0, first), *rest = cards.items()
    for name, card in rest:
        for key in keys:
            if not _same(card.get(key), first.get(key)):
                raise DataError(f"{name0} and {name} were scored differently ({key}): {what}")
    return {key: first[key] for key in keys}


def merge_cards(path: str | Path, data: OfflineDataset, pieces: list[str | Path]) -> dict[str, Any] | None:
    """The card of merged dataset ``path``: its own counts and streams, the pieces' scores.

    The behaviour and reference scores are on the evaluation streams, not the data: one piece's
    card is enough (collect the others with ``--eval-episodes 0``), and where several have one
    they must agree, and each must be its piece's by sha256 (checked; nothing is re-evaluated). None, and no card (an earlier one at ``path`` removed), when no piece has one."""
    cards = _own_cards(pieces)
    if not cards:
        card_path(path).unlink(missing_ok=True)  # a card there described the file ``path`` replaced
        return None
    return _write_card(path, data, _agreeing(cards, SCORES, "not one collection"))


def mix_cards(path: str | Path, data: OfflineDataset, parts: list[str | Path]) -> dict[str, Any] | None:
    """The card of mixture ``path`` (:func:`mix`): the reference scores its parts share, and each
    part's behaviour and score in ``behaviour_scores`` (None for a part without a card). No
    ``behaviour_score``: no one policy acted, and the parts' episode-weighted mean is no policy's
    score. Parts with cards must have been scored on the same evaluation streams. None, and no card
    (an earlier one at ``path`` removed), when no part has one."""
    cards = _own_cards(parts)
    if not cards:
        card_path(path).unlink(missing_ok=True)
        return None
    shared = _agreeing(cards, ("evaluation", "reference_scores"), "the mixture's normalised scores need one reference")
    scores = [
        {"dataset": Path(name).name, "behaviour": meta["policy"], "episodes": meta["episodes"],
         "score": _behaviour_score(cards.get(str(name)))}
        for name, meta in zip(parts, data.meta["parts"], strict=True)
    ]  # fmt: skip
    return _write_card(path, data, {**shared, "behaviour_scores": scores})


def _behaviour_score(card: dict[str, Any] | None) -> Any:
    """A part's score on a mixture's card: its behaviour's, or a mixture part's list of them (None without a card)."""
    return None if card is None else card.get("behaviour_score", card.get("behaviour_scores"))


def _same(a: Any, b: Any) -> bool:
    """Equal, floats to 1e-9 relative (pieces collected by another build may round differently)."""
    if isinstance(a, dict) and isinstance(b, dict):
        return a.keys() == b.keys() and all(_same(a[k], b[k]) for k in a)
    if isinstance(a, float) or isinstance(b, float):
        return isinstance(a, (int, float)) and isinstance(b, (int, float)) and bool(np.isclose(a, b, rtol=1e-9, atol=0))
    return a == b


def read_card(path: str | Path) -> dict[str, Any]:
    """The card beside dataset ``path`` (or the card file itself)."""
    p = Path(path)
    p = p if p.suffix == ".json" else card_path(p)
    if not p.is_file():
        raise DataError(f"no dataset card at {p} (collect writes it beside the .npz)")
    return json.loads(p.read_text())
