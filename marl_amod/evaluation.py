"""Run policies for whole episodes on a scenario and collect the metrics JSON."""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from marl_amod.baselines import BASELINES, Policy
from marl_amod.errors import ConfigError
from marl_amod.metrics import episode_metrics, region_metrics, result_record
from marl_amod.scenario import City, load_city
from marl_amod.system import FleetSystem
from marl_amod.validation import as_count, as_seed

PolicyFactory = Callable[[City], Policy]
_EXTRA_POLICIES: dict[str, PolicyFactory] = {}


def register_policy(name: str, factory: PolicyFactory) -> None:
    """Make a policy available by name to :func:`make_policy` and the CLI."""
    _EXTRA_POLICIES[name] = factory


def policy_names() -> list[str]:
    return sorted(set(BASELINES) | set(_EXTRA_POLICIES))


def make_policy(name: str, city: City) -> Policy:
    """A policy by name (a baseline or a registered one) or from a checkpoint path (.pt)."""
    if name in BASELINES:
        return BASELINES[name]()
    if name in _EXTRA_POLICIES:
        return _EXTRA_POLICIES[name](city)
    if name.endswith(".pt"):
        from marl_amod.checkpoints import load_policy

        return load_policy(name, city)
    raise ConfigError(f"unknown policy {name!r}; known: {', '.join(policy_names())} or a checkpoint .pt path")


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
    scenario: str | City,
    policy: str | Policy,
    *,
    episodes: int = 10,
    seed: int = 0,
    progress: Callable[[int], None] | None = None,
    **system_kwargs: Any,
) -> dict[str, Any]:
    """Evaluate one policy for ``episodes`` episodes; episode k draws demand from (seed, k)."""
    if as_count(episodes, "episodes") < 1:
        raise ConfigError(f"episodes must be >= 1, got {episodes}")
    seed = as_seed(seed)
    city = load_city(scenario) if isinstance(scenario, str) else scenario
    pol = make_policy(policy, city) if isinstance(policy, str) else policy
    system = FleetSystem(city, **system_kwargs)
    per_episode, per_region = [], []
    for k in range(episodes):
        m, r = run_episode(system, pol, seed, k)
        per_episode.append(m)
        per_region.append(r)
        if progress is not None:
            progress(k)
    return result_record(city.name, getattr(pol, "name", str(policy)), seed, per_episode, per_region)
