"""The env options both faces share (the ParallelEnv and the batched vector env), checked once.

Both envs take the same keywords and must read them identically, or a policy trained on one
would meet different rewards or episode lengths on the other; so the checks, the values derived
from them (the episode's step count, the reward multiplier) and the attributes the envs expose
them as (:class:`HasEnvOptions`) live here.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

from marl_amod.env import actions as act
from marl_amod.env.rewards import REWARD_MODES, RewardMode, typical_step_revenue
from marl_amod.errors import ConfigError
from marl_amod.scenario import City, load_city
from marl_amod.validation import as_count, as_flag, as_real


@dataclass(frozen=True)
class EnvOptions:
    """Checked options: the city, and the values the envs read every step."""

    city: City
    reward_mode: RewardMode
    action_mode: act.ActionMode
    lookahead: int
    strict_actions: bool
    max_cycles: int  # control steps per episode: min(horizon - 1, max_cycles)
    reward_scale: float  # multiplies every reward ("auto": 1 / the city's expected fares per step)
    arrivals_now: bool  # the opt-in node column of the vehicles arriving now (env/features.py)


def env_options(
    scenario: str | City,
    *,
    reward_mode: RewardMode,
    action_mode: act.ActionMode,
    lookahead: int,
    reward_scale: float | Literal["auto"],
    strict_actions: bool,
    max_cycles: int | None,
    scenario_overrides: dict[str, Any],
    arrivals_now: bool = False,
) -> EnvOptions:
    """The options checked (a ConfigError naming the bad one) and the city loaded."""
    if reward_mode not in REWARD_MODES:
        raise ConfigError(f"reward_mode must be one of {REWARD_MODES}, got {reward_mode!r}")
    if action_mode not in act.ACTION_MODES:
        raise ConfigError(f"action_mode must be one of {act.ACTION_MODES}, got {action_mode!r}")
    # counts and numbers as the policies' options are checked: lookahead=True is a slip, not 1 step
    lookahead = as_count(lookahead, "lookahead (steps)", lower=1)
    if max_cycles is not None:
        max_cycles = as_count(max_cycles, "max_cycles (steps, or None)", lower=1)
    if not (isinstance(reward_scale, str) and reward_scale == "auto"):
        reward_scale = as_real(reward_scale, "reward_scale (or 'auto')", above=0)
    strict_actions = as_flag(strict_actions, "strict_actions")  # strict_actions="no" would be truthy
    arrivals_now = as_flag(arrivals_now, "arrivals_now")
    if isinstance(scenario, City):
        if scenario_overrides:
            raise ConfigError(f"scenario overrides {sorted(scenario_overrides)} need a scenario name, not a City")
        city = scenario
    else:
        city = load_city(scenario, **scenario_overrides)
    if city.horizon < 2:
        raise ConfigError(f"{city.name}: the env needs a horizon of at least 2 steps, got {city.horizon}")
    return EnvOptions(
        city=city,
        reward_mode=reward_mode,
        action_mode=action_mode,
        lookahead=int(lookahead),
        strict_actions=strict_actions,
        max_cycles=city.horizon - 1 if max_cycles is None else min(int(max_cycles), city.horizon - 1),
        reward_scale=1.0 / typical_step_revenue(city) if reward_scale == "auto" else float(reward_scale),
        arrivals_now=arrivals_now,
    )


class HasEnvOptions:
    """The checked options as plain attributes of an env (settable: PettingZoo's API test sets
    ``max_cycles``); both envs take them from :meth:`adopt_options`, so neither copies the fields."""

    reward_mode: RewardMode
    action_mode: act.ActionMode
    lookahead: int
    strict_actions: bool
    max_cycles: int  # control steps per episode: min(horizon - 1, max_cycles)
    reward_scale: float  # multiplies every reward ("auto": 1 / the city's expected fares per step)
    arrivals_now: bool  # the opt-in node column of the vehicles arriving now

    def adopt_options(self, options: EnvOptions) -> None:
        """Every option but the city as an attribute of the same name."""
        for name in ENV_ATTRIBUTES:
            setattr(self, name, getattr(options, name))


ENV_ATTRIBUTES = tuple(name for name in EnvOptions.__dataclass_fields__ if name != "city")


def check_reset_options(options: Any) -> None:
    """``reset(options=...)``: a dict or None, as the PettingZoo and Gymnasium APIs type it. The envs read
    none of its keys (everything an episode depends on is set when the env is made, or by the seed), so
    wrappers may pass theirs; anything but a dict is a mistake worth saying."""
    if options is not None and not isinstance(options, Mapping):
        raise ConfigError(f"reset(options=...) takes a dict or None, got {type(options).__name__}; the env reads no reset options")
