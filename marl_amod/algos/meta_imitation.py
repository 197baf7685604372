"""MPC-Forecast demonstrations for the meta-RL policy, and the imitation that warm-starts it.

Why. RL² from scratch leaves the recurrent policy near equal distribution: its A2C signal over
trials of ten cities is too weak to find what MPC-Forecast does (2-5% below MPC-Oracle on every
city, from the forecast alone). So the recurrent GNN first learns to *imitate* MPC-Forecast on
the training cities, then RL² (:mod:`marl_amod.algos.meta`, ``init_actor``) continues from there.

Demonstrations (:func:`collect_demos`). MPC-Forecast drives whole episodes of each **training**
city (never a held-out one) on demonstration streams of their own (:func:`demo_seed`: neither a
report nor a validation stream, nor one meta-training draws). Each decision logs what the
meta-policy would read: the task features in per-city units (:func:`~marl_amod.algos.meta.task_features`),
MPC-F's desired distribution (its targets / the idle fleet: the policy's action space) and the
rewards that follow (each region's and the team's, per-city units as :class:`~marl_amod.algos.meta.MetaAgent`
feeds them back). One ``.npz`` per city: collection is split by city and resumes by skipping
the cities already written.

Imitation (:func:`imitation_losses`). Trials of ``trial_episodes`` demonstration episodes of one
city run through the recurrent GNN with teacher forcing: the memory is carried across the
episodes, the previous action it reads is MPC-F's (x N, as the agent feeds its own), the previous
rewards are those MPC-F earned. The actor fits the Dirichlet *mean* to MPC-F's distribution
(the cross-entropy of :func:`marl_amod.algos.offline.imitation_loss`: it is the mean that the
deterministic policy plays), and the critic head the discounted return of the trial, so RL²
starts with a critic that already knows what a good trial is worth instead of one whose large
early errors flow back through the shared memory.

DAgger (``dagger_rounds``). Teacher forcing fits MPC-F on MPC-F's states; the policy's own
mistakes lead it elsewhere. Every ``dagger_every`` updates the current policy drives
``dagger_episodes`` episodes of each training city as it is deployed (:func:`collect_city` with a
``learner``), MPC-F labels the states it reached, and they join the city's demonstrations (the
previous action the memory reads is then the policy's own). A share of those trials may carry a
random demand shock, labelled by :class:`MPCToldTheShock`. Rounds are files under the run, so a
resumed run reads them back.

Event tasks (``event_tasks``). A shocked DAgger trial's episodes join the city's pool and are
teacher-forced among its other episodes, so the memory never sees its shock twice in a row
(unless ``dagger_whole_trials``: a DAgger trial is drawn whole, in its order), and the
demonstrations have none. An event task (:func:`~marl_amod.algos.meta.event_task`) is a city
whose every episode carries one fixed event: demonstrated and labelled by :class:`MPCToldTheShock`
(:func:`expert_for`), drawn as a task of its own (``event_share`` of the draws), so every
teacher-forced trial of it repeats its shock.
"""

from __future__ import annotations

import functools
import time
import zlib
from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator

from marl_amod.algos import common as C
from marl_amod.algos import meta
from marl_amod.algos import offline as O
from marl_amod.algos.meta import CityScale, task_features
from marl_amod.baselines.mpc import MPCForecast
from marl_amod.errors import DataError
from marl_amod.models.dense import Cities, DenseGraph, PackedGraphs, PaddedGraphs
from marl_amod.models.recurrent import RecurrentGNN
from marl_amod.scenario import City
from marl_amod.scenario.types import step_rows
from marl_amod.system import FleetSystem

DEMO_FORMAT = "marl_amod.meta_demos/1"


def demo_seed(seed: int, episode: int) -> np.random.SeedSequence:
    """Demand of demonstration episode k: not a report (seed, k), validation or training stream."""
    return np.random.SeedSequence([seed, episode, 6007])


def dagger_seed(seed: int, episode: int, round: int = 1) -> np.random.SeedSequence:
    """Demand of DAgger round ``round``'s episode k: apart from demonstration, report, validation and training streams."""
    return np.random.SeedSequence([seed, round, episode, 6011])


@dataclass
class CityDemos:
    """E demonstration episodes of one city, T decisions each, as tensors."""

    x: torch.Tensor  # (E, T, N, F) task features before each decision
    share: torch.Tensor  # (E, T, N) MPC-F's desired distribution (sums to 1): the label
    region_reward: torch.Tensor  # (E, T, N) each region's reward after the decision, per-city units
    reward: torch.Tensor  # (E, T) team reward after the decision, per-city units
    action: torch.Tensor  # (E, T, N) what was played (the learner's in DAgger, else MPC-F's): the next previous action

    @property
    def episodes(self) -> int:
        return int(self.x.shape[0])


ShockLabels = Literal["told", "forecast"]  # who labels a shocked DAgger trial: MPC told the shock, or MPC-Forecast


class MPCToldTheShock(MPCForecast):
    """MPC-Forecast told a trial's demand shock: it plans on the expected demand *with* the event
    (``demand_rate``), not on the draw (MPC-Oracle) nor the usual forecast. The expert for the
    shocked DAgger trials: a policy that has seen the shock in the served and unserved requests
    and the regions' rewards (in this episode and the trial's earlier ones) should plan like it."""

    name = "mpc-told-the-shock"

    def forecast(self, system: FleetSystem, steps: np.ndarray) -> np.ndarray:
        return step_rows(system.city.demand_rate, steps)


def expert_for(city: City) -> MPCForecast:
    """Who labels ``city``'s states: MPC told the event on a city that carries one (an
    :func:`~marl_amod.algos.meta.event_task`, a shocked trial, and also a scenario whose YAML lists
    ``events:``, whose every episode carries them as an event task's do; MPC-Forecast labelled those
    before the event tasks, and a demonstration file collected then keeps its labels), else
    MPC-Forecast. The bundled event scenario, ``nyc_brooklyn_event``, is a held-out city's and never
    a training task (:func:`~marl_amod.algos.meta.held_out_among`)."""
    return MPCToldTheShock() if city.meta.get("events") else MPCForecast()


def collect_city(
    city: City, episodes: int, seed: int, lookahead: int, learner: RecurrentGNN | None = None, trial_episodes: int = 1,
    seed_of: Callable[[int, int], np.random.SeedSequence] = demo_seed, shock_prob: float = 0.0, shock_labels: ShockLabels = "told",
    shock_per_task: bool = False, adaptation: meta.Adaptation = "sampled", concentration: float | None = None,
) -> dict[str, np.ndarray]:
    """``episodes`` episodes of ``city`` labelled by MPC-Forecast (by MPC told the event on a city
    that carries one: :func:`expert_for`): the arrays of :class:`CityDemos`.

    Without ``learner`` MPC-F also drives (demonstrations). With it (DAgger) the recurrent policy
    drives, as it is deployed: trials of ``trial_episodes`` episodes with its memory carried, the
    first ones played by ``adaptation`` (:func:`~marl_amod.algos.meta.adapt`), or with ``concentration``
    sampled around the mean at that total Dirichlet concentration x N (the regions), the last
    deterministic; MPC-F only labels the states it
    reaches. With ``shock_prob`` that share of the trials get a random demand shock
    (:func:`~marl_amod.algos.meta.random_shock`, the same in each of the trial's episodes), which
    the features do not show and :class:`MPCToldTheShock` labels (``shock_labels="told"``) or
    MPC-Forecast, which plans as the policy must, not knowing it (``"forecast"``). Which trials are
    shocked, and how, is one draw for every task (:func:`shock_draws`) unless ``shock_per_task``."""
    scale, n = CityScale.of(city), city.n_regions
    cols: dict[str, list[np.ndarray]] = {"x": [], "share": [], "region_reward": [], "reward": [], "action": []}
    system, policy = FleetSystem(city), expert_for(city)
    shocks = shock_draws(seed_of, seed, city.name, shock_per_task)  # which trials are shocked, and how
    agent = None
    for e in range(episodes):
        if learner is not None and e % trial_episodes == 0:  # a new trial: fresh memory, maybe a shock
            shocked = shock_prob > 0 and shocks.random() < shock_prob
            trial_city = meta.random_shock(city, shocks) if shocked else city
            system = FleetSystem(trial_city)
            policy = MPCForecast() if shocked and shock_labels == "forecast" else expert_for(trial_city)
            agent = meta.MetaAgent(learner, trial_city, lookahead)
            adapts = meta.adapting(agent, adaptation)
            if concentration is not None:
                agent.concentration, adapts = concentration * n, True
        system.reset(seed_of(seed, e))
        policy.reset(system, np.random.default_rng(seed_of(seed, e)))
        if agent is not None:
            agent.new_episode()
        sample = agent is not None and adapts and (e + 1) % trial_episodes != 0  # the trial's last episode is the deterministic one
        rows: dict[str, list[np.ndarray]] = {k: [] for k in cols}
        while not system.done:
            idle = system.sim.idle
            target = np.asarray(policy.target(system), dtype=np.float64)
            target = np.where(target < 0, idle, target)  # no wish: what is there
            share = target / target.sum() if target.sum() > 0 else np.full(n, 1.0 / n)
            rows["x"].append(task_features(system, scale, lookahead))
            if agent is None:
                played, step_target = share, target.astype(np.int64)
            else:
                with torch.no_grad():
                    played = agent.act(system, sample)[0][0]
                step_target = system.targets_from_weights(played)
            out = system.step(step_target)
            if agent is not None:
                agent.observe(out.region_reward)
            rows["share"].append(share)
            rows["action"].append(played)
            rows["region_reward"].append(out.region_reward * (n / scale.reward))
            rows["reward"].append(np.asarray(out.region_reward.sum() / scale.reward))
        for k, v in rows.items():
            cols[k].append(np.stack(v))
    return {k: np.stack(v).astype(np.float32) for k, v in cols.items()}


def demo_path(folder: str | Path, city: str) -> Path:
    return Path(folder) / f"{city}.npz"


def shock_draws(seed_of: Callable[[int, int], np.random.SeedSequence], seed: int, task: str, per_task: bool) -> np.random.Generator:
    """The stream that decides which of a task's DAgger trials are shocked, and with what shock.

    Without ``per_task`` it does not depend on the task: in a round every task's trial is shocked or
    none is, with nearly the same shock (the runs up to the whole-trials pair). With it each task
    draws its own (the task's name mixed into the seed), so a round holds shocks of many kinds."""
    base = seed_of(seed, 10**6)
    return np.random.default_rng([*base.generate_state(4), zlib.crc32(task.encode())] if per_task else base)


def collect_demos(
    folder: str | Path, cities: list[str], episodes: int, seed: int, lookahead: int, learner: RecurrentGNN | None = None,
    trial_episodes: int = 1, seed_of: Callable[[int, int], np.random.SeedSequence] = demo_seed, shock_prob: float = 0.0,
    shock_labels: ShockLabels = "told", shock_per_task: bool = False, adaptation: meta.Adaptation = "sampled",
    concentration: float | None = None, announce: Callable[[str], None] | None = None,
) -> dict[str, float]:
    """Write ``folder/<task>.npz`` for each task (a city or a :func:`~marl_amod.algos.meta.task_city`
    variant) not yet there (resumable, split by task; a file there is checked, :func:`check_demo_file`; with
    ``learner``, a DAgger round: :func:`collect_city`); returns the collection wall seconds of every
    city's file (recorded in it). ``announce`` hears each task before it is collected (minutes of
    collection would otherwise show as a training bar standing still)."""
    held = meta.held_out_among(cities)
    if held:
        raise DataError(f"demonstrations on held-out {held}: the study tests on them")
    walls = {}
    for i, name in enumerate(cities, 1):
        city = meta.task_city(name)
        path = demo_path(folder, city.name)
        if path.is_file():
            check_demo_file(path, episodes, lookahead)
        else:
            if announce is not None:
                announce(f"collecting {'its own episodes' if learner is not None else 'MPC-Forecast demonstrations'}: {name} ({i}/{len(cities)})")
            start = time.perf_counter()
            arrays = collect_city(city, episodes, seed, lookahead, learner, trial_episodes, seed_of, shock_prob, shock_labels, shock_per_task,
                                  adaptation, concentration)  # fmt: skip
            wall = time.perf_counter() - start
            path.parent.mkdir(parents=True, exist_ok=True)
            tmp = path.with_suffix(".tmp.npz")
            np.savez_compressed(tmp, **arrays, format=np.array(DEMO_FORMAT), city=np.array(name),
                                seed=np.array(seed), lookahead=np.array(lookahead), wall_s=np.array(wall))  # fmt: skip
            tmp.replace(path)
        walls[city.name] = float(np.load(path)["wall_s"])
    return walls


def check_demo_file(path: Path, episodes: int, lookahead: int) -> None:
    """An existing file is reused only if it holds what this run asks for (its episode count and
    lookahead): a run that asks for more episodes over an older folder would otherwise train on the
    old ones while its card states the new count. Another training seed's file is reused (its
    streams, :func:`demo_seed`, are apart from every report and validation stream whatever the
    seed): configs/meta/bc_dagger_place.yaml (seed 1) learns from bc.yaml's seed-0 demonstrations."""
    with np.load(path) as data:
        held = (int(data["x"].shape[0]), int(data["lookahead"]))
    if held != (episodes, lookahead):
        raise DataError(f"{path} holds {held[0]} episodes at lookahead {held[1]}; this run asks for {episodes} at lookahead "
                        f"{lookahead}: remove the file to collect it anew, or give the run another demonstrations folder")  # fmt: skip


def demo_seeds(folder: str | Path, tasks: Iterable[str]) -> list[int]:
    """The seeds the tasks' demonstration files were collected with: a file of another seed is
    reused (:func:`check_demo_file`), so the card says which streams the run learnt from."""
    seeds = set()
    for task in tasks:
        with np.load(demo_path(folder, task)) as data:
            seeds.add(int(data["seed"]))
    return sorted(seeds)


def load_demos(folder: str | Path, city: City, lookahead: int, structure: bool = False, place: bool = False,
               end_cut: bool = False) -> CityDemos:  # fmt: skip
    """One city's demonstrations, checked against the city and the run's lookahead; ``structure``
    (and ``place``) add the city-structure (and place) columns (:func:`~marl_amod.algos.meta.with_structure`:
    a function of the city and the step, so the files keep only the task features), and ``end_cut``
    removes the demand past the episode's end (:func:`~marl_amod.algos.meta.cut_at_end`)."""
    path = demo_path(folder, city.name)
    if not path.is_file():
        raise DataError(f"no demonstrations for {city.name} at {path}")
    data = np.load(path)
    if str(data["format"]) != DEMO_FORMAT or int(data["lookahead"]) != lookahead or data["x"].shape[2] != city.n_regions:
        raise DataError(f"{path}: demonstrations of another format, lookahead or city (want lookahead {lookahead}, {city.n_regions} regions)")
    action = data["action"] if "action" in data else data["share"]  # files from before DAgger: MPC-F played its label
    x = meta.stored_inputs(data["x"], city, lookahead, structure, place, end_cut)
    return CityDemos(torch.from_numpy(x), *(torch.from_numpy(data[k]) for k in ("share", "region_reward", "reward")), torch.from_numpy(action))


@dataclass
class Trials:
    """Teacher-forced trials as tensors with axes ``lead``: (B,) trials of one city, or (C, B)
    trials of C cities padded to one region count (zeros in the padded regions; :func:`packed_trials`
    puts them side by side for the model). Episode and step lead (K, T, ...), contiguous: each
    decision's inputs are one contiguous block."""

    x: torch.Tensor  # (K, T, *lead, N, F) features before each decision of each of the K episodes
    share: torch.Tensor  # (K, T, *lead, N) MPC-F's distribution: the label
    region_reward: torch.Tensor  # (K, T, *lead, N)
    reward: torch.Tensor  # (K, T, *lead) the team's; side by side (K, T, B, C), one per city
    action: torch.Tensor  # (K, T, *lead, N) what was played: the next step's previous action
    regions: int | torch.Tensor  # N, or each city's own, (C, 1, 1) padded or (N,) side by side: previous actions are shares x N

    @classmethod
    def of_city(cls, demos: CityDemos, episodes: np.ndarray) -> Trials:
        """The (K, B) demonstration episodes ``episodes`` of one city."""
        idx = torch.as_tensor(episodes)
        cols = (demos.x, demos.share, demos.region_reward, demos.reward, demos.action)
        return cls(*(c[idx].movedim(2, 1).contiguous() for c in cols), demos.x.shape[2])  # (K, B, T, ...) -> (K, T, B, ...)

    @classmethod
    def padded(cls, cities: list[Trials]) -> Trials:
        """C cities' trials (same K, T and B) as one (K, T, C, B, ...) batch, zero-padded to the largest N."""
        if len({c.x.shape[:3] for c in cities}) != 1:
            raise ValueError(f"cities padded together need the same (K, T, B): got {sorted({tuple(c.x.shape[:3]) for c in cities})}")
        sizes = [int(c.regions) for c in cities]
        n = max(sizes)

        def stack(key: str, after_region: int | None) -> torch.Tensor:
            """Cities on a new axis 2, each padded on its region axis (``after_region`` axes from the end; None: none)."""
            tensors = [getattr(c, key) for c in cities]
            if after_region is not None:
                tensors = [F.pad(t, (0, 0) * after_region + (0, n - size)) for t, size in zip(tensors, sizes, strict=True)]
            return torch.stack(tensors, dim=2)

        return cls(stack("x", 1), stack("share", 0), stack("region_reward", 0), stack("reward", None), stack("action", 0),
                   torch.tensor(sizes).view(-1, 1, 1))  # fmt: skip


@dataclass(frozen=True)
class Fit:
    """How the actor fits MPC-F's labels over teacher-forced trials (the losses below; ``Args.fit``)."""

    own_prev_action: bool = False  # the memory reads the model's own previous mean (:func:`teacher_forced`)
    imitation: O.Imitation = "ce"  # the label loss (:func:`marl_amod.algos.offline.shares_loss`)
    shortfall: float = 0.0  # with "l1": a vehicle short at a receiving region (:func:`receiving`) costs 1 + this
    end_weight: float = 0.0  # a decision in an episode's last ``end_steps`` steps counts 1 + this times (:func:`step_weights`)
    end_steps: int = 3


def imitation_losses(
    model: RecurrentGNN, demos: CityDemos, episodes: np.ndarray, graph: DenseGraph, gamma: float, fit: Fit = Fit()
) -> tuple[torch.Tensor, torch.Tensor]:
    """(actor loss, critic loss) of B trials of one city with teacher forcing; ``episodes``
    (K, B) are the demonstration episodes of each trial, the memory carried across its K episodes."""
    return trial_losses(model, Trials.of_city(demos, episodes), graph, gamma, fit)


CitiesBatch = Literal["packed", "padded", "apart"]


def cities_losses(
    model: RecurrentGNN, draws: list[tuple[CityDemos, np.ndarray, DenseGraph]], gamma: float, batch: CitiesBatch = "padded",
    fit: Fit = Fit(),
) -> tuple[torch.Tensor, torch.Tensor]:
    """The mean over the drawn cities of :func:`imitation_losses`, the cities of each trial length
    ``batch``ed: ``"packed"`` side by side in one batch (:class:`~marl_amod.models.dense.PackedGraphs`),
    one forward pass per step for all of them; ``"padded"`` the same padded to the largest city
    (:class:`~marl_amod.models.dense.PaddedGraphs`); ``"apart"`` one city after another. The same
    losses to float rounding (tested); ``benchmarks/meta_update.py`` times each."""
    if batch == "apart":
        losses = [imitation_losses(model, demos, episodes, graph, gamma, fit) for demos, episodes, graph in draws]
        return torch.stack([c for c, _ in losses]).mean(), torch.stack([v for _, v in losses]).mean()
    groups: dict[int, list[int]] = {}
    for i, (demos, _, _) in enumerate(draws):
        groups.setdefault(int(demos.x.shape[1]), []).append(i)
    actor, vl = torch.zeros(()), torch.zeros(())
    for members in groups.values():
        trials = Trials.padded([Trials.of_city(draws[i][0], draws[i][1]) for i in members])
        graphs = [draws[i][2] for i in members]
        g_actor, g_vl = trial_losses(model, trials, PackedGraphs(graphs) if batch == "packed" else PaddedGraphs(graphs), gamma, fit)
        actor, vl = actor + g_actor * len(members), vl + g_vl * len(members)  # every city has B trials of T steps: equal weights
    return actor / len(draws), vl / len(draws)


def teacher_forced(
    model: RecurrentGNN, trials: Trials, graph: DenseGraph | PaddedGraphs | PackedGraphs, own_prev_action: bool = False
) -> tuple[torch.Tensor, torch.Tensor]:
    """(Dirichlet means (K T, *lead, N), values (K T, *lead)) of ``model`` run over teacher-forced
    trials: the memory carried across the K episodes, the previous action and rewards those of the
    trials (restarting at zero with each episode). What the losses and the diagnostics read. With
    :class:`~marl_amod.models.dense.PackedGraphs` the padded trials (C, B, N_max) run packed and
    come back padded (zeros in the padding).

    ``own_prev_action``: the previous action the memory reads is the model's own mean at the step
    before (detached, as deployed) instead of what was played there. In a demonstration that is
    MPC-F's move, which predicts its next one: a channel the deployed policy never has (it reads its
    own moves), the copycat problem of imitation from histories."""
    packed = graph if isinstance(graph, PackedGraphs) else None
    if packed is not None:
        trials = packed_trials(trials, packed)
    k_eps, t_steps, *lead, n, _ = trials.x.shape
    memory, cities = model.initial_memory(n, *lead), Cities(graph, n)
    means, values = [], []
    for k in range(k_eps):
        prev_a, prev_rr, prev_r = torch.zeros(*lead, n), torch.zeros(*lead, n), torch.zeros(trials.reward.shape[2:])
        for t in range(t_steps):
            alpha, v, memory = model(trials.x[k, t], prev_a, prev_rr, prev_r, memory, graph)
            means.append(cities.share(alpha))  # the Dirichlet mean, each city's own
            values.append(v)
            played = means[-1].detach() if own_prev_action else trials.action[k, t]
            prev_a, prev_rr, prev_r = played * trials.regions, trials.region_reward[k, t], trials.reward[k, t]
    if packed is not None:  # (K T, B, N) and (K T, B, C) back to the padded (K T, C, B, N_max) and (K T, C, B)
        return packed.unpack(torch.stack(means)), torch.stack(values).movedim(-1, -2)
    return torch.stack(means), torch.stack(values)


def packed_trials(trials: Trials, packed: PackedGraphs) -> Trials:
    """Padded trials (K, T, C, B, N_max, ...) as the model's inputs side by side: (K, T, B, N, ...), rewards (K, T, B, C)."""
    return Trials(packed.pack(trials.x, features=True), packed.pack(trials.share, features=False),
                  packed.pack(trials.region_reward, features=False), trials.reward.movedim(2, 3),
                  packed.pack(trials.action, features=False), packed.regions)  # fmt: skip


def trial_losses(
    model: RecurrentGNN, trials: Trials, graph: DenseGraph | PaddedGraphs | PackedGraphs, gamma: float, fit: Fit = Fit()
) -> tuple[torch.Tensor, torch.Tensor]:
    """(actor loss, critic loss) of teacher-forced trials: the actor fits the Dirichlet mean to
    MPC-F's shares (``fit.imitation``), the critic the discounted return to the trial's end; both
    means over every decision of every trial (padded regions carry share 0 and alpha 0, so they add nothing)."""
    means, values = teacher_forced(model, trials, graph, fit.own_prev_action)
    share, rewards = trials.share.flatten(0, 1), trials.reward.flatten(0, 1)  # (K T, *lead, N), (K T, *lead)
    receives = receiving(trials.x.flatten(0, 1)[..., 0], share) if fit.imitation == "l1" and fit.shortfall else None
    actor = O.shares_loss(means, share, fit.imitation, receives, fit.shortfall)  # (K T, *lead)
    ret, running = [], torch.zeros(rewards.shape[1:])
    for rew in reversed(rewards):  # discounted return to the trial's end, as the RL critic's targets
        running = rew + gamma * running
        ret.append(running)
    target = torch.stack(ret[::-1])
    weights = step_weights(*trials.x.shape[:2], fit.end_steps, fit.end_weight).view(-1, *[1] * (actor.dim() - 1))
    return (actor * weights).mean(), F.smooth_l1_loss(values, target)


def step_weights(episodes: int, steps: int, end_steps: int, end_weight: float) -> torch.Tensor:
    """(episodes x steps,) weights of a trial's decisions, mean 1: those in each episode's last
    ``end_steps`` steps count 1 + ``end_weight`` times the others. Why: MPC-F's horizon is cut at the
    episode's end, so there it stops moving vehicles that could not pay back; the clone's late moves
    are a small share of its decisions and, unweighted, it keeps moving (Brooklyn's last three steps
    cost 0.79k an episode: docs/meta/log.md, "Where the held-out gap is now")."""
    w = torch.ones(episodes, steps)
    w[:, max(steps - end_steps, 0):] += end_weight
    return (w / w.mean()).flatten()


RECEIVE_TOL = 1e-5  # in shares: float rounding lies far below, a receiver's vehicle (1 / M) far above


def receiving(idle: torch.Tensor, share: torch.Tensor) -> torch.Tensor:
    """Whether MPC-F's shares ``share`` (..., N) ask a region for more than the idle vehicles it
    holds (``idle``, the features' first column: any per-city unit, only their proportions count):
    the regions it moves vehicles into, where a vehicle short leaves requests unserved. MPC-F's
    targets keep the idle fleet, so a receiver's share is at least one vehicle (1 / M >= 1e-4 here)
    above its idle share, and every other region's equals it to float rounding."""
    return share > idle / idle.sum(-1, keepdim=True).clamp_min(1e-12) + RECEIVE_TOL


# --------------------------------------------------------------------------------------------
# Training: imitation of MPC-Forecast over trials (registered as ``meta-bc``)
# --------------------------------------------------------------------------------------------
class Args(meta.Args):
    demos: str = "runs/meta_demos"
    """folder of the demonstration files (one per training city; collected where missing)"""
    demo_episodes: int = Field(64, ge=1)
    """MPC-Forecast episodes per training city"""
    updates: int = Field(600, ge=1)
    """gradient steps, each on ``cities_per_update`` cities x ``num_envs`` trials of ``trial_episodes`` episodes"""
    stop_after: int | None = Field(None, ge=1)
    """stop (validate, save) after this many updates without changing the schedule over ``updates``
    (step size, DAgger rounds): a replicate on a slower machine stops where the run it pairs with
    stopped at its time limit, instead of fewer updates in the same seconds"""
    eval_every: int = Field(100, ge=1)
    """updates between validations (meta-RL's adapted validation on ``val_cities``; the best is kept)"""
    lr_final: float | None = Field(None, gt=0)
    """with it, the step decays geometrically from ``lr`` to this over ``updates``: one run from
    scratch takes the large steps of the first imitation, then the small ones its later stages
    used; a function of the update, so a resumed run continues it (a time-limited run stops on its way)"""
    dagger_rounds: int = Field(0, ge=0)
    """DAgger rounds: the current model drives ``dagger_episodes`` episodes of each training city
    (trials as deployed), MPC-F labels the states it reached, and they join that city's demonstrations"""
    dagger_every: int = Field(300, ge=1)
    """updates between DAgger rounds"""
    dagger_first: int = Field(0, ge=0)
    """the update before which round 1 is collected (0: before the first; later rounds every
    ``dagger_every`` after it). From scratch, round 1 at 0 is driven by an untrained policy, to
    states the trained one never reaches: an offset spends it on a policy that imitates already"""
    dagger_episodes: int = Field(8, ge=1)
    """episodes per training city and DAgger round"""
    dagger_shock_prob: float = Field(0.0, ge=0, le=1)
    """share of the DAgger trials with a random demand shock, labelled as ``dagger_shock_labels`` says:
    the policy learns to react to what the forecast misses"""
    dagger_shock_per_task: bool = False
    """each task draws its own shocked trials and shocks (:func:`shock_draws`) instead of one draw a
    round for every task (a round all shocked or none, with nearly the same shock): more kinds of shock
    in the same share of the trials"""
    dagger_whole_trials: bool = False
    """a DAgger trial is teacher-forced whole, its episodes in the order played (:func:`draw_trials`),
    instead of episode by episode among the city's demonstrations: the memory then trains on a
    shock repeated from one episode to the next, as it meets an event over its adaptation episodes"""
    dagger_concentration: float | None = Field(None, gt=0)
    """the DAgger trials' adaptation episodes sampled around the policy's mean at this total Dirichlet
    concentration x N (the regions) instead of as ``adaptation`` says; validation and deployment keep
    ``adaptation``. Why: the plain recipe's trials sample at its untrained level, which set how widely
    they spread the hotspot's states (about 1 N to 5 N, drawn by the seed: docs/meta/log.md, "What the DAgger
    trials hold"); this sets that spread on purpose (2 N, seeds 6 and 8: the rule said no, "DAgger trials
    sampled at a set spread"). None: as ``adaptation``"""
    dagger_shock_labels: ShockLabels = "told"
    """who labels the shocked DAgger trials: MPC told the shock (``told``, :class:`MPCToldTheShock`), or
    MPC-Forecast (``forecast``), which does not know it either, so its labels are moves the policy can
    make from what it sees. Measured once, two seeds: ``forecast`` lost on both event sets of the
    selection rule (docs/meta/log.md, "MPC-Forecast's labels on the shocked DAgger trials")"""
    hotspot_variants: int = Field(0, ge=0)
    """per training city, this many :func:`~marl_amod.algos.meta.hotspot` variants as more tasks
    (one busy region's requests x ``hotspot_multipliers``, forecast included), demonstrated by
    MPC-F (``hotspot_episodes`` each) and driven in the DAgger rounds like the cities; drawn as
    often as a city unless ``hotspot_share`` says otherwise. The held-out cities' hotspots are stronger than any training city's"""
    hotspot_multipliers: tuple[float, float] = (2.0, 4.0)
    """the range (log-uniform) of the variants' multipliers"""
    hotspot_episodes: int = Field(32, ge=1)
    """MPC-Forecast demonstration episodes per hotspot variant"""
    hotspot_distinct_regions: bool = False
    """a city's variants on different regions (:func:`~marl_amod.algos.meta.hotspot_tasks`): with
    two or more, the hotspot moves instead of the same region at another multiplier"""
    hotspot_share: float | None = Field(None, gt=0, lt=1)
    """the share of an update's draws that go to the variants, hotspot, skew and sink together (the rest
    to the cities; uniform within each). None: every task as often, so with one variant a city is
    drawn half as often as without, and with two a third (a cost the held-out city without a dominant hotspot showed)"""
    skew_variants: int = Field(0, ge=0)
    """per training city, this many :func:`~marl_amod.scenario.variants.skew` variants as more tasks (the
    whole demand's shape: each region's requests out x (share / average share) ^ (gamma - 1),
    forecast included; :func:`~marl_amod.algos.meta.skew_tasks`), demonstrated by MPC-F
    (``skew_episodes`` each) and driven in the DAgger rounds like the cities; drawn with the
    hotspot variants (``hotspot_share``). The held-out cities' demand is more skewed than the training cities'"""
    skew_gammas: tuple[float, float] = (1.3, 2.5)
    """the range (log-uniform, one decimal) of the skew variants' gamma (> 1: more skewed)"""
    skew_episodes: int = Field(32, ge=1)
    """MPC-Forecast demonstration episodes per skew variant"""
    sink_variants: int = Field(0, ge=0)
    """per training city, this many :func:`~marl_amod.scenario.variants.sink` variants as more tasks
    (every origin's requests to one busy destination x ``sink_multipliers``, the other destinations
    fewer, forecast included; :func:`~marl_amod.algos.meta.sink_tasks`), demonstrated by MPC-F
    (``sink_episodes`` each) and driven in the DAgger rounds like the cities; drawn with the hotspot
    and skew variants (``hotspot_share``). Brooklyn's trips in and out of its regions differ by half
    of all trips, every training city's by at most a quarter (:func:`~marl_amod.scenario.variants.in_out_imbalance`)"""
    sink_multipliers: tuple[float, float] = (4.0, 8.0)
    """the range (log-uniform, one decimal) of the sink variants' multipliers"""
    sink_episodes: int = Field(32, ge=1)
    """MPC-Forecast demonstration episodes per sink variant"""
    event_tasks: int = Field(0, ge=0)
    """per training city, this many :func:`~marl_amod.algos.meta.event_task` tasks (one fixed
    special event of the Brooklyn kind each, not in the forecast: :func:`~marl_amod.algos.meta.event_tasks`),
    demonstrated and labelled by MPC told the event (``event_episodes`` each), driven in the DAgger
    rounds, drawn in ``event_share`` of an update's draws"""
    event_multipliers: tuple[float, float] = (3.0, 8.0)
    """the range (log-uniform) of the event tasks' surge multipliers"""
    event_episodes: int = Field(32, ge=1)
    """demonstration episodes per event task"""
    event_share: float | None = Field(None, gt=0, lt=1)
    """the share of an update's draws that go to the event tasks (uniform among them); the rest as
    without them (cities and hotspot and skew variants, ``hotspot_share``)"""
    own_prev_action: bool = False
    """the previous action the memory reads in training is the model's own (its mean at the step
    before, as deployed) instead of what was played (MPC-F's move in a demonstration): MPC-F's move
    predicts its next one, so a policy trained on it leans on a channel that at deployment carries
    its own mistakes forward (the copycat problem; ``teacher_forced``)"""
    end_weight: float = Field(0.0, ge=0)
    """a decision in an episode's last ``end_steps`` steps counts 1 + this times in the actor's loss
    (:func:`step_weights`): where MPC-F's cut horizon stops moving vehicles that could not pay back"""
    end_steps: int = Field(3, ge=1)
    """the steps at an episode's end that ``end_weight`` weighs"""
    precision: C.Precision = "fp32"
    """arithmetic of the teacher-forced passes of training (:func:`cities_losses`). bf16: under
    bfloat16 autocast on the CPU (:func:`~marl_amod.algos.common.autocast`, as SAC's ``precision``)
    the matrix products run in bf16; the weights, the optimiser, the memory carried between steps
    and every output the losses read stay float32, and the policy acts in float32 everywhere (DAgger
    rounds, validation, deployment). Why: at hidden 128 the update is matrix products near the
    core's float32 peak, and a CPU with AMX or AVX512-BF16 runs them faster in bf16: 1.52x an update
    alone at hidden 128, 1.08x at 64, the loss within 4e-6 relative (``benchmarks/meta_update.py``,
    2026-12-05); 1.3x with two runs side by side. On a CPU without those units it is slower: measure first"""
    pad_cities: bool = True
    """(with ``pack_cities: false``) an update's cities padded into one batch (the same losses to float
    rounding): 1.12-1.16x faster at hidden 64 x 16 trials per city, 1.4-1.8x at 4 trials
    (``benchmarks/meta_update.py``); False: one city after another, as fast at hidden 128 x 16 trials (0.97x padded)"""
    pack_cities: bool = False
    """an update's cities side by side in one batch, one graph that is their disjoint union
    (:class:`~marl_amod.models.dense.PackedGraphs`), instead of padded to the largest: the same losses
    to float rounding, and no product spent on padding rows (the training cities have 12-23 regions,
    so padding to the largest of four costs about a quarter more rows): at hidden 128 1.08x faster
    in float32 and 1.15x in bf16, where the update is those products; at hidden 64, where it is
    not, 1.01-1.03x (``benchmarks/meta_update.py``, 2026-12-05; a real pair of wide runs side by side
    ran no faster than a padded pair had: docs/meta/log.md, "The cities side by side"; and with small
    batches, where per-op cost dominates, 0.82x: 32 units, 2 trials a city). Off by default for that;
    ``configs/meta/bc.yaml`` sets it false too, so the recipes extending it retrain to the bit unless they set it"""

    @property
    def cities_batch(self) -> CitiesBatch:
        """How an update's cities share a batch (:func:`cities_losses`), from ``pack_cities`` and ``pad_cities``."""
        return "packed" if self.pack_cities else "padded" if self.pad_cities else "apart"

    def run_length(self) -> int:
        return min(self.updates, self.stop_after or self.updates)

    def outputs(self) -> dict[str, str]:
        return super().outputs() | {"demos": self.demos}  # missing demonstrations are collected into it

    @model_validator(mode="after")
    def _consistent(self) -> Args:
        if self.pack_cities and not self.pad_cities:
            raise ValueError("pad_cities: false (one city after another) with pack_cities: true (the cities side by side): "
                             "set pad_cities: true to pack, or pack_cities: false for one city after another")  # fmt: skip
        if twice := sorted({c for c in self.cities if self.cities.count(c) > 1}):  # an update draws from the distinct tasks
            raise ValueError(f"cities names {twice} twice: a city is one task however often it is listed (its "
                             "variants would be drawn as cities under hotspot_share)")  # fmt: skip
        if (self.event_share is None) != (not self.event_tasks):
            raise ValueError(f"event_tasks {self.event_tasks} with event_share {self.event_share}: event tasks need the share of "
                             "the draws that goes to them, and a share needs event tasks")  # fmt: skip
        if self.hotspot_share is not None and not (self.hotspot_variants or self.skew_variants or self.sink_variants):
            raise ValueError(f"hotspot_share {self.hotspot_share} without hotspot_variants, skew_variants or sink_variants: there are no variants to draw")
        if self.dagger_whole_trials and (not self.dagger_rounds or self.dagger_episodes % self.trial_episodes):
            raise ValueError(f"dagger_whole_trials with dagger_rounds {self.dagger_rounds} and dagger_episodes {self.dagger_episodes}: "
                             f"whole trials need DAgger rounds of whole trials (dagger_episodes a multiple of trial_episodes {self.trial_episodes})")  # fmt: skip
        if self.dagger_concentration is not None and not self.dagger_rounds:
            raise ValueError(f"dagger_concentration {self.dagger_concentration} sets how DAgger trials sample: it needs dagger_rounds > 0")
        if self.dagger_shock_per_task and not (self.dagger_rounds and self.dagger_shock_prob):
            raise ValueError(f"dagger_shock_per_task with dagger_rounds {self.dagger_rounds} and dagger_shock_prob {self.dagger_shock_prob}: "
                             "no DAgger trial is shocked, so there is nothing to draw per task")  # fmt: skip
        if self.dagger_rounds and self.dagger_first >= self.updates:
            raise ValueError(f"dagger_first {self.dagger_first} is not before the last update ({self.updates}): no DAgger round "
                             "would run (lower dagger_first, raise updates, or dagger_rounds: 0)")  # fmt: skip
        return self

    @property
    def fit(self) -> Fit:
        return Fit(self.own_prev_action, self.imitation, self.shortfall_weight, self.end_weight, self.end_steps)

    def ignored_keys(self) -> dict[str, str]:
        return {**super().ignored_keys(), "episodes": "imitation takes no env episodes; set updates",
                "shock_prob": "demonstrations are of the usual demand", "entropy_coef": "imitation has no entropy term",
                "gae_lambda": "the critic fits the demonstrations' returns"}  # fmt: skip


def load_all(args: meta.Args, cities: dict[str, City], names: list[str] | None = None) -> dict[str, tuple[CityDemos, DenseGraph]]:
    """The demonstrations (and ``more_demos``) and dense graph of every task (default: the training cities)."""
    data = {}
    for name in args.cities if names is None else names:
        demos = [load_run_demos(folder, cities[name], args) for folder in [args.demos, *args.more_demos]]
        data[name] = (functools.reduce(joined, demos), meta.city_graph(cities[name]))
    return data


def load_run_demos(folder: str | Path, city: City, args: meta.Args) -> CityDemos:
    """One city's episodes in ``folder`` with the columns the run's model reads."""
    return load_demos(folder, city, args.lookahead, args.city_features, args.place_features, args.end_cut)


def joined(a: CityDemos, b: CityDemos) -> CityDemos:
    """One city's episodes of both (demonstrations and DAgger rounds)."""
    return CityDemos(*(torch.cat([x, y]) for x, y in zip(vars(a).values(), vars(b).values(), strict=True)))


def dagger_round(
    args: Args, model: RecurrentGNN, k: int, data: dict[str, tuple[CityDemos, DenseGraph]], cities: dict[str, City],
    announce: Callable[[str], None] | None = None,
) -> float:
    """DAgger round ``k`` on every task in ``data`` (collected unless its files exist: resumable) added
    to ``data``; its collection wall seconds."""
    folder = Path(args.run_dir) / "dagger" / f"round{k}"
    told = None if announce is None else (lambda text: announce(f"DAgger round {k}: {text}"))
    with torch.no_grad():
        walls = collect_demos(folder, list(data), args.dagger_episodes, args.seed, args.lookahead, learner=model,
                              trial_episodes=args.trial_episodes, seed_of=functools.partial(dagger_seed, round=k), shock_prob=args.dagger_shock_prob,
                              shock_labels=args.dagger_shock_labels, shock_per_task=args.dagger_shock_per_task,
                              adaptation=args.adaptation, concentration=args.dagger_concentration, announce=told)  # fmt: skip
    for name in data:
        demos, graph = data[name]
        data[name] = (joined(demos, load_run_demos(folder, cities[name], args)), graph)
    return sum(walls.values())


def draw_trials(demos: CityDemos, args: meta.Args, rng: np.random.Generator, dagger_from: int | None = None) -> np.ndarray:
    """(K, B) episodes of the city's pool for ``num_envs`` trials of ``trial_episodes`` episodes, each drawn alike.

    With ``dagger_from`` (the pool's first DAgger episode; after it, DAgger trials of K episodes in the
    order played) a trial whose first draw is a DAgger episode is that episode's whole trial, in its order,
    and the other trials draw demonstrations only. DAgger's share of the episodes stays what it is
    without it; what changes is that the memory reads a DAgger trial as the policy played it, a shocked
    trial's shock repeated in each episode, as K adaptation episodes on an event repeat the event."""
    k = args.trial_episodes
    idx = rng.integers(demos.episodes, size=(k, args.num_envs))
    if dagger_from is None or dagger_from >= demos.episodes:
        return idx
    whole = idx[0] >= dagger_from
    idx[:, whole] = dagger_from + (idx[0, whole] - dagger_from) // k * k + np.arange(k)[:, None]
    stray = (idx >= dagger_from) & ~whole  # a DAgger episode drawn into a demonstration trial
    idx[stray] = rng.integers(dagger_from, size=int(stray.sum()))
    return idx


def tasks(args: Args) -> tuple[list[str], list[str]]:
    """(the training cities, their hotspot, skew then sink variants): the tasks an update draws from."""
    return list(args.cities), hotspot_names(args) + skew_names(args) + sink_names(args)


def hotspot_names(args: Args) -> list[str]:
    """The training cities' hotspot variants (none unless ``hotspot_variants``)."""
    return meta.hotspot_tasks(args.cities, args.hotspot_variants, args.hotspot_multipliers, args.seed, args.hotspot_distinct_regions)


def skew_names(args: Args) -> list[str]:
    """The training cities' skew variants (none unless ``skew_variants``)."""
    return meta.skew_tasks(args.cities, args.skew_variants, args.skew_gammas, args.seed)


def sink_names(args: Args) -> list[str]:
    """The training cities' sink variants (none unless ``sink_variants``)."""
    return meta.sink_tasks(args.cities, args.sink_variants, args.sink_multipliers, args.seed)


def event_names(args: Args) -> list[str]:
    """The training cities' event tasks (none unless ``event_tasks``)."""
    return meta.event_tasks(args.cities, args.event_tasks, args.event_multipliers, args.seed)


def draw_task(names: list[str], plain: int, share: float | None, rng: np.random.Generator) -> str:
    """One update's task: of ``names`` (the first ``plain`` the cities, the rest their variants)
    uniformly, or with ``share`` a variant that often and a city otherwise (uniform within each)."""
    if share is None:
        return names[int(rng.integers(len(names)))]
    group = names[plain:] if rng.random() < share else names[:plain]
    return group[int(rng.integers(len(group)))]


def draw_run_task(args: Args, names: list[str], plain: int, events: list[str], rng: np.random.Generator) -> str:
    """One update's task of the run's ``names`` (cities, hotspot and skew variants, then ``events``): an
    event task in ``event_share`` of the draws (uniform among them), else :func:`draw_task` over the
    rest; without event tasks exactly :func:`draw_task`'s draws (the same generator calls)."""
    if events and rng.random() < args.event_share:
        return events[int(rng.integers(len(events)))]
    return draw_task(names[: len(names) - len(events)], plain, args.hotspot_share, rng)


def lr_at(args: Args, step: int) -> float:
    """The step size of update ``step`` (``lr_final``: geometric decay over ``updates``)."""
    if args.lr_final is None:
        return args.lr
    return args.lr * (args.lr_final / args.lr) ** (min(step, args.updates) / args.updates)


def started_rounds(args: Args, step: int) -> int:
    """DAgger rounds begun before update ``step`` (round k starts at update ``dagger_first`` + (k - 1) x ``dagger_every``)."""
    return min(args.dagger_rounds, max(0, -(-(step - args.dagger_first) // args.dagger_every)))


def round_due(args: Args, step: int) -> int:
    """The DAgger round that starts before update ``step``, or 0 if none does."""
    since = step - args.dagger_first
    k = since // args.dagger_every + 1
    return k if since >= 0 and since % args.dagger_every == 0 and k <= args.dagger_rounds else 0


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Collect what is missing, imitate MPC-Forecast over trials, keep the best validated model."""
    meta.check_tasks(args)
    torch.set_num_threads(args.threads)
    C.seed_everything(args.seed)
    plain, variants = tasks(args)
    events = event_names(args)
    # every task and validation city built before any collection: a bad name or setting fails now, not after the demonstrations
    cities = {name: meta.task_city(name) for name in dict.fromkeys([*plain, *variants, *events, *args.val_cities])}
    step = 0

    def announce(text: str) -> None:  # what the run is doing while no update moves its bar
        if progress is not None:
            progress(step, args.updates, {"status": text})

    walls = collect_demos(args.demos, plain, args.demo_episodes, args.seed, args.lookahead, announce=announce)
    n_hot, n_skew = args.hotspot_variants * len(plain), args.skew_variants * len(plain)  # each *_tasks names exactly that many per city, or refuses
    hot, skewed, sinks = variants[:n_hot], variants[n_hot : n_hot + n_skew], variants[n_hot + n_skew :]
    walls |= collect_demos(args.demos, hot, args.hotspot_episodes, args.seed, args.lookahead, announce=announce)
    walls |= collect_demos(args.demos, skewed, args.skew_episodes, args.seed, args.lookahead, announce=announce)
    walls |= collect_demos(args.demos, sinks, args.sink_episodes, args.seed, args.lookahead, announce=announce)
    walls |= collect_demos(args.demos, events, args.event_episodes, args.seed, args.lookahead, announce=announce)
    data = load_all(args, cities, [*plain, *variants, *events])
    names = list(data)
    dagger_from = {name: data[name][0].episodes if args.dagger_whole_trials else None for name in names}  # DAgger rounds join after these
    model = meta.make_model(args)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    rng = np.random.default_rng([args.seed, 23])
    prior_wall = 0.0
    best, warm = meta.warm_start(args, model, cities, resume)  # init_actor: continue an imitation (e.g. with DAgger rounds)
    if resume:
        st = C.load_state(resume, "meta-bc", args)
        if st.get("tasks", names) != names:  # its updates and DAgger rounds are of those tasks (older states: not recorded)
            raise DataError(f"{resume} trained on the tasks {st['tasks']}; this config names {names}: resume with the run's "
                            "cities, seed, hotspot and skew settings (hotspot_variants, hotspot_multipliers, hotspot_distinct_regions, "
                            "skew_variants, skew_gammas, sink_variants, sink_multipliers) and event settings (event_tasks, event_multipliers)")  # fmt: skip
        for key, drawn in (("hotspot_share", "variants"), ("event_share", "event tasks"), ("dagger_whole_trials", "DAgger trials"),
                           ("dagger_shock_per_task", "DAgger shocks"), ("adaptation", "DAgger trials' adaptation episodes"),
                           ("dagger_concentration", "DAgger trials' adaptation episodes")):  # fmt: skip
            if st.get(key, Args.model_fields[key].default) != getattr(args, key):  # older states: as the defaults
                raise DataError(f"{resume} drew its {drawn} with {key} {st.get(key)}; this config sets "
                                f"{getattr(args, key)}: resume with the run's setting (the card names it)")  # fmt: skip
        C.restore(resume, st, model=model, opt=opt)
        step, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
        rng.bit_generator.state = st["city_rng"]
    log = C.Logger(args.run_dir, resume_from=step if resume else None)
    timer = C.Timer(prior_wall)
    book = meta.MetaBook(args, model, cities, log, timer, best, progress)

    def save() -> tuple[Path, int]:
        C.save_state(C.state_path(args), args, algorithm="meta-bc", model=model.state_dict(), opt=opt.state_dict(), episode=step,
                     best_val=book.best.value, best_actor=book.best.state, wall_s=timer(), city_rng=rng.bit_generator.state, tasks=names,
                     hotspot_share=args.hotspot_share, event_share=args.event_share, dagger_whole_trials=args.dagger_whole_trials,
                     dagger_shock_per_task=args.dagger_shock_per_task, adaptation=args.adaptation,
                     dagger_concentration=args.dagger_concentration)  # fmt: skip
        return C.state_path(args), step

    dagger_wall = sum(dagger_round(args, model, k, data, cities) for k in range(1, started_rounds(args, step) + 1))  # resumed: read back
    last = args.run_length()
    amp = C.autocast(args.precision)
    with C.interruptible(save):
        while step < last:
            if k := round_due(args, step):
                dagger_wall += dagger_round(args, model, k, data, cities, announce)
            draws = []
            for _ in range(args.cities_per_update):
                name = draw_run_task(args, names, len(plain), events, rng)
                demos, graph = data[name]
                draws.append((demos, draw_trials(demos, args, rng, dagger_from[name]), graph))
            with amp():
                ce, vl = cities_losses(model, draws, args.gamma, args.cities_batch, args.fit)
            for group in opt.param_groups:
                group["lr"] = lr_at(args, step)
            opt.zero_grad()
            (ce + args.value_coef * vl).backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
            opt.step()
            step += 1
            stats = {"loss/imitation": ce.item(), "loss/value": vl.item()}
            if book.close(step, args.updates, stats, step % args.eval_every == 0 or step >= last, save):
                break
    log.close()
    model.load_state_dict(book.best.state)
    extra = book.card_fields() | {"updates": step, "demonstrations": {"policy": "mpc-forecast", "cities": list(args.cities), "episodes_per_city": args.demo_episodes,
             "seeds": demo_seeds(args.demos, walls), "collection_wall_s": round(sum(walls.values()), 1)}, **warm}  # fmt: skip
    if hot:
        extra["demonstrations"] |= {"hotspot_variants": hot, "episodes_per_variant": args.hotspot_episodes}
    if skewed:
        extra["demonstrations"] |= {"skew_variants": skewed, "skew_gammas": list(args.skew_gammas), "episodes_per_skew_variant": args.skew_episodes}
    if sinks:
        extra["demonstrations"] |= {"sink_variants": sinks, "sink_multipliers": list(args.sink_multipliers), "episodes_per_sink_variant": args.sink_episodes}
    if variants and args.hotspot_share is not None:
        extra["demonstrations"] |= {"variants_share_of_draws": args.hotspot_share}
    if events:
        extra["demonstrations"] |= {"event_tasks": events, "episodes_per_event_task": args.event_episodes, "event_share_of_draws": args.event_share,
                                    "event_expert": MPCToldTheShock.name}  # fmt: skip
    if args.dagger_rounds:
        extra["dagger"] = {"rounds": started_rounds(args, step), "episodes_per_city": args.dagger_episodes, "shock_prob": args.dagger_shock_prob,
                           "shock_labels": args.dagger_shock_labels, "whole_trials": args.dagger_whole_trials,
                           "shock_per_task": args.dagger_shock_per_task,
                           "collection_wall_s": round(dagger_wall, 1)}  # fmt: skip
    return meta.finish(args, model, timer(), 0, config_path, algorithm="meta-bc", extra=extra)
