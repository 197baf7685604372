"""A policy written for the env (observations dict -> actions dict) driven on the system directly.

Outside learners (SB3, TorchRL, RLlib, a hand-written rule) produce functions in PettingZoo's
convention. Wrapped here, such a function sees exactly the observations the env's agents see,
and its actions go through the env's own validation and action mode, so evaluating it on the
system gives the env's numbers on the same demand draws as every other policy.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any

import numpy as np

from marl_amod.baselines.base import Policy
from marl_amod.env import actions as act
from marl_amod.env import observations as ob
from marl_amod.env.features import n_features
from marl_amod.errors import ConfigError
from marl_amod.system import FleetSystem
from marl_amod.validation import as_flag

ObservationFn = Callable[[dict[str, np.ndarray]], Mapping[str, Any]]


class ObservationPolicy(Policy):
    """Runs ``fn`` on the env's local observations each step; its actions become the coordinator's target.

    ``lookahead``, ``action_mode`` and ``arrivals_now`` must match the env ``fn`` was written for
    (the env's defaults: 6, ``"weight"`` and False). ``name`` defaults to ``fn.name`` or the function's name.
    """

    def __init__(
        self, fn: ObservationFn, *, lookahead: int = 6, action_mode: act.ActionMode = "weight", name: str | None = None,
        arrivals_now: bool = False,
    ) -> None:
        if not callable(fn):
            raise ConfigError(f"a policy must be a name, a checkpoint path or a callable, got {type(fn).__name__}")
        if action_mode not in act.ACTION_MODES:
            raise ConfigError(f"action_mode must be one of {act.ACTION_MODES}, got {action_mode!r}")
        if isinstance(lookahead, (bool, np.bool_)) or not isinstance(lookahead, (int, np.integer)) or lookahead < 1:
            raise ConfigError(f"lookahead must be a positive number of steps, got {lookahead!r}")
        self.fn, self.lookahead, self.action_mode = fn, int(lookahead), action_mode
        self.arrivals_now = as_flag(arrivals_now, "arrivals_now")
        self.name = name or getattr(fn, "name", None) or getattr(fn, "__name__", type(fn).__name__)

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        super().reset(system, rng)
        self.agents = ob.agent_names(system.city.n_regions)
        self._layout = ob.LocalLayout(ob.neighbour_table(system.city), n_features(self.lookahead, self.arrivals_now))

    def target(self, system: FleetSystem) -> np.ndarray:
        obs = ob.local_observations(system, self.lookahead, layout=self._layout, arrivals_now=self.arrivals_now)
        actions = self.fn({a: obs[i] for i, a in enumerate(self.agents)})
        return act.targets(system, actions, self.agents, self.action_mode)
