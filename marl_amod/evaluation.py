"""Run a policy for whole episodes on a scenario and collect the metrics JSON.

:func:`evaluate` is the one evaluation path: ``marl-amod evaluate``, ``marl_amod.evaluate``,
``compare`` and training's validation all call it, so every policy (a baseline, MPC, a trained
checkpoint, or an outside callable on observations) is scored on the same demand draws.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.baselines.base import Policy
from marl_amod.ensemble import ENSEMBLE_SUFFIXES
from marl_amod.errors import ConfigError
from marl_amod.metrics import episode_metrics, region_metrics, result_record
from marl_amod.policies import PolicyLike, make_policy
from marl_amod.scenario import City, load_city
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_seed

SYSTEM_OPTIONS = ("max_wait", "objective", "solver", "validate")  # FleetSystem's; every other option is the policy's


def episode_seeds(seed: int, episode: int) -> tuple[np.random.SeedSequence, np.random.Generator]:
    """Demand seed and policy random generator of episode ``episode`` of a run seeded ``seed``."""
    return np.random.SeedSequence([seed, episode]), np.random.default_rng([seed, episode, 1])


def run_episode(system: FleetSystem, policy: Policy, seed: int, episode: int = 0) -> tuple[dict, dict]:
    """One episode; returns (scalar metrics, per-region metrics)."""
    demand_seed, policy_rng = episode_seeds(seed, episode)
    system.reset(demand_seed)
    policy.reset(system, policy_rng)
    while not system.done:
        system.step(policy.target(system))
    city = system.city
    return episode_metrics(system.sim.totals, city.fleet_size, city.horizon), region_metrics(system.sim.totals)


def evaluate(
    policy: PolicyLike,
    scenario: str | Path | City = "synthetic",
    episodes: int = 10,
    seed: int = 0,
    *,
    progress: Callable[[int], None] | None = None,
    **options: Any,
) -> dict[str, Any]:
    """Evaluate one policy for ``episodes`` episodes; episode k draws demand from (seed, k).

    ``policy``: a registered name, a checkpoint path, a Policy, or a callable from the env's
    observations dict to its actions dict. ``options``: ``max_wait``, ``objective`` and
    ``solver`` set up the system; the rest go to the policy (e.g. MPC's ``horizon``, a
    callable's ``lookahead`` and ``action_mode``). Returns exactly the JSON that
    ``marl-amod evaluate --output`` writes for this policy.
    """
    if isinstance(policy, City) or isinstance(scenario, Policy):
        raise ConfigError("evaluate(policy, scenario, ...) takes the policy first, then the scenario")
    as_count(episodes, "episodes", lower=1)
    seed = as_seed(seed)
    city = scenario if isinstance(scenario, City) else load_city(str(scenario))
    system_options = {key: options.pop(key) for key in SYSTEM_OPTIONS if key in options}
    policy_options = dict(options)  # before make_policy: what the user asked for, as given
    pol = make_policy(policy, city, **options)
    system = FleetSystem(city, **system_options)
    per_episode, per_region = [], []
    for k in range(episodes):
        m, r = run_episode(system, pol, seed, k)
        per_episode.append(m)
        per_region.append(r)
        if progress is not None:
            progress(k)
    return result_record(city.name, pol.name, seed, per_episode, per_region, settings=run_settings(policy, system, system_options.get("max_wait", 0), policy_options))


def run_settings(policy: PolicyLike, system: FleetSystem, max_wait: int, policy_options: dict[str, Any]) -> dict[str, Any]:
    """What else decided the numbers, so two records can be told apart: the system's options, the
    policy's, and a checkpoint's path (two files may share a name)."""
    settings: dict[str, Any] = {
        "max_wait": int(max_wait), "objective": system.coordinator.objective, "solver": system.coordinator.solver,
        "policy_options": {k: v if isinstance(v, bool | int | float | str | type(None)) else repr(v) for k, v in policy_options.items()},
    }  # fmt: skip
    if isinstance(policy, str | Path) and Path(policy).suffix in (".pt", *ENSEMBLE_SUFFIXES) and Path(policy).is_file():
        settings["checkpoint"] = str(policy)
    return settings


def results_payload(results: list[dict[str, Any]]) -> dict[str, Any]:
    """What ``evaluate --output`` writes: one policy's record as is, several under their scenario."""
    if len(results) == 1:
        return results[0]
    return {"scenario": results[0]["scenario"], "results": results}
