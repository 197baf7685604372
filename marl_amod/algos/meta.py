"""Meta-RL through recurrence (RL², the paper's "Meta-RL"): cities as tasks, one recurrent policy.

Read top to bottom: the task set and its per-city scaling, random demand shocks, the agent that
carries memory, trials in lockstep, Args, ``train``, then adaptation to a new city (no gradient
steps).

Tasks. The ten training cities are every real city except the three held out for the
inter-city study (San Francisco, NY Brooklyn, Shenzhen downtown west). Fleets differ 35-fold
(Rome 78 vehicles, Chicago 2,716), so one shared policy needs inputs and rewards in per-city
units (:class:`CityScale`):

* vehicle counts (idle, supply) are divided by the fleet per region, fleet / N;
* request values (expected fares out of a region) are divided by the mean fare and by fleet / N,
  so they read as expected requests in the same unit as the vehicles, and the supply-demand
  balance of a city stays visible;
* the requests served out of each region at the step just dispatched and those left unserved,
  in vehicles per region: what the operator saw happen (a shock the forecast misses shows here);
* a last column is the step fraction t / horizon; with ``city_features`` the city's structure
  follows (:func:`structure_table`: expected requests into each region, trip and rebalancing
  times, the cost of driving), which a single-city policy memorises and MPC-Forecast plans with,
  and with ``place_features`` where each region lies in its city (:func:`place_table`);
* the reward is the step's profit divided by the city's expected fare revenue per step
  (``forecast_rate * price`` over the episode, / horizon): about 0.5-1 per step in every city;
  the memory also reads each region's own reward (its trips' profit minus its rebalancing cost)
  in the same unit per region, so a region can tell that *its* demand departs from the usual.

Shocks (``shock_prob``). A city draw may get a random special event (:func:`random_shock`, the
scenario events of :mod:`marl_amod.scenario.events`): for all its trials and every episode of
them, requests out of a few regions surge (and sometimes drop out of others) over a window the
forecast does not know. The memory thus learns to notice a departure from the usual demand and
answer it in later steps and episodes: what the special-event study asks.

Hotspot variants (:func:`~marl_amod.scenario.variants.hotspot`; ``task_city`` is ``load_city``, which
takes the names of both variants). A training city with one region's share
of the requests raised, forecast included: a task of its own (``<city>~hot<r>x<m>``) whose
demand is more concentrated than any training city's, as the held-out cities' is; the imitation
(:mod:`.meta_imitation`, ``hotspot_variants``) can add them to the cities.

Skew variants (:func:`~marl_amod.scenario.variants.skew`, ``<city>~skew<gamma>``). A training city
with the shape of its whole demand changed: every region's requests out x (its share / the
average share) ^ (gamma - 1), forecast included, so big regions grow and small ones shrink (the
held-out cities' demand is more skewed than the training cities', not only at one region);
``skew_variants`` of :mod:`.meta_imitation` adds them (:func:`skew_tasks`).

Sink variants (:func:`~marl_amod.scenario.variants.sink`, ``<city>~sink<r>x<m>``). A training city
with every origin's trips into one region x m, forecast included: the fleet drains into it, as
Brooklyn's does into its region 6 (trips in and out differ by half of all trips there, by at most
a quarter in a training city); ``sink_variants`` adds them (:func:`sink_tasks`).

Event tasks (:func:`event_task`, ``<city>~ev...``). A training city with one fixed special event
of the Brooklyn kind (requests out of a few regions surge over a window, the busiest regions'
drop), in the draw and *not* in the forecast: every episode of the task carries the same event,
so a trial of it shows the memory a shock that repeats (a :func:`random_shock` trial's episodes
are mixed with the city's other episodes once they are teacher-forced). Labelled by MPC told the
event (:class:`~marl_amod.algos.meta_imitation.MPCToldTheShock`).

Trials in lockstep. A trial is ``trial_episodes`` consecutive episodes on one city with the
recurrent memory (:class:`~marl_amod.models.recurrent.RecurrentGNN`) carried from one episode to
the next; the previous action and rewards restart at zero with each episode. Each update draws
``cities_per_update`` cities and runs ``num_envs`` trials of each in lockstep on the batched
simulator (:class:`~marl_amod.batch_system.BatchFleetSystem`): one (B, N, F) forward pass on the
dense graph per step, the memory a (B, N, H) tensor. The A2C update treats each trial as one
sequence (discount ``gamma``, GAE ``gae_lambda``; back-propagation through the whole trial), so
the memory learns to infer the city from what happened in earlier episodes.

Warm start. RL² from scratch stays near equal distribution; ``init_actor`` starts it from the
recurrent GNN imitating MPC-Forecast on the training cities (:mod:`.meta_imitation`, validated
first and kept unless RL² beats it), and ``bc_coef`` adds that imitation loss to every update.

Adaptation. In a new city the policy runs ``trial_episodes - 1`` episodes (stochastic actions,
their own demand streams, never the report streams), and each evaluation episode starts from
the memory those left: a handful of episodes and no gradient step.
"""

from __future__ import annotations

import contextlib
import copy
import itertools
import warnings
import weakref
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from functools import partial
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch
import torch.nn.functional as F
from pydantic import Field, model_validator

from marl_amod.algos import common as C
from marl_amod.algos import offline as O
from marl_amod.algos.rollout import train_seed
from marl_amod.baselines.base import WeightPolicy, check_bound_city
from marl_amod.batch_system import BatchFleetSystem
from marl_amod.data import resolve
from marl_amod.ensemble import Adaptation, PolicyEnsemble, is_ensemble, load_ensemble, read_members, read_spec
from marl_amod.env.features import state_features
from marl_amod.errors import ConfigError, DataError
from marl_amod.models.dense import city_graph
from marl_amod.models.distributions import dirichlet
from marl_amod.models.gnn import Readout
from marl_amod.models.recurrent import STAY_CONCENTRATION, RecurrentGNN
from marl_amod.scenario import City, load_city
from marl_amod.scenario.registry import load_spec
from marl_amod.scenario.types import step_rows
from marl_amod.scenario.variants import (  # noqa: F401 (meta.<name>)
    EVENT,
    HOTSPOT,
    SINK,
    SKEW,
    base_city,
    event_name,
    event_task,
    hotspot,
    hotspot_name,
    sink_name,
    skew_name,
)
from marl_amod.system import FleetSystem

TRAIN_CITIES = (
    "chicago", "nyc_man_middle", "nyc_man_north", "nyc_man_south", "porto", "rome",
    "shenzhen_baoan", "shenzhen_downtown_east", "shenzhen_north", "washington_dc",
)  # fmt: skip
HELD_OUT = ("san_francisco", "nyc_brooklyn", "shenzhen_downtown_west")
task_city = load_city  # a task by name: a city or a variant of one (<city>~hot..., <city>~skew..., <city>~ev...: scenario/variants.py)


# --------------------------------------------------------------------------------------------
# Cities as tasks: per-city units
# --------------------------------------------------------------------------------------------
@dataclass(frozen=True)
class CityScale:
    """The units that make cities of any fleet and demand size look alike to one policy."""

    vehicles: float  # fleet / N: vehicles per region
    requests: float  # mean fare * fleet / N: a region's request value in "vehicles per region"
    reward: float  # expected fare revenue per control step (forecast demand x fares)

    @classmethod
    def of(cls, city: City) -> CityScale:
        steps = slice(0, city.horizon)
        rate, price = city.forecast_rate[steps], city.price[steps]
        revenue, requests = float((rate * price).sum()), float(rate.sum())
        per_region = city.fleet_size / city.n_regions
        return cls(vehicles=per_region, requests=revenue / max(requests, 1e-9) * per_region, reward=revenue / city.horizon)


def task_features(
    system: FleetSystem | BatchFleetSystem, scale: CityScale, lookahead: int, structure: bool = False, place: bool = False,
    end_cut: bool = False,
) -> np.ndarray:
    """(..., N, 2T + 4) float32: the paper's features in per-city units, the step's served and
    unserved requests out of each region (vehicles per region), then t / horizon; with
    ``structure`` the T + 3 columns of :func:`structure_table` after them, and with ``place`` the
    ``N_PLACE`` of :func:`place_table` after those; with ``end_cut`` no demand past the episode's
    end (:func:`cut_at_end`)."""
    sim = system.sim
    raw = state_features(system.city, sim.t, sim.idle, sim.arrivals, lookahead, scale=1.0).astype(np.float64)  # idle, supply x T, value x T
    raw[..., : 1 + lookahead] /= scale.vehicles
    raw[..., 1 + lookahead :] /= scale.requests
    served = sim.last_dispatch.sum(-1) / scale.vehicles  # (..., N) trips that just left each region
    unserved = sim.requests().sum(-1) / scale.vehicles  # (..., N) requests no vehicle was there for
    step = np.full(sim.idle.shape, sim.t / system.city.horizon)
    cols = [raw, np.stack([served, unserved, step], axis=-1)]
    if structure:
        cols.append(np.broadcast_to(structure_table(system.city, lookahead)[sim.t], (*sim.idle.shape, lookahead + 3)))
    if place:
        cols.append(np.broadcast_to(place_table(system.city), (*sim.idle.shape, N_PLACE)))
    x = np.concatenate(cols, axis=-1).astype(np.float32)
    return cut_at_end(x, system.city, lookahead) if end_cut else x


def cut_at_end(x: np.ndarray, city: City, lookahead: int) -> np.ndarray:
    """Task features (..., N, F) with the requests expected past the episode's last step set to zero:
    the value columns and, when present, the structure table's inflow columns.

    Why: MPC-Forecast, the teacher, plans with no demand past the last control step
    (:func:`~marl_amod.baselines.mpc.plan_data`), while the look-ahead columns read the city's
    tables, which go on past the episode; a policy imitating it had to learn from the clock alone
    which columns no longer count. Cut, it sees the demand MPC-F plans with. The step is read back
    from the t / horizon column, so stored demonstrations are cut at load as well."""
    t = np.rint(x[..., :1, 3 + 2 * lookahead] * city.horizon)  # (..., 1): the step, one per episode
    past = t[..., None] + np.arange(1, lookahead + 1) > city.horizon - 1  # (..., 1, T)
    out = x.copy()
    out[..., 1 + lookahead : 1 + 2 * lookahead] *= ~past  # value
    if x.shape[-1] >= n_task_features(lookahead, structure=True):
        out[..., 4 + 2 * lookahead : 4 + 3 * lookahead] *= ~past  # expected requests into each region
    return out


def demand_columns(lookahead: int) -> tuple[int, int, int]:
    """The task-feature columns that count requests out of a region: expected at t+1, served and
    left unserved at the step just dispatched (in vehicles per region)."""
    return 1 + lookahead, 1 + 2 * lookahead, 2 + 2 * lookahead


N_STRUCTURE = 3  # + T: columns of structure_table
N_PLACE = 5  # columns of place_table


def n_task_features(lookahead: int, structure: bool = False, place: bool = False) -> int:
    if place and not structure:
        raise ConfigError("place_features extend city_features: set city_features too")
    return 4 + 2 * lookahead + (lookahead + N_STRUCTURE if structure else 0) + (N_PLACE if place else 0)


def features_read(model: RecurrentGNN, lookahead: int) -> tuple[bool, bool]:
    """(structure, place): which optional columns ``model``'s input has after the task features."""
    for options in ((False, False), (True, False), (True, True)):
        if model.n_features == n_task_features(lookahead, *options):
            return options
    raise DataError(f"a recurrent GNN reading {model.n_features} features is none of the task-feature sets of lookahead {lookahead}")


_STRUCTURE: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def structure_table(city: City, lookahead: int) -> np.ndarray:
    """(S, N, T + 3) float32: what MPC-Forecast plans with beyond the paper's features and a
    single-city policy memorises, in per-city units, as a function of (city, t) alone:

    * expected requests *into* each region at t+1..t+T (where trips will leave vehicles), in
      vehicles per region;
    * the demand-weighted trip time out of the region and the mean rebalancing time to its graph
      neighbours, in steps / T (how long a vehicle sent there is away);
    * the cost of a step of driving / the mean fare (what a move costs against what a trip earns).
    """
    per_city = _STRUCTURE.setdefault(city, {})
    if lookahead not in per_city:
        scale, n, rate = CityScale.of(city), city.n_regions, city.forecast_rate
        steps = np.arange(city.n_steps)[:, None] + np.arange(1, lookahead + 1)[None, :]  # (S, T)
        inflow = np.swapaxes(step_rows(rate.sum(axis=1), steps), -1, -2) / scale.vehicles  # (S, N, T)
        out = rate.sum(axis=2)  # (S, N)
        trip = np.where(out > 0, (rate * city.trip_time).sum(axis=2) / np.maximum(out, 1e-12), city.trip_time.mean(axis=2))
        src, dst = np.asarray(city.edge_index)
        degree = np.bincount(src, minlength=n)
        neighbours = np.bincount(src, weights=city.reb_time[src, dst], minlength=n) / np.maximum(degree, 1)
        neighbours = np.where(degree > 0, neighbours, city.reb_time.sum(1) / max(n - 1, 1))  # no neighbour: the mean to all
        mean_fare = scale.requests / scale.vehicles
        cost = np.full((city.n_steps, n), city.beta * city.tstep / mean_fare)
        table = np.concatenate([inflow, np.stack([trip / lookahead, np.broadcast_to(neighbours / lookahead, out.shape), cost], axis=-1)], axis=-1)
        per_city[lookahead] = table.astype(np.float32)
        per_city[lookahead].setflags(write=False)
    return per_city[lookahead]


def place_table(city: City) -> np.ndarray:
    """(N, N_PLACE) float32: where each region lies in its city, static and size-agnostic (each
    relative to the city's average, so 1 is a typical region in any city): the mean rebalancing
    time to the other regions and from them, the region's share of the day's requests out and
    in, and its share of the initial fleet (shares x N). MPC-Forecast's plan depends on a region's
    place; a network that treats regions alike (one set of weights for every city) can only learn
    it from features (docs/offline "BC fidelity" 6: with a fleet readout these took a one-hop
    clone of MPC-Forecast half-way to the MLP one)."""
    per_city = _STRUCTURE.setdefault(city, {})
    if "place" not in per_city:
        n = city.n_regions
        others = max(n - 1, 1)
        to, came = city.reb_time.sum(1) / others, city.reb_time.sum(0) / others  # the diagonal is 0
        mean = max(float(to.mean()), 1e-9)
        day = city.forecast_rate[: city.horizon].sum(axis=0)  # (N, N) expected requests over the episode
        total = max(float(day.sum()), 1e-9)
        fleet = max(float(city.initial_vehicles.sum()), 1e-9)
        cols = [to / mean, came / mean, day.sum(1) * n / total, day.sum(0) * n / total, city.initial_vehicles * n / fleet]
        per_city["place"] = np.stack(cols, axis=-1).astype(np.float32)
        per_city["place"].setflags(write=False)
    return per_city["place"]


def with_structure(x: np.ndarray, city: City, lookahead: int, place: bool = False) -> np.ndarray:
    """Task features (..., N, 2T + 4) -> with the structure columns (..., N, 3T + 7), and with
    ``place`` the place columns: the step is read back from the last column, t / horizon (stored
    demonstrations gain them at load)."""
    t = np.rint(x[..., 0, -1] * city.horizon).astype(np.int64)  # (...)
    cols = [x, structure_table(city, lookahead)[t]]
    if place:
        cols.append(np.broadcast_to(place_table(city), (*x.shape[:-1], N_PLACE)))
    return np.concatenate(cols, axis=-1)


def stored_inputs(x: np.ndarray, city: City, lookahead: int, structure: bool = False, place: bool = False,
                  end_cut: bool = False) -> np.ndarray:  # fmt: skip
    """Stored task features (..., N, 2T + 4), as the files keep them, in the columns a model reads: the
    structure (and place) columns added (:func:`with_structure`), the demand past the episode's end cut
    (:func:`cut_at_end`); the same as :func:`task_features` gives live."""
    x = with_structure(x, city, lookahead, place) if structure else x
    return cut_at_end(x, city, lookahead) if end_cut else x


# --------------------------------------------------------------------------------------------
# Task variants: random demand shocks the forecast does not know
# --------------------------------------------------------------------------------------------
def random_shock(city: City, rng: np.random.Generator) -> City:
    """``city`` with a random special event (:func:`event_task`: on a plain city named so
    :func:`task_city` replays it): requests out of 1-3 regions x1.5-8 and, half the time, out of 1-2 others x0.2-0.8, over
    3-10 steps; the forecast (what the features read) keeps the usual demand."""
    n, h = city.n_regions, city.horizon
    up, down = int(rng.integers(1, 4)), int(rng.integers(1, 3)) * int(rng.random() < 0.5)
    regions = rng.choice(n, size=min(n, up + down), replace=False).tolist()
    start = int(rng.integers(0, h - 3))
    end = min(h, start + int(rng.integers(3, 11)))
    multiplier = float(np.exp(rng.uniform(np.log(1.5), np.log(8.0))))
    drop_multiplier = float(rng.uniform(0.2, 0.8)) if regions[up:] else 1.0
    return event_task(city, regions[:up], multiplier, start, end, regions[up:], drop_multiplier)


def first_distinct(draws: Iterator[str | None], n: int) -> list[str] | None:
    """The first ``n`` distinct task names among ``1000 n`` draws (None: a draw refused), or None
    if there are fewer. Why distinct: a repeated name would be one task counted twice."""
    names: list[str] = []
    for name in itertools.islice(draws, 1000 * n):
        if name is not None and name not in names:
            names.append(name)
            if len(names) == n:
                return names
    return None


def event_tasks(cities: list[str], per_city: int, multipliers: tuple[float, float], seed: int) -> list[str]:
    """``per_city`` event tasks of each city, drawn like the Brooklyn event: two regions outside the
    city's two busiest surge x a multiplier log-uniform in ``multipliers`` (one decimal) for 6-10
    steps (fewer in a city of fewer control steps) starting anywhere the window fits; in three draws of four the two busiest drop x
    0.3-0.8 (one decimal) meanwhile. A function of the seed, so a resumed run names the same tasks."""
    lo, hi = map(float, multipliers)
    if per_city and not (np.isfinite(hi) and 1.05 < lo <= hi):
        raise ConfigError(f"event_multipliers {list(multipliers)}: a range [low, high] with 1.05 < low <= high (a surge; one "
                          "decimal is kept, so a lower one would name surges of x1)")  # fmt: skip
    names: list[str] = []
    for i, name in enumerate(cities if per_city else []):
        city = load_city(name)
        if city.n_regions < 4 or city.horizon < 2:
            raise ConfigError(f"event tasks of {name}: need at least 4 regions (the two busiest and two that surge) and 2 control steps")
        mine = first_distinct(_event_draws(name, city, np.random.default_rng([seed, i, 6037]), lo, hi), per_city)
        if mine is None:
            raise ConfigError(f"{per_city} distinct event tasks of {name} not found (its {city.n_regions} regions, {city.horizon} "
                              f"control steps, event_multipliers {list(multipliers)} to one decimal): ask for fewer")  # fmt: skip
        names += mine
    return names


def _event_draws(name: str, city: City, rng: np.random.Generator, lo: float, hi: float) -> Iterator[str]:
    busiest = np.argsort(-place_table(city)[:, 2], kind="stable")[:2]
    others = np.setdiff1d(np.arange(city.n_regions), busiest)
    longest = min(10, city.horizon - 1)
    while True:
        surge = sorted(int(r) for r in rng.choice(others, size=2, replace=False))
        multiplier = round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), 1)
        length = int(rng.integers(min(6, longest), longest + 1))
        start = int(rng.integers(0, city.horizon - length + 1))
        dropped = rng.random() < 0.75
        drop_m = round(float(rng.uniform(0.3, 0.8)), 1)
        yield event_name(name, surge, multiplier, start, start + length, sorted(map(int, busiest)) if dropped else [], drop_m)


def hotspot_tasks(cities: list[str], variants: int, multipliers: tuple[float, float], seed: int, distinct_regions: bool = False) -> list[str]:
    """``variants`` hotspot variants of each city: the region drawn by its share of the day's
    requests out (busy regions become hotspots more often), the multiplier log-uniform in
    ``multipliers`` (one decimal); a function of the seed, so a resumed run names the same tasks.
    ``distinct_regions``: a city's variants on as many different regions (redrawn otherwise), so a
    second variant puts the hotspot somewhere else rather than the same region at another
    multiplier; its first variant is the one without it."""
    lo, hi = map(float, multipliers)
    if variants and not (np.isfinite(hi) and 0.05 <= lo <= hi):
        raise ConfigError(f"hotspot_multipliers {list(multipliers)}: a range [low, high] with 0.05 <= low <= high (one decimal is kept)")
    names: list[str] = []
    for i, name in enumerate(cities if variants else []):
        city = load_city(name)
        out = place_table(city)[:, 2].astype(np.float64)
        draws = _region_draws(partial(hotspot_name, name), out, np.random.default_rng([seed, i, 6029]), lo, hi, distinct_regions)
        if (mine := first_distinct(draws, variants)) is None:
            raise ConfigError(f"{variants} distinct hotspot variants of {name} not found in hotspot_multipliers {list(multipliers)} "
                              f"(one decimal) x its busy regions{' (each region once: hotspot_distinct_regions)' if distinct_regions else ''}: "
                              "ask for fewer, or widen the range")  # fmt: skip
        names += mine
    return names


def _region_draws(
    name_of: Callable[[int, float], str], weights: np.ndarray, rng: np.random.Generator, lo: float, hi: float, distinct_regions: bool = False
) -> Iterator[str | None]:
    """Endless task names ``name_of(region, multiplier)``: the region drawn by ``weights`` (N,), the
    multiplier log-uniform in [lo, hi] (one decimal); with ``distinct_regions`` a region drawn again yields None."""
    used: set[int] = set()  # with distinct_regions a region not used yet names a new task, so every yield is kept
    while True:
        region = int(rng.choice(len(weights), p=weights / weights.sum()))
        multiplier = round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), 1)
        if distinct_regions and region in used:
            yield None
            continue
        used.add(region)
        yield name_of(region, multiplier)


def sink_tasks(cities: list[str], variants: int, multipliers: tuple[float, float], seed: int) -> list[str]:
    """``variants`` sink variants of each city (:func:`~marl_amod.scenario.variants.sink`): the
    region drawn by its share of the day's requests *in* (busy destinations become sinks more
    often), the multiplier log-uniform in ``multipliers`` (one decimal); a function of the seed, so
    a resumed run names the same tasks."""
    lo, hi = map(float, multipliers)
    if variants and not (np.isfinite(hi) and 0.05 <= lo <= hi):
        raise ConfigError(f"sink_multipliers {list(multipliers)}: a range [low, high] with 0.05 <= low <= high (one decimal is kept)")
    names: list[str] = []
    for i, name in enumerate(cities if variants else []):
        city = load_city(name)
        into = np.asarray(city.forecast_rate)[: city.horizon].sum(axis=(0, 1))
        draws = _region_draws(partial(sink_name, name), into, np.random.default_rng([seed, i, 8087]), lo, hi)
        if (mine := first_distinct(draws, variants)) is None:
            raise ConfigError(f"{variants} distinct sink variants of {name} not found in sink_multipliers {list(multipliers)} "
                              "(one decimal) x its busy destinations: ask for fewer, or widen the range")  # fmt: skip
        names += mine
    return names


def skew_tasks(cities: list[str], variants: int, gammas: tuple[float, float], seed: int) -> list[str]:
    """``variants`` skew variants of each city (:func:`~marl_amod.scenario.variants.skew`), gamma
    log-uniform in ``gammas`` (one decimal; gamma 1, the city itself, and a repeat are drawn again);
    a function of the seed, so a resumed run names the same tasks."""
    lo, hi = map(float, gammas)
    if variants and not (np.isfinite(hi) and 0.1 <= lo <= hi):
        raise ConfigError(f"skew_gammas {list(gammas)}: a range [low, high] with 0.1 <= low <= high (one decimal is kept)")
    names: list[str] = []
    for i, name in enumerate(cities if variants else []):
        rng = np.random.default_rng([seed, i, 7057])
        gammas_drawn = (round(float(np.exp(rng.uniform(np.log(lo), np.log(hi)))), 1) for _ in itertools.count())
        if (mine := first_distinct((skew_name(name, g) if g != 1 else None for g in gammas_drawn), variants)) is None:
            raise ConfigError(f"{variants} distinct skew variants of {name} not found in skew_gammas {list(gammas)} "
                              "(one decimal, gamma 1 excluded): ask for fewer, or widen the range")  # fmt: skip
        names += mine
    return names


# --------------------------------------------------------------------------------------------
# The agent: a policy with memory on one city, B trials in lockstep
# --------------------------------------------------------------------------------------------
class MetaAgent:
    """The recurrent policy on one city for B trials in lockstep: its scale, graph, memory (B, N, H)
    and previous action / rewards. It acts on a :class:`BatchFleetSystem` of B episodes, or (B = 1)
    on a :class:`FleetSystem`, the deployed case."""

    def __init__(self, model: RecurrentGNN, city: City, lookahead: int, num_trials: int = 1) -> None:
        self.model, self.city, self.lookahead, self.num_trials = model, city, lookahead, num_trials
        self.scale, (self.structure, self.place) = CityScale.of(city), features_read(model, lookahead)
        self.graph = city_graph(city)
        self.memory = model.initial_memory(city.n_regions, num_trials)  # a new trial: nothing known yet
        self.concentration: float | None = None  # sampled actions: Dirichlet(this x mean) instead of the model's alpha (adapt)
        self.new_episode()

    def new_episode(self) -> None:
        """Previous action and rewards restart; the memory does not (that is the adaptation)."""
        b, n = self.num_trials, self.city.n_regions
        self.prev_action, self.prev_region_reward, self.prev_reward = torch.zeros(b, n), torch.zeros(b, n), torch.zeros(b)

    def act(self, system: FleetSystem | BatchFleetSystem, sample: bool) -> tuple[np.ndarray, torch.Tensor, torch.Tensor, torch.Tensor]:
        """(weights (B, N), log pi (B,), entropy (B,), value (B,)) and the memory moves one step."""
        b, n = self.num_trials, self.city.n_regions
        x = torch.as_tensor(task_features(system, self.scale, self.lookahead, self.structure, self.place, self.model.end_cut)).reshape(b, n, -1)
        alpha, v, self.memory = self.model(x, self.prev_action, self.prev_region_reward, self.prev_reward, self.memory, self.graph)
        dist = dirichlet(alpha if self.concentration is None else self.concentration * alpha / alpha.sum(-1, keepdim=True))
        if sample:
            y = dist.sample().clamp_min(1e-6)
            y = y / y.sum(-1, keepdim=True)
        else:
            y = alpha / alpha.sum(-1, keepdim=True)  # the Dirichlet mean, as every deterministic evaluation
        y = y.detach()
        self.prev_action = y * n  # mean 1 per region in every city
        return y.numpy().astype(np.float64), dist.log_prob(y), dist.entropy(), v

    def executed(self, shares: np.ndarray) -> None:
        """Record the shares of the idle fleet the fleet actually took ((B, N), or (N,) for B = 1) as the
        previous action, in the units :meth:`act` records its own: an ensemble's member is told the mean."""
        self.prev_action = torch.as_tensor(shares * self.city.n_regions, dtype=torch.float32).reshape(self.num_trials, self.city.n_regions)

    def observe(self, region_reward: np.ndarray) -> np.ndarray:
        """Feed the step's per-region rewards back (money, (B, N)) in per-city units; returns the
        scaled team rewards (B,)."""
        per_region = np.asarray(region_reward, dtype=np.float64).reshape(self.num_trials, self.city.n_regions)
        team = per_region.sum(-1) / self.scale.reward
        self.prev_region_reward = torch.as_tensor(per_region * (self.city.n_regions / self.scale.reward), dtype=torch.float32)
        self.prev_reward = torch.as_tensor(team, dtype=torch.float32)
        return team


@dataclass
class Trial:
    """What B trials in lockstep produced: S = episodes x steps decisions each."""

    logps: torch.Tensor  # (S, B)
    entropies: torch.Tensor  # (S, B)
    values: torch.Tensor  # (S, B)
    rewards: np.ndarray  # (S, B) scaled team rewards
    profits: np.ndarray  # (K, B) money of each episode, its first dispatch included


def run_trials(agent: MetaAgent, system: BatchFleetSystem, seeds: list[list[np.random.SeedSequence]], sample: bool = True) -> Trial:
    """Episode k of trial b draws its demand from ``seeds[k][b]``; the memory is carried across the K episodes."""
    logps, ents, values, rewards, profits = [], [], [], [], []
    for row in seeds:
        profit = system.reset(row).reward  # (B,) the first dispatch: before any decision
        agent.new_episode()
        while not system.done:
            w, logp, ent, v = agent.act(system, sample)
            out = system.step(system.targets_from_weights(w))
            logps.append(logp), ents.append(ent), values.append(v)
            rewards.append(agent.observe(out.region_reward))
            profit = profit + out.reward
        profits.append(profit)
    return Trial(torch.stack(logps), torch.stack(ents), torch.stack(values), np.stack(rewards), np.stack(profits))


def advantages(rewards: np.ndarray, values: torch.Tensor, gamma: float, lam: float) -> tuple[torch.Tensor, torch.Tensor]:
    """GAE(lambda) over trials (S, B), terminal at each trial's end; returns (advantages, value targets) (S, B)."""
    v = values.detach().numpy().astype(np.float64)
    adv, running = np.zeros_like(v), np.zeros(v.shape[1:])
    for t in reversed(range(len(rewards))):
        nxt = v[t + 1] if t + 1 < len(rewards) else 0.0
        running = rewards[t] + gamma * nxt - v[t] + gamma * lam * running
        adv[t] = running
    adv_t = torch.as_tensor(adv, dtype=torch.float32)
    return adv_t, adv_t + values.detach()


# --------------------------------------------------------------------------------------------
# Training
# --------------------------------------------------------------------------------------------
class Args(C.RunArgs):
    scenario: str = "nyc_brooklyn"
    """not trained on: the held-out city the run's card names; training draws from ``cities``"""
    cities: list[str] = Field(default_factory=lambda: list(TRAIN_CITIES), min_length=1)
    """training cities (tasks); the held-out ones must not be among them"""
    hidden: int = Field(64, ge=1)
    """memory and hidden units of the recurrent GNN"""
    conv: Literal["gcn", "sage"] = "sage"
    """message passing between regions' memories"""
    city_features: bool = False
    """the policy also reads the city's structure (:func:`structure_table`: expected requests into
    each region, trip and rebalancing times, the cost of driving): what a single-city policy
    memorises and a policy for many cities must be told"""
    place_features: bool = False
    """with ``city_features``, also where each region lies in its city (:func:`place_table`:
    rebalancing times to and from the rest, its shares of the day's demand and of the fleet)"""
    readout: Readout = "none"
    """a fleet-wide pool (mean and/or max) appended to each region's memory and messages before the
    heads (:class:`~marl_amod.models.gnn.FleetReadout`)"""
    stay_prior: bool = False
    """the actor outputs log-ratios to the idle vehicles' distribution (:class:`RecurrentGNN`): untrained, it keeps vehicles where they are"""
    demand_prior: float = Field(0.0, ge=0, le=0.9)
    """with ``stay_prior``, the share of the prior given to the regions' requests (:func:`demand_columns`):
    a busy region its own demand has emptied keeps weight (:class:`RecurrentGNN`)"""
    centred_actor: bool = False
    """with ``stay_prior``, the actor's log-ratios centred over the city's regions (:class:`RecurrentGNN`):
    their common level, which imitation never trains, cannot drift (nor stall the actor past the clamp).
    For imitation (``meta-bc``): RL² trains that level, the only way it sets how widely it samples"""
    end_cut: bool = False
    """the task features show no demand past the episode's last step, as MPC-Forecast plans (:func:`cut_at_end`)"""
    episodes: int = Field(20000, ge=1)
    """training episodes in all (updates x cities_per_update x num_envs x trial_episodes)"""
    trial_episodes: int = Field(6, ge=2, le=11)
    """episodes per trial on one city with memory carried; adaptation uses one fewer"""
    num_envs: int = Field(16, ge=1)
    """trials of one city run in lockstep on the batched simulator (one (B, N, F) pass per step)"""
    cities_per_update: int = Field(2, ge=1)
    """cities drawn per gradient step, each running ``num_envs`` trials"""
    shock_prob: float = Field(0.0, ge=0, le=1)
    """share of the city draws that get a random demand shock for their trials (:func:`random_shock`)"""
    lr: float = Field(1e-3, gt=0)
    """Adam learning rate (actor and critic share the recurrent trunk)"""
    gae_lambda: float = Field(0.95, ge=0, le=1)
    """GAE lambda of the advantages"""
    value_coef: float = Field(0.5, ge=0)
    """weight of the critic loss"""
    entropy_coef: float = Field(0.0, ge=0)
    """weight of the policy entropy bonus"""
    max_grad_norm: float = Field(1.0, gt=0)
    """gradient clipping (recurrent nets need it tight)"""
    bc_coef: float = Field(0.0, ge=0)
    """weight of an imitation term on MPC-Forecast demonstrations (``demos``) added to each update:
    keeps an imitation warm start (``init_actor``, :mod:`.meta_imitation`) from drifting while
    A2C's noisy signal accumulates"""
    demos: str = "runs/meta_demos"
    """folder of the MPC-Forecast demonstrations (:func:`.meta_imitation.collect_demos`), read when ``bc_coef`` > 0"""
    imitation: O.Imitation = "ce"
    """the actor's loss against MPC-F's shares (:func:`marl_amod.algos.offline.shares_loss`), in meta-bc's
    training and in RL²'s ``bc_coef`` term (which should pull a warm start towards what it was fitted to):
    ce, the cross-entropy, which near its optimum prices a vehicle off at a region holding a third of the
    fleet some 30 times less than at one holding 1%; l1, every vehicle alike (the offline clone of
    MPC-F in Brooklyn, whose error was at the busiest regions too, halved its gap with it)"""
    shortfall_weight: float = Field(0.0, ge=0)
    """with ``imitation: l1``, a vehicle short at a receiving region (:func:`.meta_imitation.receiving`) costs
    1 + this times one over: a vehicle short there leaves requests unserved (offline's selected weight: 2)"""
    more_demos: list[str] = []
    """folders of more labelled episodes joined to ``demos`` (an earlier run's DAgger rounds,
    ``<run_dir>/dagger/round<k>``): a run continuing a DAgger run keeps the states its rounds reached"""
    val_cities: list[str] = Field(default_factory=lambda: ["porto", "nyc_man_north", "shenzhen_north", "washington_dc"], min_length=1)
    """training cities whose adapted profit (``eval_episodes`` trials each, validation seeds) picks the best model"""
    eval_every: int = Field(600, ge=1)
    """episodes between validations (and training-state saves)"""
    adaptation: Adaptation = "sampled"
    """how the policy acts in its adaptation episodes (:func:`adapt`): in validation, in meta-bc's DAgger
    trials and, read from its card, when deployed. RL²'s training trials always sample (their gradient
    needs the draws)"""
    stall_validations: int = Field(5, ge=0)
    """stop, with a warning and the card's ``stalled_at``, when this many validations in a row lie within
    ``STALL_TOL`` of each other: the policy no longer moves (a stay-prior actor past its clamp did so
    for 2,400 updates in silence: docs/meta/log.md, "Why seed 7 stalled"); 0: never"""
    run_dir: str = "runs/meta"
    """logs, the resumable training state"""

    @model_validator(mode="after")
    def _prior(self) -> Args:
        if self.demand_prior and not self.stay_prior:  # refused with the config, not after the demonstrations
            raise ValueError(f"demand_prior {self.demand_prior} mixes into the stay prior: set stay_prior too")
        if self.centred_actor and not self.stay_prior:
            raise ValueError("centred_actor centres the log-ratios to the stay prior: set stay_prior too")
        if self.shortfall_weight and self.imitation != "l1":
            raise ValueError(f"shortfall_weight {self.shortfall_weight} with imitation {self.imitation!r}: only l1 prices a "
                             "vehicle short apart (set imitation: l1, or shortfall_weight: 0)")  # fmt: skip
        return self

    def trained_on(self) -> str:
        return f"{len(self.cities)} training cities"  # the scenario is only where its card is evaluated

    def ignored_keys(self) -> dict[str, str]:
        return {"actor": "meta-RL always uses the recurrent GNN", "mode": "meta-RL is centralised",
                "central_critic": "meta-RL is centralised", "critic_time": "the recurrent critic reads t / horizon already",
                "actor_time": "the recurrent actor reads t / horizon already",
                "arrivals_now": "meta-RL reads its own task features (task_features), not the env's node columns",
                "final_eval_seed": "the held-out card evaluation runs on the validation streams (eval_seed); report seeds: marl-amod evaluate"}  # fmt: skip


def make_model(args: Args) -> RecurrentGNN:
    """The run's recurrent GNN (its inputs: the task features and the optional column sets)."""
    n_features = n_task_features(args.lookahead, args.city_features, args.place_features)
    return RecurrentGNN(n_features, args.hidden, args.conv, args.stay_prior, args.readout, args.demand_prior, demand_columns(args.lookahead),
                        end_cut=args.end_cut, centred=args.centred_actor)  # fmt: skip


def held_out_among(tasks: list[str]) -> list[str]:
    """The held-out cities that ``tasks`` are, or are variants of (hotspot, skew, event task), or that a
    scenario of theirs is built on (sorted): ``nyc_brooklyn_event`` (``extends: nyc_brooklyn``) is
    Brooklyn's data with the event the study tests, not another city."""
    held = {_data_of(name) for name in HELD_OUT} - {None}
    return sorted({base for base in map(base_city, tasks) if base in HELD_OUT or _data_of(base) in held})


def _data_of(scenario: str) -> str | None:
    """The data file a scenario's city is built from (None: a synthetic or unknown one), read from its YAML."""
    try:
        data = getattr(load_spec(scenario), "data_file", None)
    except ConfigError:  # not a scenario: loading the task says so where it is used
        return None
    if data is None:
        return None
    try:
        return str(resolve(data).resolve())
    except DataError:  # no data here: the name as written still tells the file
        return str(data)


def check_tasks(args: Args) -> None:
    bases = {base_city(name) for name in args.cities}
    leaked = held_out_among(args.cities) + ([args.scenario] if args.scenario in bases else [])
    if leaked:
        raise ConfigError(f"meta-RL training cities include held-out {sorted(set(leaked))}; the study tests on them")
    if chosen_on := held_out_among(args.val_cities):  # the best model would be chosen on the test cities
        raise ConfigError(f"meta-RL validation cities (val_cities) include held-out {chosen_on}; the study tests on them")


def adapting(agent: MetaAgent, adaptation: Adaptation) -> bool:
    """Set ``agent`` up to act by ``adaptation`` in adaptation episodes (:func:`adapt`); whether it samples."""
    if adaptation == "prior-concentration":
        agent.concentration = STAY_CONCENTRATION * agent.city.n_regions
    return adaptation != "mean"


def validate(model: RecurrentGNN, args: Args, cities: dict[str, City]) -> float:
    """Mean scaled profit of the last (deterministic) episode of ``eval_episodes`` trials on each
    validation city, their adaptation episodes played by ``args.adaptation``."""
    scores, b = [], args.eval_episodes
    with torch.no_grad():
        for name in args.val_cities:
            agent, system = MetaAgent(model, cities[name], args.lookahead, b), BatchFleetSystem(cities[name], b)
            sample = adapting(agent, args.adaptation)
            run_trials(agent, system, [[adapt_seed(args.eval_seed, k, j) for j in range(b)] for k in range(args.trial_episodes - 1)], sample)
            last = run_trials(agent, system, [[np.random.SeedSequence([args.eval_seed, j]) for j in range(b)]], sample=False)
            scores.append(float(last.profits.mean()) / (cities[name].horizon * agent.scale.reward))
    return float(np.mean(scores))


STALL_TOL = 1e-4  # relative spread of validations that counts as "not moving": converged runs still move ~1e-3


def stalled(values: list[float], rounds: int) -> bool:
    """Whether the last ``rounds`` validations (>= 2) lie within ``STALL_TOL`` of each other."""
    last = values[-rounds:]
    return rounds >= 2 and len(last) == rounds and max(last) - min(last) <= STALL_TOL * max(abs(float(np.mean(last))), 1e-12)


@dataclass
class MetaBook:
    """What meta-RL and its imitation warm start do after every update, in one place: validate when
    due and at the time limit (keeping the best model), save the resumable state, log, report
    progress; ``best`` lives here so the state saved on an interrupt is the one validation kept."""

    args: Args
    model: RecurrentGNN
    cities: dict[str, City]
    log: C.Logger
    timer: C.Timer
    best: C.BestActor
    progress: C.Progress | None = None
    validations: list[float] = field(default_factory=list)  # this process's, in order (a resume starts afresh)
    stalled_at: int | None = None  # the update at which the validations stopped moving (``Args.stall_validations``)

    def close(self, count: int, total: int, stats: dict[str, float], due: bool, save: Callable[[], Any]) -> bool:
        """After update ``count`` (of ``total``): validate if ``due`` or out of time, log; True when
        time is up or the validations have stalled. A Ctrl-C pressed during the update stops the run here, once it is logged."""
        out_of_time = bool(self.args.time_limit_s) and self.timer() > self.args.time_limit_s  # validate the last model too
        if due or out_of_time:
            stats["eval/scaled_return"] = val = validate(self.model, self.args, self.cities)
            if val > self.best.value:
                self.best = C.BestActor(val, copy.deepcopy(self.model.state_dict()))
            self.validations.append(val)
            if stalled(self.validations, self.args.stall_validations):
                self.stalled_at = count
                warnings.warn(f"{self.args.run_dir}: the last {self.args.stall_validations} validations lie within {STALL_TOL:g} of "
                              f"{val:.5f} (update {count}): the policy no longer moves; stopping and keeping the best "
                              "(stall_validations: 0 never stops)", RuntimeWarning, stacklevel=2)  # fmt: skip
            save()
        stats["time/wall_s"] = self.timer()
        self.log.log(count, **stats)
        if self.progress is not None:
            self.progress(count, total, stats)
        C.stop_if_asked()
        return out_of_time or self.stalled_at is not None

    def card_fields(self) -> dict[str, Any]:
        """What the card says of how the run ended, beside its updates: ``stalled_at`` when it stalled."""
        return {} if self.stalled_at is None else {"stalled_at": self.stalled_at}


def warm_start(args: Args, model: RecurrentGNN, cities: dict[str, City], resume: str | None) -> tuple[C.BestActor, dict[str, Any]]:
    """Load ``init_actor`` (a meta-policy file: the MPC-F imitation) into ``model`` on a fresh run and
    validate it first, so it is kept unless training beats it; (the best so far, the card's ``warm_start``)."""
    if not args.init_actor:
        return C.BestActor.of(model), {}
    start, card = load_meta(args.init_actor, like=None if args.city_features or args.readout != "none" else model)
    warm = {"warm_start": {k: card.get(k) for k in ("algorithm", "updates", "training_wall_s", "demonstrations", "dagger")} | {"policy": args.init_actor}}
    if resume:  # the resumed state brings its own model and best
        return C.BestActor.of(model), warm
    model.load_state_dict(widened(start, model))
    value = validate(model, args, cities)
    warm["warm_start"]["validation"] = value  # what training had to beat: the card says whether the start was kept
    return C.BestActor(value, copy.deepcopy(model.state_dict())), warm


def widened(start: RecurrentGNN, model: RecurrentGNN) -> dict[str, torch.Tensor]:
    """``start``'s weights for ``model``, which may read more: more features (the structure and
    place columns after the task features) or a fleet readout before the heads. What is new
    enters through zero weights (the input columns of the encoder, the readout's columns of each
    head's first layer; the readout's own map keeps ``model``'s initialisation), so the widened
    model starts as the same policy, free to use them."""
    state, ours = start.state_dict(), model.state_dict()
    new = set(ours) - set(state)
    if (start.n_features > model.n_features or set(state) - set(ours) or start.stay_prior != model.stay_prior
            or start.hidden != model.hidden or (new and start.readout is not None) or any(not k.startswith("readout.") for k in new)):  # fmt: skip
        raise DataError(f"init_actor reads {start.n_features} features, hidden {start.hidden}, readout {start.readout_kind}; "
                        "this run's model cannot extend it")  # fmt: skip
    weight = state["encode.0.weight"]  # (H, F + feedback): the new columns go between the features and the feedback
    zeros = weight.new_zeros(weight.shape[0], model.n_features - start.n_features)
    state["encode.0.weight"] = torch.cat([weight[:, : start.n_features], zeros, weight[:, start.n_features :]], dim=1)
    for head in ("actor.0.weight", "critic.0.weight"):  # (H, 2H [+ kH]): the readout's columns come last
        weight = state[head]
        state[head] = torch.cat([weight, weight.new_zeros(weight.shape[0], ours[head].shape[1] - weight.shape[1])], dim=1)
    return state | {k: ours[k] for k in new}


def train(args: Args, *, resume: str | None = None, progress: C.Progress | None = None, config_path: str | None = None) -> dict[str, Any]:
    """Meta-train over trials on the training cities, keep the best validated model, write its card."""
    check_tasks(args)
    torch.set_num_threads(args.threads)
    C.seed_everything(args.seed)
    cities = {name: load_city(name) for name in dict.fromkeys([*args.cities, *args.val_cities])}
    systems = {name: BatchFleetSystem(cities[name], args.num_envs) for name in args.cities}  # reused: the coordinator caches per city
    model = make_model(args)
    opt = torch.optim.Adam(model.parameters(), lr=args.lr)
    rng = np.random.default_rng([args.seed, 17])  # which city (and shock) each draw gets

    start_ep, prior_wall = 0, 0.0
    best, warm = warm_start(args, model, cities, resume)
    imitation = None
    if args.bc_coef > 0:
        from marl_amod.algos.meta_imitation import Fit, draw_trials, imitation_losses, load_all

        imitation, fit = load_all(args, cities), Fit(imitation=args.imitation, shortfall=args.shortfall_weight)
    if resume:
        st = C.load_state(resume, "meta", args)
        C.restore(resume, st, model=model, opt=opt)
        start_ep, prior_wall, best = st["episode"], st["wall_s"], C.BestActor(st["best_val"], st["best_actor"])
        rng.bit_generator.state = st["city_rng"]
    log = C.Logger(args.run_dir, resume_from=start_ep if resume else None)
    timer = C.Timer(prior_wall)
    book = MetaBook(args, model, cities, log, timer, best, progress)
    done_ep = ep = start_ep
    b, k_eps = args.num_envs, args.trial_episodes
    per_update = args.cities_per_update * b * k_eps

    def save() -> tuple[Path, int]:
        path = C.state_path(args)
        C.save_state(path, args, algorithm="meta", model=model.state_dict(), opt=opt.state_dict(), episode=done_ep,
                     best_val=book.best.value, best_actor=book.best.state, wall_s=timer(), city_rng=rng.bit_generator.state)  # fmt: skip
        return path, done_ep

    with C.interruptible(save):
        while ep < args.episodes:
            losses, profits, rewards, shocked = [], [], [], 0
            for _ in range(args.cities_per_update):
                name = args.cities[int(rng.integers(len(args.cities)))]
                city, system = cities[name], systems[name]
                if args.shock_prob and rng.random() < args.shock_prob:
                    city = random_shock(city, rng)
                    system, shocked = BatchFleetSystem(city, b), shocked + 1
                agent = MetaAgent(model, city, args.lookahead, b)
                # episode k of trial j: training stream ep + k * B + j, each used once
                trial = run_trials(agent, system, [[train_seed(args.seed, ep + k * b + j) for j in range(b)] for k in range(k_eps)])
                ep += b * k_eps
                adv, target = advantages(trial.rewards, trial.values, args.gamma, args.gae_lambda)
                adv = (adv - adv.mean()) / (adv.std() + 1e-8)
                loss = (-(trial.logps * adv).mean() + args.value_coef * F.smooth_l1_loss(trial.values, target)
                        - args.entropy_coef * trial.entropies.mean())  # fmt: skip
                losses.append(loss)
                profits.append(float(trial.profits[-1].mean()) / (city.horizon * agent.scale.reward))
                rewards.append(float(trial.rewards.mean()))
            total = torch.stack(losses).mean()
            if imitation is not None:  # one city's trials of MPC-F demonstrations, teacher-forced
                demos, graph = imitation[args.cities[int(rng.integers(len(args.cities)))]]
                ce, vl = imitation_losses(model, demos, draw_trials(demos, args, rng), graph, args.gamma, fit)
                total = total + args.bc_coef * (ce + args.value_coef * vl)
            opt.zero_grad()
            total.backward()
            torch.nn.utils.clip_grad_norm_(model.parameters(), args.max_grad_norm)
            opt.step()
            done_ep = ep

            stats = {"train/last_episode_scaled_profit": float(np.mean(profits)), "train/scaled_reward": float(np.mean(rewards)),
                     "train/shocked_cities": shocked, "loss/total": total.item()}  # fmt: skip
            if book.close(ep, args.episodes, stats, C.crossed(ep, per_update, args.eval_every) or ep >= args.episodes, save):
                break

    log.close()
    model.load_state_dict(book.best.state)
    return finish(args, model, timer(), ep, config_path, extra=warm | book.card_fields())


def finish(
    args: Args, model: RecurrentGNN, wall_s: float, episodes: int, config_path: str | None, algorithm: str = "meta",
    extra: dict[str, Any] | None = None,
) -> dict[str, Any]:
    """Adapt to the held-out ``scenario`` and evaluate there on the *validation* streams
    (``eval_seed``, the card's ``eval_seed``: the report seeds 0..9 are scored once per shipped
    change, by ``marl-amod evaluate``, never by a training run), then the policy card (``extra``:
    algorithm-specific fields, e.g. the demonstrations an imitation run learned from)."""
    from marl_amod.checkpoints import make_card, save_policy
    from marl_amod.evaluation import evaluate
    from marl_amod.files import write_json

    city = load_city(args.scenario)
    policy = adapt(model, city, args.trial_episodes - 1, args.lookahead, seed=args.eval_seed, adaptation=args.adaptation)
    result = evaluate(policy, city, args.final_eval_episodes, args.eval_seed)
    profit = result["metrics"]["profit"]
    card = make_card(
        scenario=city.name, n_regions=None, algorithm=algorithm, mode="centralised", actor="recurrent", conv=args.conv,
        hidden=args.hidden, n_features=model.n_features, lookahead=args.lookahead, seed=args.seed,
        episodes_trained=episodes, eval_episodes=args.final_eval_episodes, eval_seed=args.eval_seed, eval_streams="validation",
        profit_mean=profit["mean"], profit_std=profit["std"], served_demand_mean=result["metrics"]["served_demand"]["mean"],
        training_wall_s=round(wall_s, 1), torch_threads=torch.get_num_threads(), config=config_path,
        args=args.model_dump(mode="json"), **(extra or {}),
    ).to_dict()
    summary: dict[str, Any] = {"card": card, "result": result}
    if args.policy_out:
        summary["policy"] = str(save_policy(args.policy_out, model, card))
    Path(args.run_dir).mkdir(parents=True, exist_ok=True)
    write_json(Path(args.run_dir) / "final_eval.json", result)
    return summary


# --------------------------------------------------------------------------------------------
# Adaptation to a new city: K episodes with memory, no gradient step
# --------------------------------------------------------------------------------------------
def adapt_seed(seed: int, episode: int, trial: int = 0) -> np.random.SeedSequence:
    """Demand of adaptation episode k (of trial j): neither a report stream (seed, k) nor a training stream."""
    return np.random.SeedSequence([seed, episode, 4243] + ([trial] if trial else []))


class MetaPolicy(WeightPolicy):
    """The recurrent policy after adaptation: every episode starts from the adapted memory."""

    def __init__(self, agent: MetaAgent, name: str = "meta-rl") -> None:
        self.agent, self.name = agent, name
        self.adapted = agent.memory.detach().clone()

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        check_bound_city(self.name, self.agent.city, system)  # adapted there: its memory is of that city
        super().reset(system, rng)
        self.agent.memory = self.adapted.clone()
        self.agent.new_episode()
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    @torch.no_grad()
    def weights(self, system: FleetSystem) -> np.ndarray:
        totals = system.sim.totals  # booked as BatchFleetSystem books a step: profit and cost apart
        booked = (totals.revenue - totals.trip_cost, totals.rebalancing_cost.copy())
        if self._last is not None:  # the step just taken: each region's dispatch profit minus its rebalancing cost
            self.agent.observe((booked[0] - self._last[0]) - (booked[1] - self._last[1]))
        self._last = booked
        return self.agent.act(system, sample=False)[0][0]

    def executed(self, weights: np.ndarray) -> None:
        self.agent.executed(weights)


@contextlib.contextmanager
def adaptation_stream(seed: int) -> Iterator[None]:
    """Torch's random stream for adaptation episodes, drawn from ``seed`` and restored after. Why: the
    adaptation samples its actions; from a stream of the seed, not torch's global one, the same policy
    file(s), city and seed always adapt to the same memory (and report the same numbers)."""
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(int(np.random.SeedSequence([seed, 4243, 7]).generate_state(1)[0]))
        yield


def trained_adaptation_episodes(card: dict[str, Any]) -> int:
    """K a meta-policy adapts for by default: the trial length it was trained with, minus the scored episode."""
    return card["args"]["trial_episodes"] - 1


def trained_adaptation(card: dict[str, Any], override: Adaptation | None = None) -> Adaptation:
    """How a meta-policy acts while adapting: ``override`` if given, else as its card says ("sampled" on older cards)."""
    return override or card["args"].get("adaptation", "sampled")


@torch.no_grad()
def adapt(model: RecurrentGNN, city: City, episodes: int, lookahead: int, seed: int = 0, adaptation: Adaptation = "sampled") -> MetaPolicy:
    """Run ``episodes`` adaptation episodes in ``city`` (memory carried, no gradient) -> the policy.

    ``adaptation``: how it acts there. "sampled" (as trained: the DAgger trials' first episodes
    sample too) draws from its Dirichlet, whose concentration, for a stay-prior actor that is not
    ``centred``, is set by a level imitation never trained (180x apart across one recipe's seeds:
    docs/meta/log.md, "Why seed 7 stalled"); "mean" plays the Dirichlet mean, as the scored
    episodes do; "prior-concentration" samples around the mean with the stay prior's total
    concentration (``STAY_CONCENTRATION`` x N), what a centred actor's level-0 output gives."""
    model.eval()
    agent = MetaAgent(model, city, lookahead)
    sample = adapting(agent, adaptation)
    with adaptation_stream(seed):
        if episodes:  # K = 0: zero-shot, the memory of a new trial
            run_trials(agent, BatchFleetSystem(city, 1), [[adapt_seed(seed, k)] for k in range(episodes)], sample=sample)
    return MetaPolicy(agent)


@torch.no_grad()
def adapt_together(models: list[tuple[RecurrentGNN, int]], city: City, episodes: int, seed: int = 0,
                   adaptations: list[Adaptation] | None = None) -> list[MetaPolicy]:
    """Adapt several meta-policies (model, look-ahead) as the ensemble they will act as: ``episodes``
    episodes in ``city`` in all, each step the mean of their actions (each sampled as its
    ``adaptations`` says, default "sampled") executed, each member's memory reading that executed
    action and the rewards it earned. Why: adapted alone, a member's memory describes the path it
    drove alone, and it then acts on the ensemble's path; together, it adapts on that path, and an
    ensemble of m members plays K episodes in the target, not m x K (docs/meta/log.md, "Members
    adapted together")."""
    agents = [MetaAgent(model.eval(), city, lookahead) for model, lookahead in models]
    samples = [adapting(agent, a) for agent, a in zip(agents, adaptations or ["sampled"] * len(agents), strict=True)]
    system = BatchFleetSystem(city, 1)
    with adaptation_stream(seed):  # as adapt: the same files, city and seed adapt alike
        for k in range(episodes):
            system.reset([adapt_seed(seed, k)])
            for agent in agents:
                agent.new_episode()
            while not system.done:
                shares = [agent.act(system, sample)[0] for agent, sample in zip(agents, samples, strict=True)]
                executed = np.mean([w / w.sum(-1, keepdims=True) for w in shares], axis=0)  # (1, N)
                out = system.step(system.targets_from_weights(executed))
                for agent in agents:
                    agent.executed(executed)
                    agent.observe(out.region_reward)
    return [MetaPolicy(agent) for agent in agents]


META_ALGOS = ("meta", "meta-bc")  # the cards of a recurrent meta-policy: RL², or its MPC-F imitation


def load_meta(path: str | Path, like: RecurrentGNN | None = None) -> tuple[RecurrentGNN, dict[str, Any]]:
    """The recurrent model of a meta-RL policy file and its card (the weights checked against it,
    and against ``like``'s shapes when given: a warm start)."""
    from marl_amod.checkpoints import _card_of, _read_blob
    path = Path(path)
    blob = _read_blob(path)
    card = _card_of(path, blob["card"]).to_dict()
    if card["algorithm"] not in META_ALGOS:
        raise DataError(f"{path} is a {card['algorithm']} policy, not a meta-RL one")

    args = card["args"]
    model = RecurrentGNN(card["n_features"], card["hidden"], card["conv"], args.get("stay_prior", False), args.get("readout", "none"),
                         args.get("demand_prior", 0.0), demand_columns(card["lookahead"]), end_cut=args.get("end_cut", False),
                         centred=args.get("centred_actor", False))  # fmt: skip
    try:
        model.load_state_dict(blob["state_dict"])
    except RuntimeError as exc:
        raise DataError(f"{path}: weights do not fit its card: {str(exc).splitlines()[0]}") from None
    theirs, ours = model.state_dict(), (like.state_dict() if like is not None else None)
    if ours is not None and (set(theirs) != set(ours) or any(theirs[k].shape != ours[k].shape for k in ours)
                             or (model.stay_prior, model.demand_prior, model.end_cut, model.centred) != (like.stay_prior, like.demand_prior, like.end_cut, like.centred)):
        raise DataError(f"{path} is a recurrent GNN with {card['n_features']} features, hidden {card['hidden']}, {card['conv']}, "
                        f"readout {model.readout_kind}; this run's differs (set lookahead, hidden, conv, stay_prior, demand_prior, end_cut, centred_actor and readout to match)")  # fmt: skip
    model.eval()
    return model, card


def load_policy(path: str | Path, city: City, episodes: int | None = None, seed: int = 0, adaptation: Adaptation | None = None) -> MetaPolicy | PolicyEnsemble:
    """A meta-RL policy file adapted to ``city`` (``episodes`` adaptation episodes; default: the
    trial length it was trained with, minus one; acting by ``adaptation`` there, default: as its
    card's ``adaptation`` says, "sampled" on older cards: :func:`adapt`), ready for
    :func:`marl_amod.evaluation.evaluate`; an ensemble file (:mod:`marl_amod.ensemble`) of them, each
    member adapted alone (or, where the file says ``together``, all of them as one: :func:`load_together`),
    by the file's ``adaptation`` where it names one."""
    if is_ensemble(path):
        spec = read_spec(path)
        adaptation = spec.adaptation or adaptation
        if spec.together:
            return load_together(path, city, episodes, seed, adaptation)
        return load_ensemble(path, lambda member: load_policy(member, city, episodes, seed, adaptation))
    model, card = load_meta(path)
    k = trained_adaptation_episodes(card) if episodes is None else episodes
    adaptation = trained_adaptation(card, adaptation)
    policy = adapt(model, city, k, card["lookahead"], seed=seed, adaptation=adaptation)
    policy.name = Path(path).stem
    return policy


def load_together(path: str | Path, city: City, episodes: int | None = None, seed: int = 0, adaptation: Adaptation | None = None) -> PolicyEnsemble:
    """The ensemble file ``path`` of meta-policies adapted together to ``city`` (:func:`adapt_together`;
    ``episodes`` in all, default: the members' trial length minus one, which must agree)."""
    loaded = [(member, *load_meta(member)) for member in read_members(path)]
    if episodes is None:
        lengths = {trained_adaptation_episodes(card) for _, _, card in loaded}
        if len(lengths) > 1:
            raise ConfigError(f"ensemble {path}: its members were trained for {sorted(lengths)} adaptation episodes; "
                              "adapting together needs one number (give the episodes)")  # fmt: skip
        episodes = lengths.pop()
    adaptations = [trained_adaptation(card, adaptation) for _, _, card in loaded]
    policies = adapt_together([(model, card["lookahead"]) for _, model, card in loaded], city, episodes, seed, adaptations)
    for policy, (member, _, _) in zip(policies, loaded, strict=True):
        policy.name = Path(member).stem
    return PolicyEnsemble(list(policies), name=Path(path).stem)
