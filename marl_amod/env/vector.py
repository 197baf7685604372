"""The batched env: B episodes of one city, every region an agent, arrays in and out (VMAS style).

``marl_amod.vector_env(scenario, num_envs=B, ...)`` takes the ParallelEnv's options
(:mod:`marl_amod.env.parallel`: reward and action modes, look-ahead, max_wait, objective,
``reward_scale``, ``strict_actions``, ``max_cycles``, ``validate``, scenario overrides) and gives the same
episodes, stacked:

==================  ===================================================================================
reset(seed)         observations (B, N, D) float32, infos; ``seed=s`` seeds episode b with s + b (a
                    sequence of B seeds also works), so episode b equals ``parallel_env().reset(seed=s + b)``
step(actions)       actions (B, N) or (B, N, 1) in [0, 1] (finite values clipped, or an ActionError with
                    ``strict_actions``; NaN/inf raise ActionError)
                    -> observations (B, N, D), rewards (B, N) float64 (team or local, from the booked
                    money), terminations (B, N) all False, truncations (B, N), infos
infos               dict of arrays: ``served``, ``demand``, ``rebalancing_cost``, ``idle`` (B, N) and the
                    ``system_*`` episode metrics of the ParallelEnv's infos (B,)
state()             (B, N * F + 3) float32; ``graph()``: ``x`` (B, N, F), ``edge_index`` (2, E) and
                    ``edge_attr`` (E, 2) shared by the batch
==================  ===================================================================================

Resets are explicit, not automatic: every episode has the same horizon and all run in lockstep,
so they all end at the same step (truncations all True); the next ``step`` raises until
``reset()`` starts B new episodes. A ``reset()`` without a seed draws B seeds from a sequence
started by the last seeded reset (one seed, or a list of B integers), as the ParallelEnv does.
Macro-simulator cities only.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any, Literal

import numpy as np
from gymnasium import spaces

from marl_amod.batch_system import BatchFleetSystem, BatchOutcome, Seed
from marl_amod.coordinator.coordinator import Objective
from marl_amod.env import actions as act
from marl_amod.env import observations as ob
from marl_amod.env.features import feature_high, n_features, state_features
from marl_amod.env.options import HasEnvOptions, check_reset_options, env_options
from marl_amod.env.rewards import RewardMode
from marl_amod.errors import ActionError, ConfigError
from marl_amod.metrics import metric_arrays
from marl_amod.scenario import City
from marl_amod.validation import as_count, as_seed


class AmodVectorEnv(HasEnvOptions):
    """B lockstep episodes of one city with array observations, actions and rewards (see module doc)."""

    metadata = {"name": "amod_vector_v0"}

    def __init__(
        self,
        scenario: str | City = "synthetic",
        num_envs: int = 16,
        *,
        reward_mode: RewardMode = "team",
        action_mode: act.ActionMode = "weight",
        lookahead: int = 6,
        max_wait: int = 0,
        objective: Objective = "profit",
        reward_scale: float | Literal["auto"] = 1.0,
        strict_actions: bool = False,
        max_cycles: int | None = None,
        arrivals_now: bool = False,
        validate: bool = False,
        **scenario_overrides: Any,
    ) -> None:
        if "render_mode" in scenario_overrides:  # would read as a scenario key otherwise
            raise ConfigError("the vector env does not render: drop render_mode (a ParallelEnv of one episode does: marl_amod.parallel_env(..., render_mode=...))")
        num_envs = as_count(num_envs, "num_envs", lower=1)  # a bool is not a count
        opts = env_options(
            scenario, reward_mode=reward_mode, action_mode=action_mode, lookahead=lookahead, reward_scale=reward_scale,
            strict_actions=strict_actions, max_cycles=max_cycles, scenario_overrides=scenario_overrides,
            arrivals_now=arrivals_now,
        )
        city = opts.city
        self.adopt_options(opts)
        self.num_envs = int(num_envs)
        self._steps = 0
        self.system = BatchFleetSystem(city, self.num_envs, max_wait=max_wait, objective=objective, validate=validate)
        n = city.n_regions
        self.num_agents = n
        self.possible_agents = ob.agent_names(n)
        self.max_degree = ob.max_in_degree(city)
        self._layout = ob.LocalLayout(ob.neighbour_table(city, self.max_degree), n_features(self.lookahead, self.arrivals_now))
        high = feature_high(city, self.lookahead, arrivals_now=self.arrivals_now)
        self.observation_space = spaces.Box(*ob.local_bounds(high, self.max_degree), dtype=np.float32)  # one agent
        self.action_space = spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32)  # one agent
        self.state_space = spaces.Box(*ob.state_bounds(high, n), dtype=np.float32)  # one episode
        self._seeds: np.random.SeedSequence | None = None
        self._running = False
        self.last_outcome: BatchOutcome | None = None

    @property
    def city(self) -> City:
        return self.system.city

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | Sequence[Seed] | None = None, options: dict | None = None) -> tuple[np.ndarray, dict]:
        """B new episodes; returns observations (B, N, D) and infos."""
        check_reset_options(options)
        b = self.num_envs
        if seed is None:
            if self._seeds is None:
                self._seeds = np.random.SeedSequence()
            seeds: list[Seed] = list(self._seeds.spawn(b))
        elif isinstance(seed, (str, bytes)) or not isinstance(seed, (Sequence, np.ndarray)):  # one seed ("a" is no list)
            first = as_seed(seed)  # as the ParallelEnv: numpy integers welcome, a negative seed a ConfigError
            self._seeds = np.random.SeedSequence(first)
            seeds = [first + k for k in range(b)]
        else:
            seeds = [s if s is None or isinstance(s, np.random.SeedSequence) else as_seed(s, f"seed of episode {k}")
                     for k, s in enumerate(seed)]  # fmt: skip
            if len(seeds) != b:
                raise ConfigError(f"reset needs one seed per episode ({b}), got {len(seeds)}")
            if all(isinstance(s, int) for s in seeds):  # a seeded reset: the next unseeded ones follow from it
                self._seeds = np.random.SeedSequence(seeds)
        self.last_outcome = self.system.reset(seeds)
        self._steps = 0
        self._running = True
        return self._observations(), self._infos(self.last_outcome)

    def step(self, actions: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, dict]:
        """Advance every episode one control step with actions (B, N) or (B, N, 1)."""
        if not self._running:
            raise RuntimeError("the episodes are over (or never started); call reset()")
        joint = self._joint(actions)
        target = self.system.targets_from_weights(act.weights(joint, self.action_mode), check=False)  # finite, in [0, 1]
        outcome = self.last_outcome = self.system.step(target)
        if self.reward_mode == "team":  # the same selections as env/rewards.py, per episode
            rew = np.repeat(outcome.reward[:, None], self.num_agents, axis=1)
        else:
            rew = outcome.region_reward
        rew = rew * self.reward_scale
        self._steps += 1
        done = self.system.done or self._steps >= self.max_cycles
        self._running = not done
        shape = (self.num_envs, self.num_agents)
        return self._observations(), rew, np.zeros(shape, bool), np.full(shape, done), self._infos(outcome)

    # ------------------------------------------------------------------ global view
    def node_features(self) -> np.ndarray:
        """(B, N, F) float32 features of every region of every episode."""
        sim = self.system.sim
        return state_features(self.city, sim.t, sim.idle, sim.arrivals, self.lookahead, arrivals_now=self.arrivals_now)

    def state(self) -> np.ndarray:
        """(B, N * F + 3) float32: every region's features, then time of day and step fraction."""
        return ob.state_from_features(self.node_features(), ob.time_features(self.city, self.system.t))

    def graph(self) -> dict[str, np.ndarray]:
        """``x`` (B, N, F) float32, and ``edge_index`` (2, E), ``edge_attr`` (E, 2) shared by the batch."""
        return {"x": self.node_features(), **ob.graph_edges(self.city)}

    def close(self) -> None:
        """Nothing to release (no viewer, no files); for API symmetry."""

    # ------------------------------------------------------------------ helpers
    def _observations(self) -> np.ndarray:
        return self._layout(self.node_features(), ob.time_features(self.city, self.system.t))

    def _joint(self, actions: Any) -> np.ndarray:
        """(B, N) float64 actions clipped into [0, 1]; the ParallelEnv's rules, checked in one pass."""
        a = act.real_array(actions).astype(np.float64, copy=False)
        shape = (self.num_envs, self.num_agents)
        if a.shape == (*shape, 1):
            a = a[..., 0]
        if a.shape != shape:
            raise ActionError(f"actions must have shape {shape} or {(*shape, 1)}, got {a.shape}")
        if not np.all(np.isfinite(a)):
            e, i = np.argwhere(~np.isfinite(a))[0]
            raise ActionError(f"action of region_{i} in episode {e} is not finite: {a[e, i]}")
        outside = (a < 0.0) | (a > 1.0)
        if self.strict_actions and outside.any():
            e, i = np.argwhere(outside)[0]
            raise ActionError(
                f"action of region_{i} in episode {e} is {a[e, i]}, outside the action space [0, 1] (strict_actions=True)"
            )
        return a.clip(0.0, 1.0)

    def _infos(self, outcome: BatchOutcome) -> dict[str, np.ndarray]:
        sim, city = self.system.sim, self.city
        metrics = metric_arrays(sim.totals, city.fleet_size, self.max_cycles + 1)  # the episode's steps as run (the horizon by default)
        return {
            "served": outcome.dispatch.sum(axis=-1),
            "demand": sim.demand[:, sim.t].sum(axis=-1),
            "rebalancing_cost": outcome.region_rebalancing_cost,
            "idle": sim.idle.copy(),
            **{f"system_{k}": v for k, v in metrics.items() if k != "revenue"},
        }
