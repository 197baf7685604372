"""Every policy behind one name lookup: baselines, MPC, behaviour policies, checkpoints, callables.

:data:`POLICIES` maps a name to a factory (usually the class), called with the policy's own
options (``make_policy("mpc-forecast", noise=0.2)``). :func:`make_policy` also accepts a path to
a trained checkpoint (``.pt``), a ready :class:`~marl_amod.baselines.base.Policy`, or any
callable from the env's observations dict to its actions dict (PettingZoo's convention, as SB3,
TorchRL or a hand-written rule provide), which it wraps in
:class:`~marl_amod.baselines.observation.ObservationPolicy`.

Adding a policy is one class (subclass :class:`~marl_amod.baselines.base.WeightPolicy`,
:class:`~marl_amod.baselines.base.FlowPolicy` or :class:`~marl_amod.baselines.base.Policy`,
whichever its output is) and one line in :data:`POLICIES`; the CLI, ``marl_amod.evaluate``,
``compare`` and ``collect`` then know it by name.
"""

from __future__ import annotations

import inspect
from collections.abc import Callable
from pathlib import Path
from typing import Any

from marl_amod.baselines import (
    DynamicTripVehicle,
    EqualDistribution,
    Informed,
    MPCForecast,
    MPCOracle,
    MPCScenarios,
    NoRebalancing,
    ObservationPolicy,
    PlusOne,
    Policy,
    Proportional,
    RandomPolicy,
)
from marl_amod.baselines.observation import ObservationFn
from marl_amod.ensemble import ENSEMBLE_SUFFIXES
from marl_amod.errors import ConfigError
from marl_amod.scenario.types import City

PolicyLike = str | Path | Policy | ObservationFn

POLICIES: dict[str, Callable[..., Policy]] = {
    "no-rebalancing": NoRebalancing,
    "equal-distribution": EqualDistribution,
    "plus-one": PlusOne,
    "random": RandomPolicy,
    "mpc-oracle": MPCOracle,
    "mpc-forecast": MPCForecast,
    "mpc-scenarios": MPCScenarios,
    "inf": Informed,
    "dtv": DynamicTripVehicle,
    "prop": Proportional,
}


def policy_names() -> list[str]:
    """The registered names, in registry order."""
    return list(POLICIES)


def make_policy(policy: PolicyLike, city: City | None = None, **options: Any) -> Policy:
    """A policy from a registered name, a checkpoint path (``.pt``, built for ``city``) or an
    ensemble file of them (``.yaml``), a Policy, or a callable on the env's observations;
    ``options`` go to the policy's factory."""
    if isinstance(policy, Policy):
        if options:
            raise ConfigError(f"options {sorted(options)} need a policy name or a callable, not a ready policy")
        return policy
    if isinstance(policy, (str, Path)):
        name = str(policy)
        if name in POLICIES:
            return _build(name, POLICIES[name], options)
        if name.endswith((".pt", *ENSEMBLE_SUFFIXES)):
            if options:
                raise ConfigError(f"a checkpoint takes no options, got {sorted(options)}")
            from marl_amod.checkpoints import load_policy

            return load_policy(name, city)
        raise ConfigError(f"unknown policy {name!r}; known: {', '.join(policy_names())}, a checkpoint .pt path or an ensemble .yaml")
    if callable(policy):
        return _build(getattr(policy, "__name__", "callable"), ObservationPolicy, options, policy)
    raise ConfigError(f"a policy must be a name, a checkpoint path or a callable, got {type(policy).__name__}")


def _build(name: str, factory: Callable[..., Policy], options: dict[str, Any], *args: Any) -> Policy:
    """``factory(*args, **options)``, with options the factory does not take as one clear error."""
    try:
        inspect.signature(factory).bind(*args, **options)
    except TypeError as exc:
        raise ConfigError(f"policy {name!r}: {exc}") from None
    return factory(*args, **options)
