"""Diagnostics of the meta-policy (docs/meta/README.md): the imitation gap, K, the special event.

* ``gap``: on training cities, the cross-entropy of the policy's Dirichlet mean above the labels'
  own entropy, on MPC-Forecast's states (the last 8 stored demonstrations) and on the states
  the policy reaches itself (8 episodes it drives as deployed, labelled by MPC-F: a DAgger
  collection on streams of their own). Tells compounding error from under-fit.
* ``k``: the profit gap to MPC-Oracle on the held-out cities (report episodes, the tables'
  MPC-Oracle rows) for each number K of adaptation episodes; with ``--validation``, the
  validation return on the training cities instead (the only place K may be chosen).
* ``heldout``: the imitation error on training (validation) and held-out cities alike, on fresh
  MPC-Forecast states (demand streams of their own: no city's training data) and on the states
  the policy reaches itself: the cross-entropy above the labels' entropy and the share of the
  idle fleet a step sent elsewhere than MPC-F's targets (half the L1 distance of the
  distributions); then each input's range in every held-out city against the training
  demonstrations' (per-feature quantiles). Does the policy imitate worse where it was not trained,
  and which inputs lie outside what it saw?
* ``where``: where the held-out profit gap to MPC-Forecast comes from, on validation episodes
  (seed 1000, never the report streams): served trips, fares, trip and rebalancing cost by step
  and by region, and the share of the idle fleet each asks for.
* ``hotspot``: for each task (a city, or a hotspot variant ``<city>~hot<r>x<m>``), its busiest
  region's share of the day's requests (x N), what MPC-F sends there and what the policy sends
  (teacher-forced on 4 fresh MPC-F episodes), and with ``--multiplier m`` the city with that
  region x m (``meta.hotspot``) beside it, with both profit gaps to MPC-F on validation episodes.
  With ``--own`` also on the states the policy reaches itself (8 episodes driven as deployed,
  labelled by MPC-F): does a hotspot it fills on MPC-F's states stay filled on its own path?
* ``event``: the share of the idle fleet each policy asks for in the Brooklyn event's surge
  regions and halved hotspots, inside the event window and outside, and the requests left
  unserved at the surge: does the memory notice the shock?
* ``transplant``: which inputs differ on the policy's own path: trials driven by MPC-F and by the
  policy on the same demand streams, MPC-F's inputs (previous moves, rewards, each feature group)
  moved into the policy's own trials, then teacher-forced: the busiest region's share and the
  share misplaced (docs/meta/log.md, "The policy's own moves as its previous action").
* ``hold``: what the policy's moves at the episode's start and end are worth: its validation profit
  with no rebalancing (every region keeps its idle vehicles) at the first step, at the last
  ``--last`` steps, and at both, every other step its own, beside MPC-Forecast's on the same
  episodes (docs/meta/log.md, "Where the held-out gap is now").
* ``steps``: step by step at a city's busiest region, the share the policy asks for on its own path
  and on MPC-F's (MPC-F playing) beside MPC-F's, and the requests served there; then the profit the
  policy gains with MPC-F's targets played in each of ``--windows`` (docs/meta/log.md, "San Francisco,
  step by step").
* ``rule``: the selection rule the meta arms are judged by, in one command: the hotspot, skew and
  sink variants, the training-city events, the shaped set, the hotspot events and the sink events (:data:`RULE_SETS`,
  20 validation episodes each) for ``--reference`` (the tables' meta-rl by default) and the candidate
  ``--policy``, each set's file under ``--rule-dir`` (reused when it holds the same policy; the tables'
  meta-rl's own are shipped in ``docs/meta/rule/``, with its recipe's other pair, which the reference
  averages in), then the measures paired by episode and the verdict: every one must pass
  (docs/meta/log.md). ``--workers 2`` runs the tasks over two processes.
* ``recipes``: two recipes on the rule's sets from records the rule kept, each recipe's pairs averaged
  episode by episode (``--first`` and ``--second``: record prefixes, ``docs/meta/rule/cut01``), the
  second against the first in the rule's table. It decides nothing: does a difference outlive the seeds?
* ``misread``: each evented task (``--cities``: event tasks ``<city>~ev...`` or scenarios with
  ``events:``) scored with the memory adapted on the evented day, on the usual day and not at all:
  whether the memory misreads the event or drifts with any adaptation; with ``--freeze 6-13`` the
  memory does not move at those steps while adapting, to find where the misreading is written
  (docs/meta/log.md, "What the memory does on the event").
* ``told``: what knowing an event is worth (``--cities``, default the Brooklyn event; report episodes, seed 0): MPC-Forecast,
  MPC told the event, MPC-Oracle, the meta-policy as deployed and with the event in its forecast inputs, each paired with
  MPC-Forecast; the largest gain an adaptation could bring a policy that plays MPC-Forecast's plan, and whether the
  meta-policy acts on the demand it is shown (docs/meta/log.md, "What knowing the event is worth").
* ``tasks``: each episode's profit of the policy (K = ``--k``, 3 as deployed) and of MPC-Forecast (not
  told an event task's event) on training-city tasks (hotspot variants ``<city>~hot<r>x<m>``, skew variants ``<city>~skew<gamma>``,
  event tasks ``<city>~ev...``: ``meta.task_city``), validation episodes (seed 1000), written to
  ``--out`` (with ``--mpc-from`` an earlier file's MPC-F profits of the same tasks and episodes are reused);
  ``compare A.json B.json``: per file the mean gap to MPC-F over the hotspot variants (and, apart,
  the skew variants) and the mean profit over the event tasks, and B - A paired by episode with its standard error (over
  the episodes, each the tasks' mean: ``paired_se``): what a selection rule reads
  (docs/meta/log.md, "The event tasks"). That error is the episodes' noise for two fixed
  policies only: two training seeds of one recipe differed by 8-9 times it on the events and skew variants (log.md, "A second
  training seed"), so compare a candidate against more than one run of the recipe it would replace.
* ``spread``: each rule set's mean for single training runs of one recipe (``files``: the folders of ``rule --policy
  <one member .pt>`` runs) and its sd over them, written to ``docs/meta/rule/runs.json`` (``--out``); ``rule`` and
  ``recipes`` then print each difference in those units beside the episodes' SE, which is for two fixed policies and
  3-11 times smaller than the spread between runs (docs/meta/log.md, "How far apart one recipe's runs lie").
* ``runs``: two recipes by their single runs (``--first``, ``--second``: comma-separated rule folders of single runs,
  as ``spread`` reads them): each set's mean over each recipe's runs and the difference, its standard error from the
  first recipe's spread between runs (sd x sqrt(1/n1 + 1/n2)); how an arm is read against the plain recipe once it
  has more than one pair (docs/meta/log.md, "The prior arm, a second pair"). It decides nothing.
* ``track``: whether the rule's sets rank runs as the held-out cities do (``--first``: rule folders of single runs,
  ``--second``: each run's ``transfer-table --strategy meta-rl`` folder, same order): Spearman's rank correlation
  per set and held-out measure, signed so +1 agrees (docs/meta/log.md, "Which rule sets track the held-out cities").
  ``--cities``: each set read on those cities' tasks only (the cities a recipe left out of training), and on the rule's
  other cities' apart; ``--plot``: the tables as heatmaps. It decides nothing, and it must not choose a proxy: read on the test cities, it only says which sets to distrust.
* ``trials``: what DAgger collected (``files``: run folders holding ``dagger/round*/<task>.npz``), by the
  episode's place in its trial (1..K-1 adaptation, K scored): the share of the idle fleet the played action
  sends elsewhere than MPC-F's label, at each task's busiest region (MPC-F's largest mean label share over the
  trial) the share asked against the label's and the requests left unserved, the spread of the idle vehicles
  there (sd over the trial's episodes, per step: coverage) and the episode's return (per-city units); then each
  run's trials paired with the first run's where both played the same days (same seed), and the adaptation
  episodes' misplaced share round by round (docs/meta/log.md, "What the DAgger trials hold").

    python benchmarks/meta_diagnostics.py gap [--policy policies/meta_rl_l1_cities.pt]
    python benchmarks/meta_diagnostics.py k --ks 0,1,3,10 [--validation]
    python benchmarks/meta_diagnostics.py event
    python benchmarks/meta_diagnostics.py heldout [--cities nyc_brooklyn,porto]
    python benchmarks/meta_diagnostics.py where [--cities nyc_brooklyn]
    python benchmarks/meta_diagnostics.py hotspot --cities porto,washington_dc --multiplier 3 --episodes 6
    python benchmarks/meta_diagnostics.py hotspot --cities san_francisco --episodes 0 --own
    python benchmarks/meta_diagnostics.py transplant --cities san_francisco,nyc_brooklyn --episodes 8
    python benchmarks/meta_diagnostics.py hold --cities nyc_brooklyn,san_francisco --last 3
    python benchmarks/meta_diagnostics.py steps --cities san_francisco --policy policies/meta_rl_l1_whole_ensemble.yaml
    python benchmarks/meta_diagnostics.py tasks --cities porto~hot1x2.5,porto~ev7+12x6@6-14dr1+2x0.5 --episodes 20 --out A.json
    python benchmarks/meta_diagnostics.py compare A.json B.json
    python benchmarks/meta_diagnostics.py misread --cities nyc_brooklyn_event,porto~ev7+12x6@6-14dr1+2x0.5 --episodes 20 --policy policies/meta_rl_l1_whole_ensemble.yaml
    python benchmarks/meta_diagnostics.py told --episodes 10 --policy policies/meta_rl_l1_whole_ensemble.yaml
    python benchmarks/meta_diagnostics.py rule --policy runs/ens/candidate.yaml --workers 2 [--reference policies/meta_rl_l1_whole_ensemble.yaml]
    python benchmarks/meta_diagnostics.py spread runs/rule_seed0 runs/rule_seed1 runs/rule_rep4 runs/rule_rep5 runs/rule_rep6 runs/rule_rep6_again runs/rule_rep8
    python benchmarks/meta_diagnostics.py trials runs/meta_bc_dagger_l1_whole_rep8 runs/meta_bc_dagger_l1_whole_mean8
    python benchmarks/meta_diagnostics.py recipes --first docs/meta/rule/cut01,docs/meta/rule/cut23 --second docs/meta/rule/replicate,docs/meta/rule/reference
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
from collections.abc import Callable, Collection, Iterator
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from functools import partial
from pathlib import Path
from typing import Any

import numpy as np
import torch
from scipy.stats import sem

from marl_amod.algos import meta
from marl_amod.algos import meta_imitation as mi
from marl_amod.baselines.mpc import MPCForecast, MPCOracle
from marl_amod.batch_system import BatchFleetSystem
from marl_amod.evaluation import evaluate
from marl_amod.models.dense import DenseGraph
from marl_amod.scenario import City, load_city
from marl_amod.scenario.variants import base_city
from marl_amod.system import FleetSystem, StepOutcome
from marl_amod.transfer import META_POLICY, STUDIES, run_strategy

VAL_CITIES = ("porto", "nyc_man_north", "shenzhen_north", "washington_dc")


def fresh(tag: int) -> Callable[[int, int], np.random.SeedSequence]:
    """Demand streams of their own (``tag``): no city's demonstrations, validation or report episodes."""
    return lambda s, e: np.random.SeedSequence([s, e, tag])


def labelled(model: meta.RecurrentGNN, task: City, episodes: int, lookahead: int, seed_of: Callable[[int, int], np.random.SeedSequence],
             learner: meta.RecurrentGNN | None = None) -> mi.CityDemos:  # fmt: skip
    """``episodes`` episodes of ``task`` labelled by MPC-F (by MPC told the event on a task that
    carries one, an event task or an ``events:`` scenario: ``mi.expert_for``), with the inputs
    ``model`` reads: driven by that expert, or with ``learner`` by the policy as deployed (trials of
    4, memory carried)."""
    structure, place = meta.features_read(model, lookahead)
    got = mi.collect_city(task, episodes, 99, lookahead, learner=learner, trial_episodes=4, seed_of=seed_of)
    got["x"] = meta.stored_inputs(got["x"], task, lookahead, structure, place, model.end_cut)
    return mi.CityDemos(*(torch.from_numpy(got[k]) for k in ("x", "share", "region_reward", "reward", "action")))


def gap(policy: str, demos: str, episodes: int = 8) -> None:
    model, card = meta.load_meta(policy)
    lookahead = card["lookahead"]
    structure, place = meta.features_read(model, lookahead)
    for name in VAL_CITIES:
        city, graph = load_city(name), meta.city_graph(load_city(name))
        mine = labelled(model, city, episodes, lookahead, fresh(777), learner=model)
        stored = mi.load_demos(demos, city, lookahead, structure, place, model.end_cut)
        theirs = mi.CityDemos(*(v[-episodes:] for v in vars(stored).values()))
        row = [imitation_error(model, d, graph)[0] for d in (theirs, mine)]
        print(f"{name:22s} cross-entropy above the labels' entropy: MPC-F's states {row[0]:.3f}, its own {row[1]:.3f}", flush=True)


def k_sweep(policy: str, ks: list[int]) -> None:
    for study, names in STUDIES.items():
        ref = json.load(open(f"docs/meta/{study}.json"))["targets"]
        for name in names:
            oracle = ref[name]["mpc-oracle"]["metrics"]["profit"]["mean"]
            gaps = [100 * (1 - run_strategy("meta-rl", name, meta_policy=policy, adapt_episodes=k)["metrics"]["profit"]["mean"] / oracle) for k in ks]
            print(f"{name:24s} " + " ".join(f"K{k}: {g:5.1f}%" for k, g in zip(ks, gaps, strict=True)), flush=True)


def k_validation(policy: str, ks: list[int]) -> None:
    model, card = meta.load_meta(policy)
    a = card["args"]
    torch.manual_seed(0)
    for k in ks:
        scores = []
        with torch.no_grad():
            for name in a["val_cities"]:
                city, b = load_city(name), a["eval_episodes"]
                agent, system = meta.MetaAgent(model, city, card["lookahead"], b), BatchFleetSystem(city, b)
                if k:
                    meta.run_trials(agent, system, [[meta.adapt_seed(a["eval_seed"], e, j) for j in range(b)] for e in range(k)])
                last = meta.run_trials(agent, system, [[np.random.SeedSequence([a["eval_seed"], j]) for j in range(b)]], sample=False)
                scores.append(float(last.profits.mean()) / (city.horizon * agent.scale.reward))
        print(f"K={k}: validation {np.mean(scores):.4f}", flush=True)


def drive(pol: Any, city: City, episode_seed: np.random.SeedSequence, policy_rng: np.random.Generator) -> tuple[FleetSystem, Iterator]:
    """One episode of ``pol`` on ``city``, reset now: the system, and its steps as they are played
    (the step's t, the share of the idle fleet asked, the outcome); a target of -1 keeps a region's idle vehicles."""
    system = FleetSystem(city)
    system.reset(episode_seed)
    pol.reset(system, policy_rng)

    def steps() -> Iterator[tuple[int, np.ndarray, StepOutcome]]:
        while not system.done:
            t = system.sim.t
            want = np.asarray(pol.target(system), dtype=np.float64)
            want = np.where(want < 0, system.sim.idle, want)
            share = want / max(want.sum(), 1.0)
            yield t, share, system.step(want.astype(np.int64))

    return system, steps()


def event(policy: str, surge: tuple[int, ...] = (8, 10), hotspots: tuple[int, ...] = (5, 6), window: range = range(6, 14), episodes: int = 10) -> None:
    for name in ("nyc_brooklyn", "nyc_brooklyn_event"):
        city = load_city(name)
        makers = {"meta K=3": lambda c=city: meta.load_policy(policy, c, 3), "meta K=0": lambda c=city: meta.load_policy(policy, c, 0),
                  "mpc-forecast": MPCForecast, "mpc-oracle": MPCOracle}  # fmt: skip
        for label, make in makers.items():
            pol, inside, outside, unserved = make(), [], [], []
            for k in range(episodes):
                system, steps = drive(pol, city, np.random.SeedSequence([0, k]), np.random.default_rng(k))
                for t, share, _ in steps:
                    (inside if t in window else outside).append([share[list(surge)].sum(), share[list(hotspots)].sum()])
                    if t in window:
                        unserved.append(system.sim.requests().sum(-1)[list(surge)].sum())
            i, o = np.mean(inside, 0), np.mean(outside, 0)
            print(f"{name:20s} {label:12s} surge share in/out {i[0]:.3f}/{o[0]:.3f}  hotspots in/out {i[1]:.2f}/{o[1]:.2f}  "
                  f"unserved at the surge {np.mean(unserved):5.1f}", flush=True)  # fmt: skip


def feature_names(lookahead: int, structure: bool, place: bool) -> list[str]:
    """The columns of :func:`~marl_amod.algos.meta.task_features` (and the two rewards the memory reads)."""
    steps = range(1, lookahead + 1)
    names = ["idle", *(f"supply+{k}" for k in steps), *(f"value+{k}" for k in steps), "served", "unserved", "t"]
    if structure:
        names += [*(f"inflow+{k}" for k in steps), "trip time", "neighbour reb time", "drive cost/fare"]
    if place:
        names += ["reb time to", "reb time from", "share out", "share in", "share fleet"]
    return names + ["region reward", "team reward"]


def columns(d: mi.CityDemos) -> np.ndarray:
    """(decisions x regions, F + 2) every input per region and decision, with the two rewards."""
    x = d.x.numpy().reshape(-1, d.x.shape[-1])
    team = np.broadcast_to(d.reward.numpy()[..., None], d.region_reward.shape).reshape(-1, 1)
    return np.concatenate([x, d.region_reward.numpy().reshape(-1, 1), team], axis=1)


def forced(model: meta.RecurrentGNN, d: mi.CityDemos, graph: DenseGraph, own_prev_action: bool = False) -> tuple[torch.Tensor, torch.Tensor]:
    """(the policy's Dirichlet means, MPC-F's shares), (decisions, B, N), teacher-forced over trials
    of 4 episodes (the memory carried as in training; ``own_prev_action``: reading its own means as
    the previous actions, :func:`~marl_amod.algos.meta_imitation.teacher_forced`)."""
    trials = mi.Trials.of_city(d, np.arange(d.episodes).reshape(-1, 4).T)
    with torch.no_grad():
        means = mi.teacher_forced(model, trials, graph, own_prev_action)[0]
    return means, trials.share.flatten(0, 1)


def misplaced(means: torch.Tensor, share: torch.Tensor) -> float:
    """The share of the idle fleet a step sends elsewhere than MPC-F's targets (half the L1 distance)."""
    return float(0.5 * (means - share).abs().sum(-1).mean())


def imitation_error(model: meta.RecurrentGNN, d: mi.CityDemos, graph: DenseGraph) -> tuple[float, float]:
    """(cross-entropy above the labels' entropy, share of the idle fleet sent elsewhere) over trials of 4."""
    means, share = forced(model, d, graph)
    ce = -(share * torch.log(means.clamp_min(1e-8))).sum(-1) + (share * torch.log(share.clamp_min(1e-12))).sum(-1)
    return float(ce.mean()), misplaced(means, share)


def heldout(policy: str, demos: str, cities: list[str], episodes: int = 8) -> None:
    model, card = meta.load_meta(policy)
    lookahead = card["lookahead"]
    structure, place = meta.features_read(model, lookahead)
    pool = np.concatenate([columns(mi.load_demos(demos, load_city(n), lookahead, structure, place, model.end_cut)) for n in meta.TRAIN_CITIES])
    lo, mid, hi = np.quantile(pool, [0.01, 0.5, 0.99], axis=0)
    ranges = {}
    for name in cities:
        city = meta.task_city(name)  # a city or a hotspot variant of one
        graph, row = meta.city_graph(city), []
        for learner in (None, model):
            d = labelled(model, city, episodes, lookahead, fresh(778), learner=learner)
            row += imitation_error(model, d, graph)
            if learner is None:
                ranges[name] = columns(d)
        held = " (held out)" if name in meta.HELD_OUT else ""
        print(f"{name:24s} MPC-F's states: CE {row[0]:.3f}, misplaced {row[1]:.3f}; its own: CE {row[2]:.3f}, misplaced {row[3]:.3f}{held}", flush=True)
    print(f"\n{'input':20s} {'train q01 / q50 / q99':>24s}  " + "  ".join(f"{n[:18]:>18s}" for n in ranges))
    print(f"{'':20s} {'':>24s}  " + "  ".join(f"{'median (out)':>18s}" for _ in ranges))
    for j, label in enumerate(feature_names(lookahead, structure, place)):
        cells = [f"{np.median(v[:, j]):8.3f} ({np.mean((v[:, j] < lo[j]) | (v[:, j] > hi[j])):4.0%})" for v in ranges.values()]
        print(f"{label:20s} {lo[j]:7.3f} / {mid[j]:6.3f} / {hi[j]:7.3f}  " + "  ".join(f"{c:>18s}" for c in cells), flush=True)


def hotspot(policy: str, cities: list[str], multiplier: float | None, episodes: int, seed: int = 1000, own: bool = False) -> None:
    model, card = meta.load_meta(policy)
    lookahead = card["lookahead"]
    for name in cities:
        city = meta.task_city(name)
        region = city.meta.get("hotspot", {}).get("region", int(meta.place_table(city)[:, 2].argmax()))
        for task in (city, meta.hotspot(city, region, multiplier)) if multiplier else (city,):
            line = f"{task.name:34s} share out {meta.place_table(task)[region, 2]:.2f}"
            # on MPC-F's states (4 episodes, one trial); with ``own`` also on the policy's (8: 2 trials of 4)
            for learner, n in ((None, 4), (model, 8)) if own else ((None, 4),):
                means, share = forced(model, labelled(model, task, n, lookahead, fresh(778), learner=learner), meta.city_graph(task))
                off = misplaced(means, share)
                if learner is None:
                    line += f"  MPC-F sends {share[..., region].mean():.3f}  the policy {means[..., region].mean():.3f}  misplaced {off:.3f}"
                else:
                    line += f"  | on its own states: it sends {means[..., region].mean():.3f}, MPC-F's label {share[..., region].mean():.3f}, misplaced {off:.3f}"
            if episodes:
                mine = evaluate(meta.load_policy(policy, task, seed=seed), task, episodes, seed)["metrics"]["profit"]["mean"]
                theirs = evaluate(MPCForecast(), task, episodes, seed)["metrics"]["profit"]["mean"]
                line += f"  gap to MPC-F {100 * (1 - mine / theirs):.1f}% ({episodes} validation episodes)"
            print(line, flush=True)


def _transplanted(model: meta.RecurrentGNN, graph: DenseGraph, region: int, label: str, d: mi.CityDemos, own_prev_action: bool = False) -> None:
    means, share = forced(model, d, graph, own_prev_action)
    print(f"  {label:44s} r{region} {means[..., region].mean():.3f} ({share[..., region].mean():.3f})  misplaced {misplaced(means, share):.3f}", flush=True)


def transplant(policy: str, cities: list[str], episodes: int = 8) -> None:
    """Which inputs make the policy's own path differ from MPC-F's? Trials driven by MPC-F and by the
    policy on the same demand streams (each decision has a twin with the same requests); MPC-F's
    inputs moved group by group into the policy's own trials, then teacher-forced: the share asked
    for the busiest region (MPC-F's label on those states) and the share misplaced."""
    model, card = meta.load_meta(policy)
    lookahead = card["lookahead"]
    names = feature_names(lookahead, *meta.features_read(model, lookahead))
    group_of = {"idle": "idle vehicles", "supply": "supply", "value": "expected demand", "served": "served, unserved", "unserved": "served, unserved", "t": "clock"}
    groups: dict[str, list[int]] = {}
    for j, column in enumerate(names):  # "supply+3" is in the group of "supply"; the city's own columns are the same on both paths
        if label := group_of.get(column.split("+")[0]):
            groups.setdefault(label, []).append(j)
    for name in cities:
        city = meta.task_city(name)
        region, graph = int(meta.place_table(city)[:, 2].argmax()), meta.city_graph(city)
        theirs = labelled(model, city, episodes, lookahead, fresh(778))
        own = labelled(model, city, episodes, lookahead, fresh(778), learner=model)
        rows = {"nothing (all its own)": own,
                "moves as the previous actions": replace(own, action=theirs.action),
                "rewards as the previous rewards": replace(own, region_reward=theirs.region_reward, reward=theirs.reward)}  # fmt: skip
        for label, cols in groups.items():
            x = own.x.clone()
            x[..., cols] = theirs.x[..., cols]
            rows[label] = replace(own, x=x)
        rows["whole trials (MPC-F's own states)"] = theirs
        rows["whole trials, the policy's moves as previous"] = replace(theirs, action=own.action)
        print(f"{name}: the policy's own trials ({episodes} episodes) with MPC-F's ...: the busiest region asked (MPC-F's label)")
        for label, d in rows.items():
            _transplanted(model, graph, region, label, d)
        _transplanted(model, graph, region, "whole trials, its own means as previous", theirs, own_prev_action=True)  # as own_prev_action trains


def task_profits(policy: str, name: str, episodes: int, seed: int, k: int, mpc: list[float] | None = None) -> dict[str, list[float]]:
    """One task's per-episode profits of ``policy`` (adapted over ``k`` episodes) and of MPC-Forecast
    (``mpc`` when given, an earlier record's: MPC-F is the slow half). Pure in its arguments, so the
    tasks of a rule can run in any order and any process."""
    task = meta.task_city(name)
    mine = [m["profit"] for m in evaluate(meta.load_policy(policy, task, k, seed=seed), task, episodes, seed)["per_episode"]]
    theirs = mpc or [m["profit"] for m in evaluate(MPCForecast(), task, episodes, seed)["per_episode"]]
    return {"policy": mine, "mpc-forecast": theirs}


def in_workers(jobs: list[tuple[Any, ...]], workers: int) -> Iterator[dict[str, list[float]]]:
    """:func:`task_profits` of each job, in order; over ``workers`` processes when more than one (spawned:
    torch and HiGHS do not survive a fork cleanly), so a two-core machine measures a rule in half the time."""
    if workers <= 1 or len(jobs) <= 1:
        yield from (task_profits(*job) for job in jobs)
        return
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn")) as pool:
        yield from pool.map(task_profits, *zip(*jobs, strict=True))


def tasks(policy: str, names: list[str], episodes: int, out: str, seed: int = 1000, mpc_from: str | None = None, k: int = 3,
          workers: int = 1) -> None:  # fmt: skip
    """Per-episode profits of ``policy`` (adapted over ``k`` episodes) and MPC-Forecast on each task, into ``out``;
    with ``mpc_from`` (an earlier ``out`` of the same episodes) MPC-F's are read from there, not rerun."""
    record: dict[str, Any] = {"policy": policy, "seed": seed, "episodes": episodes, "k": k, "tasks": {}}
    old = json.load(open(mpc_from)) if mpc_from else {"tasks": {}}
    if mpc_from and (old["seed"], old["episodes"]) != (seed, episodes):
        raise SystemExit(f"--mpc-from {mpc_from}: other episodes (seed {old['seed']}, {old['episodes']} episodes)")
    jobs = [(policy, name, episodes, seed, k, old["tasks"].get(name, {}).get("mpc-forecast")) for name in names]
    for name, got in zip(names, in_workers(jobs, workers), strict=True):
        record["tasks"][name] = got
        print_task(name, got)
    with open(out, "w") as f:
        json.dump(record, f, indent=1)


def print_task(name: str, got: dict[str, list[float]]) -> None:
    mine, theirs = np.mean(got["policy"]), np.mean(got["mpc-forecast"])
    print(f"{name:44s} policy {mine:10,.0f}  MPC-F {theirs:10,.0f}  gap {100 * (1 - mine / theirs):5.2f}%", flush=True)


def paired_se(d: np.ndarray) -> tuple[float, float]:
    """The standard error of ``d.mean()``, ``d`` (tasks, episodes) paired differences: (the pairs
    taken as independent, as the docs' first rules read it; over the episodes, each the tasks' mean).
    The second is the one for a fixed set of tasks whose episode k all come from one seed: a task's
    steady gain is not noise, and an episode that moves every task is one draw."""
    return float(sem(d, axis=None)), float(sem(d.mean(0)))


def per_episode(r: dict[str, Any], group: list[str], what: str) -> np.ndarray:
    """(tasks, episodes) of a ``tasks`` record: the gap to MPC-F in % (``gap``) or the profit (``profit``)."""
    p = np.array([r["tasks"][n]["policy"] for n in group], dtype=np.float64)
    m = np.array([r["tasks"][n]["mpc-forecast"] for n in group], dtype=np.float64)
    return 100 * (1 - p / m) if what == "gap" else p


def compare(files: list[str]) -> None:
    """The rule's numbers of each ``tasks`` file, and the second against the first paired by episode."""
    recs = [json.load(open(f)) for f in files]
    names = list(recs[0]["tasks"])
    if any(list(r["tasks"]) != names or (r["episodes"], r["seed"], r.get("k", 3)) != (recs[0]["episodes"], recs[0]["seed"], recs[0].get("k", 3))
           for r in recs):  # fmt: skip
        raise SystemExit("compare: the files hold other tasks, episodes, seeds or adaptation episodes (k)")
    events = [n for n in names if meta.EVENT in n]  # an event on a variant (``porto~hot1x3~ev...``) is an event
    hot, skewed, sinks = ([n for n in names if kind in n and n not in events] for kind in (meta.HOTSPOT, meta.SKEW, meta.SINK))
    for group, what, unit in ((hot, "gap", "% gap to MPC-F"), (skewed, "gap", "% gap to MPC-F"), (sinks, "gap", "% gap to MPC-F"), (events, "profit", " profit")):
        if not group:
            continue
        vals = [per_episode(r, group, what) for r in recs]
        for f, v in zip(files, vals, strict=True):
            print(f"{f}: mean{unit} over {len(group)} tasks x {v.shape[1]} episodes: {v.mean():.3f}  (per task: "
                  + ", ".join(f"{n} {x:.2f}" if what == "gap" else f"{n} {x:,.0f}" for n, x in zip(group, v.mean(1), strict=True)) + ")")  # fmt: skip
        if len(vals) == 2:
            d = vals[1] - vals[0]  # paired: the same task and episode
            pooled, by_episode = paired_se(d)
            print(f"  {files[1]} - {files[0]}: {d.mean():+.3f}{unit}, paired SE by episode {by_episode:.3f} ({d.shape[1]} episodes x "
                  f"{d.shape[0]} tasks; the {d.size} pairs as independent: {pooled:.3f})"
                  + (f"; {100 * d.mean() / vals[0].mean():+.2f}% of the first's mean" if what == "profit" else ""))  # fmt: skip
        if what == "profit":
            m = np.array([recs[0]["tasks"][n]["mpc-forecast"] for n in group], dtype=np.float64)
            print(f"  MPC-Forecast (not told the events): mean profit {m.mean():.1f}")


# The selection rule's task sets (docs/meta/log.md, from "Stronger hotspots for the second member" on): validation
# cities only, 20 validation episodes each, K = 3. What each measures and how: a gap to MPC-F to lower, or a profit to raise.
RULE_SETS: dict[str, tuple[str, list[str]]] = {
    "hotspot variants x2.5": ("gap", [
        "porto~hot1x2.5", "porto~hot2x2.5", "nyc_man_north~hot5x2.5", "nyc_man_north~hot3x2.5", "shenzhen_north~hot14x2.5",
        "shenzhen_north~hot8x2.5", "washington_dc~hot0x2.5", "washington_dc~hot4x2.5"]),
    "skew variants 2.7": ("gap", ["porto~skew2.7", "nyc_man_north~skew2.7", "shenzhen_north~skew2.7", "washington_dc~skew2.7"]),
    "sink variants x6": ("gap", [
        "porto~sink2x6", "porto~sink5x6", "nyc_man_north~sink5x6", "nyc_man_north~sink4x6", "shenzhen_north~sink8x6",
        "shenzhen_north~sink14x6", "washington_dc~sink4x6", "washington_dc~sink7x6"]),
    "training-city events": ("profit", [
        "porto~ev7+12x6@6-14dr1+2x0.5", "porto~ev7+12x6@11-19dr1+2x0.5", "nyc_man_north~ev1+2x6@6-14dr3+5x0.5",
        "nyc_man_north~ev1+2x6@11-19dr3+5x0.5", "shenzhen_north~ev5+15x6@6-14dr8+14x0.5", "shenzhen_north~ev5+15x6@11-19dr8+14x0.5",
        "washington_dc~ev1+3x6@6-14dr0+4x0.5", "washington_dc~ev1+3x6@11-19dr0+4x0.5"]),
    "shaped set": ("gap", [  # shaped like the held-out cities: San Francisco's hotspot share, Brooklyn's in-out imbalance
        "porto~hot1x3.2", "porto~sink2x12", "nyc_man_north~hot5x4.6", "nyc_man_north~sink5x12", "shenzhen_north~hot14x5.7",
        "shenzhen_north~sink8x12", "washington_dc~hot0x3.3", "washington_dc~sink4x12"]),
    "hotspot events": ("profit", [  # the Brooklyn event on the shaped set's hotspots: the dominant region halved, two small x6
        "porto~hot1x3.2~ev7+12x6@6-14dr1+2x0.5", "porto~hot1x3.2~ev7+12x6@11-19dr1+2x0.5",
        "nyc_man_north~hot5x4.6~ev1+2x6@6-14dr3+5x0.5", "nyc_man_north~hot5x4.6~ev1+2x6@11-19dr3+5x0.5",
        "shenzhen_north~hot14x5.7~ev5+15x6@6-14dr8+14x0.5", "shenzhen_north~hot14x5.7~ev5+15x6@11-19dr8+14x0.5",
        "washington_dc~hot0x3.3~ev1+3x6@6-14dr0+4x0.5", "washington_dc~hot0x3.3~ev1+3x6@11-19dr0+4x0.5"]),
    "sink events": ("profit", [  # the same events on the shaped set's sinks (Brooklyn's in-out imbalance), the one set whose
        "porto~sink2x12~ev7+12x6@6-14dr1+2x0.5", "porto~sink2x12~ev7+12x6@11-19dr1+2x0.5",  # misreading ranked two pairs as Brooklyn's did
        "nyc_man_north~sink5x12~ev1+2x6@6-14dr3+5x0.5", "nyc_man_north~sink5x12~ev1+2x6@11-19dr3+5x0.5",
        "shenzhen_north~sink8x12~ev5+15x6@6-14dr8+14x0.5", "shenzhen_north~sink8x12~ev5+15x6@11-19dr8+14x0.5",
        "washington_dc~sink4x12~ev1+3x6@6-14dr0+4x0.5", "washington_dc~sink4x12~ev1+3x6@11-19dr0+4x0.5"]),
}  # fmt: skip


RULE_SEED, RULE_K = 1000, 3  # the validation streams, and the adaptation episodes as deployed
RULE_RECORDS = Path(__file__).resolve().parent.parent / "docs" / "meta" / "rule"  # the tables' meta-rl's sets, as the rule measured them
# The rule's reference is the tables' recipe, not one draw of it: where the reference is the tables' pair, each set's
# record is that pair and the recipe's other pair (RULE_RECORDS' replicate_*.json: the whole-trials recipe's seeds 0
# and 1) averaged episode by episode (docs/meta/log.md, "The tables' recipe, two fresh seeds", "Whole DAgger trials,
# two fresh seeds"). The earlier recipe's two pairs are kept beside them (cut01_*, cut23_*) for ``recipes``.
RULE_AVERAGED_WITH = META_POLICY  # the tables' pair, whose recipe the replicate shares (its records hold this path: tested)


def averaged(records: list[dict[str, Any]]) -> dict[str, Any]:
    """One set's records of several policies as one, their profits averaged episode by episode: a recipe
    measured over its pairs of seeds rather than one draw (the same tasks and episodes, so the same MPC-F:
    refused otherwise)."""
    first = records[0]
    if any(list(r["tasks"]) != list(first["tasks"]) or r["episodes"] != first["episodes"] for r in records):
        raise SystemExit("the records hold other tasks or episodes than the first's")
    tasks_ = {name: {"policy": list(np.mean([r["tasks"][name]["policy"] for r in records], axis=0)), "mpc-forecast": t["mpc-forecast"]}
              for name, t in first["tasks"].items()}  # fmt: skip
    return {**first, "policy": " + ".join(r["policy"] for r in records), "tasks": tasks_}


def rule_file(out_dir: str | Path, label: str, name: str) -> Path:
    """Where ``rule`` keeps the ``tasks`` record of one set for the reference or the candidate."""
    return Path(out_dir) / f"{label}_{name.replace(' ', '_')}.json"


def rule_rows(reference: dict[str, dict[str, Any]], candidate: dict[str, dict[str, Any]]) -> list[dict[str, Any]]:
    """Each rule set's means, the candidate's paired difference and its standard error over the episodes,
    and whether it passes: a gap to MPC-F below the reference's, or a profit at least the reference's."""
    rows = []
    for name, (what, tasks_) in RULE_SETS.items():
        ref, cand = per_episode(reference[name], tasks_, what), per_episode(candidate[name], tasks_, what)
        d = cand - ref  # paired: the same task and episode
        passes = bool(cand.mean() < ref.mean()) if what == "gap" else bool(cand.mean() >= ref.mean())
        rows.append({"set": name, "what": what, "reference": float(ref.mean()), "candidate": float(cand.mean()),
                     "diff": float(d.mean()), "se": paired_se(d)[1], "passes": passes})  # fmt: skip
    return rows


def set_value(what: str, value: float) -> str:
    """A rule set's value as its tables print it: a gap in % to three places, a profit in whole dollars."""
    return f"{value:.3f}%" if what == "gap" else f"{value:,.0f}"


def print_rule_table(rows: list[dict[str, Any]], reference: str, candidate: str, spread: dict[str, float] | None = None) -> bool:
    """:func:`rule_rows` as a markdown table; whether every set passes. With ``spread`` (each set's sd between
    single training runs of one recipe: :func:`runs_spread`) a column puts each difference in those units: the
    SE beside it is the episodes' only, for two fixed policies."""
    extra = (" difference / runs' sd |", "---|") if spread else ("", "")
    print(f"| rule set | {reference} | {candidate} | difference (SE by episode) | passes |{extra[0]}\n|---|---|---|---|---|{extra[1]}")
    for r in rows:
        unit = "%" if r["what"] == "gap" else ""
        fmt = partial(set_value, r["what"])
        in_runs = f" {r['diff'] / spread[r['set']]:+.1f} |" if spread else ""
        print(f"| {r['set']} ({'gap to MPC-F' if r['what'] == 'gap' else 'profit'}) | {fmt(r['reference'])} | {fmt(r['candidate'])} "
              f"| {r['diff']:+.3f}{unit} ({r['se']:.3f}) | {'yes' if r['passes'] else '**no**'} |{in_runs}")  # fmt: skip
    if spread:
        print(f"runs' sd: each set's sd over the single runs in {RUN_SPREAD.name} (a pair of runs spreads about 1/sqrt(2) of it)")
    return all(r["passes"] for r in rows)


RUN_SPREAD = Path(__file__).resolve().parent.parent / "docs" / "meta" / "rule" / "runs.json"  # the tables' recipe, run by run


def set_tasks(name: str, cities: list[str] | None = None) -> list[str]:
    """Rule set ``name``'s tasks, or those on ``cities`` only (by the city each task varies): a set read on the
    cities a run never trained on, apart from those it did."""
    tasks_ = RULE_SETS[name][1]
    return tasks_ if cities is None else [t for t in tasks_ if base_city(t) in cities]


def run_means(folder: str | Path, cities: list[str] | None = None) -> dict[str, Any]:
    """One single run's mean on each rule set (its ``rule --policy <one .pt>`` folder's ``candidate_<set>.json``),
    each set restricted to ``cities``' tasks when given."""
    records = {name: json.loads(rule_file(folder, "candidate", name).read_text()) for name in RULE_SETS}
    return {"policy": records[next(iter(RULE_SETS))]["policy"],
            **{name: float(per_episode(r, set_tasks(name, cities), RULE_SETS[name][0]).mean()) for name, r in records.items()}}  # fmt: skip


def spread(rule_dirs: list[str], out: str | Path = RUN_SPREAD) -> dict[str, Any]:
    """Each rule set's mean for single training runs of one recipe (``rule_dirs``: ``rule --policy <one .pt>``
    folders, their ``candidate_<set>.json``), written to ``out`` with each set's sd over the runs: how far
    one recipe's runs lie apart, the unit :func:`print_rule_table` reads differences in."""
    runs = {str(folder): run_means(folder) for folder in rule_dirs}
    if len(runs) < 2:
        raise SystemExit("spread needs the rule folders of at least two single runs")
    sd = {name: float(np.std([r[name] for r in runs.values()], ddof=1)) for name in RULE_SETS}
    summary = {"runs": runs, "sd": sd}
    Path(out).write_text(json.dumps(summary, indent=1))
    print("| rule set | " + " | ".join(Path(f).name for f in runs) + " | sd |\n|---|" + "---|" * (len(runs) + 1))
    for name in RULE_SETS:
        print(f"| {name} | " + " | ".join(f"{r[name]:.3f}" for r in runs.values()) + f" | {sd[name]:.3f} |")
    print(f"wrote {out}")
    return summary


def arm_runs(first: list[str], second: list[str]) -> list[dict[str, Any]]:
    """Two recipes by their single runs (rule folders, as :func:`spread` reads them), deciding nothing:
    each set's mean over each recipe's runs, the difference (second - first) and its standard error
    sd x sqrt(1/n1 + 1/n2), sd the first recipe's spread between runs (the yardstick: the first is the
    recipe with the most runs, the plain one), and the difference in those SEs; beside it, in Welch's SE
    from both recipes' spreads, since an arm's runs may lie further apart than the plain recipe's."""
    if len(first) < 2 or not second:
        raise SystemExit("runs needs at least two single runs of the first recipe (the yardstick) and one of the second")
    a, b = ([run_means(f) for f in group] for group in (first, second))
    rows = []
    for name, (what, _) in RULE_SETS.items():
        x, y = np.array([r[name] for r in a]), np.array([r[name] for r in b])
        diff, se = float(y.mean() - x.mean()), float(x.std(ddof=1) * np.sqrt(1 / len(x) + 1 / len(y)))
        welch = float(np.sqrt(x.var(ddof=1) / len(x) + y.var(ddof=1) / len(y))) if len(y) > 1 else float("nan")
        rows.append({"set": name, "what": what, "first": float(x.mean()), "second": float(y.mean()), "diff": diff, "se": se,
                     "z": diff / se if se > 0 else float("nan"), "welch_se": welch, "welch_z": diff / welch if welch > 0 else float("nan"),
                     "second_runs": [float(v) for v in y]})  # fmt: skip
    print(f"| rule set | first: {len(a)} runs | second: {len(b)} runs | each run of the second | difference (SE from the first's spread) | in SEs "
          "| in SEs from both spreads |\n|---|---|---|---|---|---|---|")  # fmt: skip
    for r in rows:
        fmt = partial(set_value, r["what"])
        print(f"| {r['set']} | {fmt(r['first'])} | {fmt(r['second'])} | {' / '.join(fmt(v) for v in r['second_runs'])} "
              f"| {r['diff']:+.3f} ({r['se']:.3f}) | {r['z']:+.1f} | {r['welch_z']:+.1f} |")  # fmt: skip
    print("a gap is better lower, a profit higher; SE = the first recipe's sd between runs x sqrt(1/n1 + 1/n2); "
          "from both spreads: Welch's, sqrt(sd1^2/n1 + sd2^2/n2), where the second has two runs or more")
    return rows


def heldout_measures(folder: str | Path) -> dict[str, tuple[str, float]]:
    """The meta-rl row of a ``transfer-table`` output folder (``intercity.json``, ``event.json``): each held-out city's
    ("gap", gap to MPC-Oracle in %) and the event's ("profit", profit)."""
    intercity, event = (json.loads((Path(folder) / f"{study}.json").read_text())["targets"] for study in ("intercity", "event"))
    gaps = {city: ("gap", 100 * (1 - rows["meta-rl"]["metrics"]["profit"]["mean"] / rows["mpc-oracle"]["metrics"]["profit"]["mean"]))
            for city, rows in intercity.items()}  # fmt: skip
    return gaps | {city: ("profit", rows["meta-rl"]["metrics"]["profit"]["mean"]) for city, rows in event.items()}


def track(rule_dirs: list[str], heldout_dirs: list[str], cities: list[str] | None = None) -> dict[str, dict[str, tuple[float, float]]]:
    """Whether the rule's sets track the held-out cities, over many runs (deciding nothing): run i's rule folder
    (``rule_dirs[i]``, as :func:`spread` reads it) beside its held-out measures (``heldout_dirs[i]``, a
    ``transfer-table --strategy meta-rl`` folder); per set and held-out measure, Spearman's rank correlation
    and its p-value, each signed so that +1 means the set ranks the runs as the held-out measure does (a
    lower gap, a higher profit, better on both). ``cities``: each set read on those cities' tasks only (e.g. the
    cities a recipe left out of training)."""
    from scipy.stats import spearmanr

    if len(rule_dirs) != len(heldout_dirs) or len(rule_dirs) < 4:
        raise SystemExit(f"track needs one held-out folder per rule folder, four runs or more (got {len(rule_dirs)} and {len(heldout_dirs)})")

    def worse_up(what: str, values: list[float]) -> np.ndarray:  # a gap as it is, a profit negated: higher is worse for both
        return np.array(values) * (1 if what == "gap" else -1)

    if cities is not None and (empty := [name for name in RULE_SETS if not set_tasks(name, cities)]):
        raise SystemExit(f"track --cities {','.join(cities)}: no task of {', '.join(empty)} is on those cities")
    sets, held = [run_means(f, cities) for f in rule_dirs], [heldout_measures(f) for f in heldout_dirs]
    measures = list(held[0])
    table = {}
    for name, (what, _) in RULE_SETS.items():
        x = worse_up(what, [r[name] for r in sets])
        table[name] = {}
        for m in measures:
            rho, p = spearmanr(x, worse_up(held[0][m][0], [h[m][1] for h in held]))
            table[name][m] = (float(rho), float(p))
    print(f"Spearman's rank correlation over {len(sets)} runs{' (each set on ' + ', '.join(cities) + ' only)' if cities else ''}, "
          "+1: the set ranks the runs as the held-out measure does\n"
          "| rule set | " + " | ".join(measures) + " |\n|---|" + "---|" * len(measures))  # fmt: skip
    for name, row in table.items():
        print(f"| {name} | " + " | ".join(f"{rho:+.2f} (p {p:.3f})" for rho, p in row.values()) + " |")
    return table


def track_figure(panels: dict[str, dict[str, dict[str, tuple[float, float]]]]):  # noqa: ANN201 - a matplotlib Figure
    """:func:`track`'s tables side by side (e.g. the cities a recipe never trained on, and those it did): one
    heatmap per table, rule sets by held-out measures, +1 (the set ranks runs as the measure does) in blue."""
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels) + 2.6, 4.6), sharey=True, squeeze=False, layout="constrained")
    for ax, (title, table) in zip(axes[0], panels.items(), strict=True):
        sets, measures = list(table), list(next(iter(table.values())))
        rho = np.array([[table[name][m][0] for m in measures] for name in sets])
        image = ax.imshow(rho, cmap="RdBu", vmin=-1, vmax=1, aspect="auto")
        for (i, j), value in np.ndenumerate(rho):
            ax.text(j, i, f"{value:+.2f}", ha="center", va="center", fontsize=8, color="white" if abs(value) > 0.6 else "black")
        ax.set_xticks(range(len(measures)), [m.replace("_", " ").replace("shenzhen downtown", "SZ") for m in measures], rotation=25, ha="right")
        ax.set_yticks(range(len(sets)), sets)
        ax.set_title(title.replace(",", ", "), fontsize=10)
    fig.colorbar(image, ax=axes[0].tolist(), label="Spearman's rho (+1: ranks runs as the held-out city)", shrink=0.9)
    return fig


def runs_spread(path: Path = RUN_SPREAD) -> dict[str, float] | None:
    """Each rule set's sd between single runs (:func:`spread`), if it has been measured."""
    return json.loads(path.read_text())["sd"] if path.is_file() else None


def recipes(first: list[str], second: list[str]) -> bool:
    """Two recipes on the rule's sets, each its pairs' kept records averaged episode by episode (a record
    prefix is a rule dir and label: ``runs/rule6/candidate`` reads ``runs/rule6/candidate_<set>.json``): the
    rule's table for the second against the first. It decides nothing; it says whether a difference
    between two pairs outlives the seeds."""
    def pooled(prefixes: list[str]) -> dict[str, dict[str, Any]]:
        return {name: averaged([json.loads(rule_file(Path(p).parent, Path(p).name, name).read_text()) for p in prefixes]) for name in RULE_SETS}

    return print_rule_table(rule_rows(pooled(first), pooled(second)), " + ".join(first), " + ".join(second), runs_spread())


def rule_record(out_dir: str | Path, label: str, name: str, policy: str, episodes: int) -> dict[str, Any] | None:
    """The ``tasks`` record of one rule set for ``policy`` if one is kept: under ``out_dir``, or for the
    reference among the shipped records of the tables' meta-rl (:data:`RULE_RECORDS`, copied into
    ``out_dir`` so the candidate reads MPC-F's profits from there). None when none holds the same policy
    path, tasks, episodes, seed and K."""
    same = (policy, episodes, RULE_SETS[name][1], RULE_SEED, RULE_K)
    places = [rule_file(out_dir, label, name)] + ([rule_file(RULE_RECORDS, label, name)] if label == "reference" else [])
    for path in places:
        held = json.loads(path.read_text()) if path.is_file() else None
        if held and (held["policy"], held["episodes"], list(held["tasks"]), held["seed"], held.get("k", 3)) == same:
            if path != places[0]:
                places[0].write_text(path.read_text())
            return held
    return None


def rule(policy: str, reference: str, out_dir: str, episodes: int = 20, workers: int = 1) -> bool:
    """The selection rule, one command: every set of :data:`RULE_SETS` for ``reference`` and the candidate
    ``policy`` on the same validation episodes (each set's ``tasks`` file under ``out_dir``, reused when it
    holds the same policy path, tasks and episodes: use a fresh ``out_dir`` after retraining a file in place;
    MPC-F run once, for the reference; the reference's own from :data:`RULE_RECORDS` when it is the tables'),
    then a table of the measures (against the tables' pair, its recipe's other pair averaged in: :data:`RULE_AVERAGED_WITH`).
    All pass: the candidate replaces the reference. Returns the verdict."""
    Path(out_dir).mkdir(parents=True, exist_ok=True)
    recs: dict[str, dict[str, dict[str, Any]]] = {"reference": {}, "candidate": {}}
    for label, pol in (("reference", reference), ("candidate", policy)):  # the reference first: its MPC-F serves both
        for name in RULE_SETS:
            if (held := rule_record(out_dir, label, name, pol, episodes)) is not None:
                recs[label][name] = held
        todo = [name for name in RULE_SETS if name not in recs[label]]
        jobs = [(pol, task, episodes, RULE_SEED, RULE_K, recs["reference"][name]["tasks"][task]["mpc-forecast"] if label == "candidate" else None)
                for name in todo for task in RULE_SETS[name][1]]  # fmt: skip
        got = iter(in_workers(jobs, workers))
        for name in todo:
            record = {"policy": pol, "seed": RULE_SEED, "episodes": episodes, "k": RULE_K, "tasks": {}}
            for task in RULE_SETS[name][1]:
                record["tasks"][task] = next(got)
                print_task(task, record["tasks"][task])
            rule_file(out_dir, label, name).write_text(json.dumps(record, indent=1))
            recs[label][name] = record
    if reference == RULE_AVERAGED_WITH:  # the tables' recipe, not one draw of it
        for name in RULE_SETS:
            recs["reference"][name] = averaged([recs["reference"][name], json.loads(rule_file(RULE_RECORDS, "replicate", name).read_text())])
        print(f"reference: {reference} and its recipe's other pair averaged")
    verdict = print_rule_table(rule_rows(recs["reference"], recs["candidate"]), reference, policy, runs_spread())
    print(f"verdict: {'the candidate replaces the reference' if verdict else 'no: the reference stays'}")
    return verdict


def where(policy: str, cities: list[str], episodes: int = 10, seed: int = 1000, k: int = 3) -> None:
    for name in cities:
        city = load_city(name)
        per: dict[str, dict[str, np.ndarray]] = {}
        for label, make in {"meta": lambda c=city: meta.load_policy(policy, c, k, seed=seed), "mpc-forecast": MPCForecast}.items():
            pol, rows = make(), {"fares": [], "trip cost": [], "reb cost": [], "served": [], "share": []}
            for e in range(episodes):
                system, steps = drive(pol, city, np.random.SeedSequence([seed, e]), np.random.default_rng([seed, e, 1]))
                t0 = system.sim.totals
                last = (t0.revenue.copy(), t0.trip_cost.copy(), t0.rebalancing_cost.copy())
                ep = {key: [] for key in rows}
                for _, share, out in steps:
                    ep["share"].append(share)
                    tot = system.sim.totals
                    now = (tot.revenue.copy(), tot.trip_cost.copy(), tot.rebalancing_cost.copy())
                    for key, a, b in zip(("fares", "trip cost", "reb cost"), now, last, strict=True):
                        ep[key].append(a - b)
                    ep["served"].append(out.dispatch.sum(-1))
                    last = now
                for key in rows:
                    rows[key].append(np.stack(ep[key]))
            per[label] = {key: np.mean(v, axis=0) for key, v in rows.items()}  # (T, N) mean over episodes
        m, f = per["meta"], per["mpc-forecast"]
        profit = lambda r: r["fares"] - r["trip cost"] - r["reb cost"]  # noqa: E731
        gap = profit(f) - profit(m)
        print(f"\n{name}: meta K={k} vs MPC-Forecast, {episodes} validation episodes (seed {seed}), per episode after the first dispatch")
        for key in ("fares", "trip cost", "reb cost", "served"):
            print(f"  {key:10s} meta {m[key].sum():10.1f}  MPC-F {f[key].sum():10.1f}  diff {m[key].sum() - f[key].sum():+10.1f}")
        print(f"  profit gap {gap.sum():.1f}: by step " + " ".join(f"{g:.0f}" for g in gap.sum(1)))
        print("  served, MPC-F - meta, by step: " + " ".join(f"{g:.0f}" for g in (f["served"] - m["served"]).sum(1)))
        print("  rebalancing cost, meta - MPC-F, by step: " + " ".join(f"{g:.0f}" for g in (m["reb cost"] - f["reb cost"]).sum(1)))
        order = np.argsort(-gap.sum(0))
        print("  by region (largest first): " + ", ".join(f"r{i} {gap.sum(0)[i]:.0f}" for i in order[:6]))
        asked, mpc = m["share"].mean(0), f["share"].mean(0)  # (N,) the mean share of the idle fleet each region is asked
        print("  share asked (mean over steps) meta / MPC-F / idle fleet ratio, those regions: " + ", ".join(
            f"r{i} {asked[i]:.3f}/{mpc[i]:.3f}" for i in order[:6]))
        print("  asked most above MPC-F (mean share meta / MPC-F): " + ", ".join(  # the regions the policy sends to instead of MPC-F's
            f"r{i} {asked[i]:.3f}/{mpc[i]:.3f}" for i in np.argsort(mpc - asked)[:4]))
        l1 = 0.5 * np.abs(m["share"] - f["share"]).sum(1)
        print("  half L1 between the mean shares asked, by step: " + " ".join(f"{v:.2f}" for v in l1), flush=True)


class Override:
    """``pol`` with another player at the steps ``use(step)`` picks (step 0 the episode's first): ``other``'s
    targets (e.g. MPC-F's), or with no ``other`` its rebalancing held (a target of -1: every region keeps its
    idle vehicles). ``pol`` is still asked every step, so its memory sees its own moves; ``asked`` keeps,
    per step, the idle-fleet shares the policy and ``other`` asked for."""

    def __init__(self, pol: Any, use: Callable[[int], bool], other: Any = None) -> None:
        self.pol, self.use, self.other = pol, use, other
        self.asked: list[tuple[np.ndarray, np.ndarray | None]] = []

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        self.pol.reset(system, rng)
        if self.other is not None:
            self.other.reset(system, rng)
        self.t0, self.asked = system.sim.t, []

    def target(self, system: FleetSystem) -> np.ndarray:
        share = lambda w: (w := np.where(w < 0, system.sim.idle, w).astype(np.float64)) / max(w.sum(), 1.0)  # noqa: E731
        want = np.asarray(self.pol.target(system))
        theirs = None if self.other is None else np.asarray(self.other.target(system))
        self.asked.append((share(want), None if theirs is None else share(theirs)))
        if not self.use(system.sim.t - self.t0):
            return want
        return np.full_like(want, -1) if theirs is None else theirs


def episode_profit(pol: Any, city: City, e: int, seed: int = 1000) -> float:
    """Profit of one validation episode ``e`` driven by ``pol`` (the streams ``where`` uses)."""
    system, steps = drive(pol, city, np.random.SeedSequence([seed, e]), np.random.default_rng([seed, e, 1]))
    for _ in steps:
        pass
    return float(system.sim.totals.profit.sum())


def hold(policy: str, cities: list[str], last: int = 3, episodes: int = 10, seed: int = 1000, k: int = 3) -> dict[str, dict[str, float]]:
    out: dict[str, dict[str, float]] = {}
    for name in cities:
        city = load_city(name)
        n = city.horizon - 1  # control steps in an episode
        holds: dict[str, Callable[[int], bool]] = {
            "the policy": lambda t: False, "first step held": lambda t: t == 0,
            f"last {last} steps held": lambda t, n=n: t >= n - last, "both held": lambda t, n=n: t == 0 or t >= n - last,
        }
        row = {label: float(np.mean([episode_profit(Override(meta.load_policy(policy, city, k, seed=seed), h), city, e, seed)
                                     for e in range(episodes)])) for label, h in holds.items()}  # fmt: skip
        row["MPC-Forecast"] = float(np.mean([episode_profit(MPCForecast(), city, e, seed) for e in range(episodes)]))
        print(f"\n{name}: K={k}, {episodes} validation episodes (seed {seed}), mean profit an episode")
        for label, v in row.items():
            print(f"  {label:22s} {v:10,.0f}  ({v - row['the policy']:+,.0f})", flush=True)
        out[name] = row
    return out


def windows_of(text: str) -> dict[str, range]:
    """``"0-5,6-11,15-18"`` as named step ranges (inclusive ends), for ``steps --windows``."""
    out = {}
    for part in text.split(","):
        a, _, b = part.partition("-")
        out[f"steps {a}-{b or a}"] = range(int(a), int(b or a) + 1)
    return out


def steps(policy: str, cities: list[str], windows: dict[str, range], region: int | None = None, episodes: int = 10,
          seed: int = 1000, k: int = 3) -> dict[str, dict[str, Any]]:
    """Step by step, at a city's busiest region (or ``region``), on validation episodes: the idle-fleet share
    the policy asks for on its own path and on MPC-F's (MPC-F playing, the policy asked beside it), MPC-F's,
    and the requests each serves there; then which steps hold the profit gap: the policy with MPC-F's
    targets played in each window, paired by episode (docs/meta/log.md, "San Francisco, step by step")."""
    out: dict[str, dict[str, Any]] = {}
    for name in cities:
        city = meta.task_city(name)
        r = int(meta.place_table(city)[:, 2].argmax()) if region is None else region
        rows: dict[str, list[list[float]]] = {"own path: policy asks": [], "own path: served": [], "MPC-F's path: policy asks": [],
                                              "MPC-F's path: MPC-F asks": [], "MPC-F's path: served": []}  # fmt: skip
        base, mpc_path = [], []  # the policy's own profit and with MPC-F's targets at every step, episode by episode
        for e in range(episodes):
            for path, other in (("own path", None), ("MPC-F's path", MPCForecast())):
                pol = Override(meta.load_policy(policy, city, k, seed=seed), lambda t, o=other: o is not None, other)
                system, played = drive(pol, city, np.random.SeedSequence([seed, e]), np.random.default_rng([seed, e, 1]))
                rows[f"{path}: served"].append([outcome.dispatch.sum(-1)[r] for _, _, outcome in played])
                rows[f"{path}: policy asks"].append([mine[r] for mine, _ in pol.asked])
                (base if other is None else mpc_path).append(float(system.sim.totals.profit.sum()))
                if other is not None:
                    rows["MPC-F's path: MPC-F asks"].append([theirs[r] for _, theirs in pol.asked])
        means = {label: np.mean(v, axis=0) for label, v in rows.items()}
        print(f"\n{name}: region r{r}, K={k}, {episodes} validation episodes (seed {seed}), mean by step")
        for label, v in means.items():
            fmt = "{:5.1f}" if "served" in label else "{:5.2f}"
            print(f"  {label:28s} " + " ".join(fmt.format(x) for x in v))
        print(f"  the policy's profit {np.mean(base):10,.0f}")
        gains = {}
        for label, window in {"every step": None, **windows}.items():  # every step: MPC-F's path above, not played again
            played_ = np.array(mpc_path if window is None else [
                episode_profit(Override(meta.load_policy(policy, city, k, seed=seed), lambda t, w=window: t in w, MPCForecast()), city, e, seed)
                for e in range(episodes)])  # fmt: skip
            d = played_ - np.array(base)
            se = float(sem(d)) if len(d) > 1 else float("nan")  # one episode: no spread to read
            gains[label] = (float(d.mean()), se)
            print(f"  MPC-F's targets at {label:12s} {played_.mean():10,.0f}  ({d.mean():+,.0f}, SE {se:.0f})", flush=True)
        out[name] = {"region": r, "by_step": {label: v.tolist() for label, v in means.items()}, "policy": float(np.mean(base)), "gains": gains}
    return out


def usual_day(city: City) -> City:
    """``city`` without its events: the draw made the forecast (the usual day the features and MPC-F expect)."""
    return replace(city, name=f"{city.name} (usual day)", demand_rate=city.forecast_rate, meta={k: v for k, v in city.meta.items() if k != "events"})


def announced(city: City) -> City:
    """``city`` with its events in the forecast too: every forecast reader (MPC-Forecast, a policy's look-ahead
    columns) sees the day's expected demand, event included; the draw is unchanged (:func:`usual_day`'s converse)."""
    return replace(city, forecast_rate=np.asarray(city.demand_rate).copy())


def told(policy: str, names: list[str], episodes: int = 10, seed: int = 0, k: int = 3) -> dict[str, dict[str, np.ndarray]]:
    """What knowing an event is worth, on each evented scenario or task's episodes (``seed`` 0: the tables'):
    MPC-Forecast, MPC told the event (:class:`~marl_amod.algos.meta_imitation.MPCToldTheShock`: it plans on the
    day's expected demand), MPC-Oracle, the meta-policy as deployed and with the event in its inputs
    (:func:`announced`, adapted there too), each paired with MPC-Forecast by episode (docs/meta/log.md,
    "What knowing the event is worth")."""
    out: dict[str, dict[str, np.ndarray]] = {}
    for name in names:
        city = meta.task_city(name)
        if not city.meta.get("events"):
            raise SystemExit(f"told: {name} has no event (an event task <city>~ev... or a scenario with events:)")
        shown = announced(city)
        players = {"mpc-forecast": (MPCForecast(), city), "mpc told the event": (mi.MPCToldTheShock(), city), "mpc-oracle": (MPCOracle(), city),
                   "meta-rl": (meta.load_policy(policy, city, k, seed=seed), city),
                   "meta-rl, the event in its inputs": (meta.load_policy(policy, shown, k, seed=seed), shown)}  # fmt: skip
        rows = {label: np.array([m["profit"] for m in evaluate(pol, on, episodes, seed)["per_episode"]]) for label, (pol, on) in players.items()}
        out[name] = rows
        print(f"{name}: profit, and paired with MPC-Forecast by episode (SE)")
        for label, p in rows.items():
            d = p - rows["mpc-forecast"]
            print(f"  {label:34s} {p.mean():10,.0f}  {d.mean():+8,.0f} ({sem(d):.0f})", flush=True)
        d = rows["meta-rl, the event in its inputs"] - rows["meta-rl"]
        print(f"  the event in the meta-policy's inputs is worth {d.mean():+,.0f} (SE {sem(d):.0f}); "
              f"told MPC-F gains {np.mean(rows['mpc told the event'] - rows['mpc-forecast']):+,.0f}")
    return out


@contextlib.contextmanager
def memory_frozen(steps: Collection[int] | None) -> Iterator[None]:
    """Inside it, a meta agent's memory does not move at the control steps ``steps`` (it acts as usual):
    which steps of the adaptation episodes write what the memory carries (None: every step moves it)."""
    act = meta.MetaAgent.act

    def frozen(agent: meta.MetaAgent, system: Any, sample: bool) -> Any:
        before = agent.memory
        out = act(agent, system, sample)
        if system.t in steps:
            agent.memory = before
        return out

    if steps is not None:
        meta.MetaAgent.act = frozen  # type: ignore[method-assign]
    try:
        yield
    finally:
        meta.MetaAgent.act = act  # type: ignore[method-assign]


def misread(policy: str, names: list[str], episodes: int = 20, seed: int = 1000, k: int = 3, freeze: Collection[int] | None = None) -> dict[str, dict[str, float]]:
    """Each evented task's profit with the policy's memory adapted (``k`` episodes, each ensemble member
    alone) on the task itself (as deployed), on its usual day (:func:`usual_day`), and not at all (K = 0),
    on the same validation episodes: a memory that misreads the event does better after the usual day;
    one that drifts with any adaptation does worse after both than with none (docs/meta/log.md, "What the
    memory does on the event"). With ``freeze`` the memory does not move at those steps of the adaptation
    episodes (:func:`memory_frozen`; the scored episodes play as deployed): where the misreading is written."""
    out: dict[str, dict[str, float]] = {}

    def adapted(on: City, kk: int) -> Any:
        with memory_frozen(freeze):
            return meta.load_policy(policy, on, kk, seed=seed)

    for name in names:
        task = meta.task_city(name)
        if not task.meta.get("events"):
            raise SystemExit(f"misread: {name} has no event (an event task <city>~ev... or a scenario with events:)")
        rows = {label: [m["profit"] for m in evaluate(adapted(on, kk), task, episodes, seed)["per_episode"]]
                for label, on, kk in (("evented", task, k), ("usual day", usual_day(task), k), ("none", task, 0))}  # fmt: skip
        d = np.array(rows["usual day"]) - np.array(rows["evented"])
        out[name] = {label: float(np.mean(v)) for label, v in rows.items()}
        print(f"{name:50s} adapted on the evented day {out[name]['evented']:10,.0f}  the usual day {out[name]['usual day']:10,.0f} "
              f"({d.mean():+,.0f}, SE {sem(d):.0f})  none {out[name]['none']:10,.0f}", flush=True)  # fmt: skip
    return out


def trial_measures(path: Path) -> tuple[int, dict[str, np.ndarray]]:
    """One DAgger trial file's collection seed (its days) and measures by the episode's place in the trial
    (:func:`trials`); the unserved column is found from the file's own look-ahead."""
    d = np.load(path)
    action, share, x = d["action"], d["share"], d["x"]  # (K, T, N), (K, T, N), (K, T, N, F)
    hot = int(share.mean((0, 1)).argmax())
    idle = x[..., hot, 0]
    return int(d["seed"]), {
        "misplaced": 0.5 * np.abs(action - share).sum(-1).mean(-1),
        "asked": action[..., hot].mean(-1), "label": share[..., hot].mean(-1),
        "unserved": x[..., hot, 2 + 2 * int(d["lookahead"])].sum(-1),
        "spread": np.full(len(idle), idle.std(0).mean()),  # one value a trial, repeated so every column reads by episode
        "return": d["reward"].sum(-1),
    }


def trials(runs: list[str]) -> None:
    """What each run's DAgger trials hold (module docstring); the first run is the one the others pair with."""
    found: dict[str, dict[tuple[int, str], tuple[int, dict[str, np.ndarray]]]] = {}  # run -> (round, task) -> (seed, measures)
    for run in runs:
        files = sorted(Path(run).glob("dagger/round*/*.npz"))
        if not files:
            raise SystemExit(f"{run}: no DAgger trials (dagger/round*/<task>.npz)")
        found[run] = {(int(f.parent.name.removeprefix("round")), f.stem): trial_measures(f) for f in files}
    keys = ["misplaced", "asked", "label", "unserved", "spread", "return"]
    print(f"{'run':44s} {'ep':>2s} " + " ".join(f"{k:>9s}" for k in keys), flush=True)
    for run, got in found.items():
        for e in range(len(next(iter(got.values()))[1]["return"])):
            row = [np.mean([m[k][e] for _, m in got.values()]) for k in keys]
            print(f"{Path(run).name:44s} {e + 1:2d} " + " ".join(f"{v:9.4f}" for v in row), flush=True)
    first = found[runs[0]]
    for run, got in list(found.items())[1:]:
        shared = [t for t in got if t in first and first[t][0] == got[t][0]]
        if not shared:
            print(f"{Path(run).name}: no trials on the same days as {Path(runs[0]).name}", flush=True)
            continue
        diff = np.array([got[t][1]["return"] - first[t][1]["return"] for t in shared])  # (trials, K)
        se = diff.std(0, ddof=1) / np.sqrt(len(diff)) if len(diff) > 1 else np.full(diff.shape[1], np.nan)  # one trial: no error
        text = ", ".join(f"ep {e + 1} {diff[:, e].mean():+.3f} ({se[e]:.3f})" for e in range(diff.shape[1]))
        print(f"{Path(run).name} - {Path(runs[0]).name}, return over {len(shared)} paired trials: {text}", flush=True)
    print("adaptation episodes' misplaced share, round by round:", flush=True)
    for run, got in found.items():
        rounds = sorted({r for r, _ in got})
        text = " ".join(f"{np.mean([m['misplaced'][:-1].mean() for (r, _), (_, m) in got.items() if r == k]):.3f}" for k in rounds)
        print(f"{Path(run).name:44s} {text}", flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("what", choices=["gap", "k", "event", "heldout", "where", "hold", "steps", "hotspot", "transplant", "tasks", "compare", "rule", "recipes", "misread", "told", "trials", "spread", "runs", "track"])
    parser.add_argument("files", nargs="*", help="compare: two tasks --out files (the second against the first); trials: run folders; spread: rule folders of single runs")
    parser.add_argument("--policy", default="policies/meta_rl_l1_cities.pt")
    parser.add_argument("--demos", default="runs/meta_demos")
    parser.add_argument("--ks", default="0,1,2,3,4,5,6,8,10")
    parser.add_argument("--episodes", type=int, default=8, help="heldout: episodes per city and side (a multiple of 4); hotspot: validation episodes (0: none); told: report episodes (the tables: 10)")
    parser.add_argument("--multiplier", type=float, default=None, help="hotspot: also each city with its busiest region x this")
    parser.add_argument("--cities", help="heldout, where: the cities (default: the validation and held-out cities); "
                                         "track: each set read on these cities' tasks only (default: all)")
    parser.add_argument("--validation", action="store_true", help="k: the training cities' validation return instead")
    parser.add_argument("--out", default=None, help="tasks: the JSON of per-episode profits")
    parser.add_argument("--plot", default=None, help="track: a heatmap of the correlations (PNG), beside them the rule's other cities' with --cities")
    parser.add_argument("--mpc-from", default=None, help="tasks: reuse MPC-F's profits from this earlier --out")
    parser.add_argument("--k", type=int, default=3, help="tasks: the policy's adaptation episodes before each scored one")
    parser.add_argument("--reference", default=META_POLICY, help="rule: the policy the candidate (--policy) must beat (default: the tables' meta-rl)")
    parser.add_argument("--rule-dir", default="runs/rule", help="rule: where each set's tasks files go (reused when they hold the same policy)")
    parser.add_argument("--workers", type=int, default=1, help="rule, tasks: processes the tasks run over (one core each)")
    parser.add_argument("--first", default="", help="recipes: the first recipe's record prefixes, comma-separated (docs/meta/rule/cut01,docs/meta/rule/cut23); "
                                                    "runs, track: its single runs' rule folders")
    parser.add_argument("--second", default="", help="recipes: the second recipe's record prefixes, comma-separated; runs: its single runs' rule folders; "
                                                     "track: the runs' transfer-table folders")
    parser.add_argument("--rule-episodes", type=int, default=20, help="rule: validation episodes per task")
    parser.add_argument("--last", type=int, default=3, help="hold: the episode's last steps held")
    parser.add_argument("--windows", default="0-5,6-11,12-14,15-16,17-18", help="steps: the step windows MPC-F plays in (inclusive)")
    parser.add_argument("--region", type=int, default=None, help="steps: the region followed (default: the city's busiest origin)")
    parser.add_argument("--own", action="store_true", help="hotspot: also on the states the policy reaches itself (8 episodes, labelled by MPC-F)")
    parser.add_argument("--freeze", default=None, help="misread: steps (inclusive windows, e.g. 6-13 or 0-5,14-19) at which the memory does not move while adapting")
    args = parser.parse_args()
    only_on, args.cities = args.cities, args.cities or ",".join([*VAL_CITIES, *meta.HELD_OUT])  # track reads only what was asked
    torch.manual_seed(0)  # the policy's sampled adaptation episodes (gap, heldout, hotspot --own): a rerun repeats them
    ks = [int(k) for k in args.ks.split(",")]
    if args.what == "gap":
        gap(args.policy, args.demos)
    elif args.what == "heldout":
        heldout(args.policy, args.demos, args.cities.split(","), args.episodes)
    elif args.what == "hotspot":
        hotspot(args.policy, args.cities.split(","), args.multiplier, args.episodes, own=args.own)
    elif args.what == "transplant":
        transplant(args.policy, args.cities.split(","), args.episodes)
    elif args.what == "where":
        where(args.policy, args.cities.split(","))
    elif args.what == "hold":
        hold(args.policy, args.cities.split(","), args.last)
    elif args.what == "steps":
        steps(args.policy, args.cities.split(","), windows_of(args.windows), args.region)
    elif args.what == "tasks":
        if not args.out:
            parser.error("tasks needs --out")
        tasks(args.policy, args.cities.split(","), args.episodes, args.out, mpc_from=args.mpc_from, k=args.k, workers=args.workers)
    elif args.what == "rule":
        rule(args.policy, args.reference, args.rule_dir, args.rule_episodes, args.workers)
    elif args.what == "recipes":
        if not (args.first and args.second):
            parser.error("recipes needs --first and --second record prefixes")
        recipes(args.first.split(","), args.second.split(","))
    elif args.what == "misread":
        freeze = set().union(*windows_of(args.freeze).values()) if args.freeze else None  # every window given, not the first
        misread(args.policy, args.cities.split(","), args.episodes, k=args.k, freeze=freeze)
    elif args.what == "told":
        told(args.policy, only_on.split(",") if only_on else ["nyc_brooklyn_event"], args.episodes, k=args.k)
    elif args.what == "spread":
        spread(args.files, args.out or RUN_SPREAD)
    elif args.what == "track":
        if not (args.first and args.second):
            parser.error("track needs --first (rule folders of single runs) and --second (their transfer-table folders), comma-separated, in the same order")
        rule_dirs, heldout_dirs = args.first.split(","), args.second.split(",")
        if args.plot:  # a bad figure name fails before the tables, not after
            from marl_amod.errors import OutputError
            from marl_amod.plots import figure_destination, save_figure

            try:
                plot = figure_destination(args.plot)
            except OutputError as exc:
                parser.error(str(exc))
        only = only_on.split(",") if only_on else None
        panels = {f"each set on {only_on}" if only else "every task of each set": track(rule_dirs, heldout_dirs, only)}
        if only and (rest := [c for c in VAL_CITIES if c not in only]):  # the rule's other cities, beside them
            panels[f"each set on {','.join(rest)}"] = track(rule_dirs, heldout_dirs, rest)
        if args.plot:
            print(f"wrote {save_figure(track_figure(panels), plot)}")
    elif args.what == "runs":
        if not (args.first and args.second):
            parser.error("runs needs --first and --second: comma-separated rule folders of single runs")
        arm_runs(args.first.split(","), args.second.split(","))
    elif args.what == "trials":
        if not args.files:
            parser.error("trials needs run folders holding dagger/round*/<task>.npz")
        trials(args.files)
    elif args.what == "compare":
        if not args.files:
            parser.error("compare needs tasks --out files: A.json B.json")
        compare(args.files)
    elif args.what == "k":
        (k_validation if args.validation else k_sweep)(args.policy, ks)
    else:
        event(args.policy)


if __name__ == "__main__":
    main()
