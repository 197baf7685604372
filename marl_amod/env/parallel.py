"""AMoD fleet coordination: a PettingZoo ``ParallelEnv`` in which every region is an agent.

A city is a graph of N regions with a fleet of robo-taxis. Each control step, every region
(agent) emits one number; a central coordinator turns the joint action into a desired
distribution of idle vehicles, moves vehicles there at least cost (exact min-cost flow), the
simulator advances one step, and the coordinator dispatches the new requests (exact, greedy by
margin). Flows are always feasible whatever the agents do.

==================  ===================================================================================
Import              ``from marl_amod import amod_v0`` (or ``from marl_amod import parallel_env, env``)
Agents              ``region_0`` ... ``region_{N-1}``, all alive for the whole episode
Parallel API        yes (``env()`` is the AEC version through ``parallel_to_aec``)
Action space        ``Box(0, 1, (1,), float32)``, identical for every agent
Observation space   ``Box(float32, (F + 3 + K(F + 1),))``, F = 1 + 2 * lookahead (13; + 1 with ``arrivals_now``), K = max in-degree; finite bounds
State space         ``Box(float32, (N * F + 3,))``
Episode             ``min(horizon - 1, max_cycles)`` steps (reset dispatches step 0), then every agent is truncated
==================  ===================================================================================

Actions (see :mod:`marl_amod.env.actions`): ``action_mode="weight"`` (default) reads the
actions as non-negative weights w; region i's target is floor(w_i / sum(w) * M) idle vehicles
(M idle vehicles in total); all zeros means "stay" (no rebalancing). ``action_mode="logit"``
maps a in [0, 1] to a logit 10 * (2a - 1) and takes a softmax across agents. Finite values
outside [0, 1] (negative ones included) are clipped into the space, as PettingZoo's continuous
envs do, so Gaussian policies act unmodified; ``strict_actions=True`` raises on them instead.
NaN/inf, shapes other than (1,) and missing agents raise :class:`~marl_amod.errors.ActionError`.

Observations (see :mod:`marl_amod.env.observations`): own 13 features (idle vehicles, supply
over the next 6 steps, expected request value over the next 6 steps, all x 0.01), sin/cos of the
clock time, t / horizon, then the 13 features of each in-neighbour in K padded slots and a mask
of K slots. :func:`~marl_amod.env.observations.split_local` cuts it back into blocks.

Rewards (see :mod:`marl_amod.env.rewards`): ``reward_mode="team"`` gives every agent the
system's step profit (dispatch profit of the new step minus the rebalancing cost);
``"local"`` gives a region its own dispatch profit minus the cost of the vehicles it sent away.
Local rewards sum to the team reward. ``reward_scale`` multiplies every reward: a float (1.0,
money as booked, is the default), or ``"auto"`` = 1 / the city's expected fares per step
(:func:`~marl_amod.env.rewards.typical_step_revenue`), which puts team rewards near [-1, 1] so
off-the-shelf learners (SB3, tianshou, ...) work without reward normalisation. Infos stay in money.

Infos (per agent, small): ``served`` (trips that left the region this step), ``demand``
(requests that appeared there this step),
``rebalancing_cost`` (of the vehicles the region sent away), ``idle`` (after dispatch), and the
episode so far, the same for every agent: ``system_profit``, ``system_served_demand``,
``system_demand``, ``system_rebalancing_cost``, ``system_wait_time``, ``system_utilization``,
``system_wait_time_gini``, ``system_service_rate_gini`` (the equity metrics over regions)
(flat scalars, so TorchRL and vector wrappers can stack them).

Global view: ``state()`` / ``state_space``, ``graph()`` -> ``{"x": (N, F) float32,
"edge_index": (2, E) int64, "edge_attr": (E, 2) float32 [rebalancing steps, cost]}`` and
``system`` (the underlying :class:`~marl_amod.system.FleetSystem`).

Arguments: ``scenario`` (a name from ``marl-amod scenarios``, a YAML path or a ``City``, or a
variant of a name or path such as ``porto~hot1x2.5``: :mod:`marl_amod.scenario.variants`; a SUMO
scenario such as ``sumo_grid`` or ``lux`` runs the same env in SUMO's mesoscopic model),
``reward_mode``, ``action_mode``, ``lookahead`` (T), ``max_wait`` (steps a request waits),
``objective`` (dispatch objective, ``"profit"`` or ``"revenue"``), ``reward_scale``,
``strict_actions``, ``arrivals_now`` (False; True appends each region's vehicles arriving in the
current step, idle from the next, as a last node feature: :mod:`marl_amod.env.features`), ``max_cycles`` (PettingZoo's cap on the number of steps; the episode is
truncated after ``min(horizon - 1, max_cycles)`` steps), ``render_mode`` (``"human"`` or
``"rgb_array"``), ``validate`` (False; True re-checks every flow the coordinator hands the
simulator, a debug mode: :class:`~marl_amod.system.FleetSystem`), and scenario overrides (e.g.
``horizon=10``; unknown keys raise).

Seeding: ``reset(seed=s)`` draws demand exactly as ``FleetSystem.reset(s)``; a later
``reset()`` without a seed draws the next episode from a seed sequence started by the last
seeded reset (from fresh entropy if there was none). The env is picklable and writes no files.

Version History (the version changes whenever learning results could change):

* v0: first release. Options added later without changing results at their defaults:
  ``max_cycles`` (None), ``reward_scale`` (1.0), ``strict_actions`` (False; negative finite
  actions, which used to raise, are now clipped to 0 like values above 1), ``arrivals_now`` (False).
"""

from __future__ import annotations

from typing import Any, Literal

import numpy as np
from gymnasium import logger, spaces
from pettingzoo import ParallelEnv
from pettingzoo.utils import parallel_to_aec
from pettingzoo.utils.env import AECEnv

from marl_amod.coordinator.coordinator import Objective
from marl_amod.env import ENV_ID, ENV_VERSION
from marl_amod.env import actions as act
from marl_amod.env import observations as ob
from marl_amod.env.features import feature_high as feature_bounds
from marl_amod.env.features import n_features
from marl_amod.env.options import HasEnvOptions, check_reset_options, env_options
from marl_amod.env.rewards import RewardMode, agent_rewards
from marl_amod.errors import ConfigError
from marl_amod.metrics import METRICS, metric_arrays
from marl_amod.scenario import City
from marl_amod.system import FleetSystem, StepOutcome
from marl_amod.validation import as_seed

RENDER_MODES = ["human", "rgb_array"]
_SYSTEM_INFOS = {name: f"system_{name}" for name in METRICS if name != "revenue"}  # episode metric -> info key


class AmodParallelEnv(HasEnvOptions, ParallelEnv):
    """Every region an agent; a thin adapter over :class:`~marl_amod.system.FleetSystem` (see module doc)."""

    metadata = {"name": ENV_VERSION, "render_modes": RENDER_MODES, "is_parallelizable": True, "render_fps": 4}

    def __init__(
        self,
        scenario: str | City = "synthetic",
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
        render_mode: str | None = None,
        validate: bool = False,
        **scenario_overrides: Any,
    ) -> None:
        if render_mode is not None and render_mode not in RENDER_MODES:
            raise ConfigError(f"render_mode must be None or one of {RENDER_MODES}, got {render_mode!r}")
        opts = env_options(
            scenario, reward_mode=reward_mode, action_mode=action_mode, lookahead=lookahead, reward_scale=reward_scale,
            strict_actions=strict_actions, max_cycles=max_cycles, scenario_overrides=scenario_overrides,
            arrivals_now=arrivals_now,
        )
        city = opts.city
        self.adopt_options(opts)
        self.render_mode = render_mode
        self.system = FleetSystem(city, max_wait=max_wait, objective=objective, validate=validate)

        n = city.n_regions
        self.possible_agents = ob.agent_names(n)
        self.agents: list[str] = []
        self.max_degree = ob.max_in_degree(city)
        self._layout = ob.LocalLayout(ob.neighbour_table(city, self.max_degree), n_features(self.lookahead, self.arrivals_now))
        feature_high = feature_bounds(city, self.lookahead, arrivals_now=self.arrivals_now)
        self._observation_space = spaces.Box(*ob.local_bounds(feature_high, self.max_degree), dtype=np.float32)
        self._action_space = spaces.Box(0.0, 1.0, shape=(1,), dtype=np.float32)
        self.observation_spaces = {a: self._observation_space for a in self.possible_agents}
        self.action_spaces = {a: self._action_space for a in self.possible_agents}
        self.state_space = spaces.Box(*ob.state_bounds(feature_high, n), dtype=np.float32)
        self._seeds: np.random.SeedSequence | None = None
        self._steps = 0
        self._last_outcome: StepOutcome | None = None
        self._viewer: Any = None

    @property
    def city(self) -> City:
        """The region view the simulator holds now (SUMO scenarios update travel times during an episode)."""
        return self.system.city

    @property
    def last_outcome(self) -> StepOutcome | None:
        """The last reset's or step's :class:`~marl_amod.system.StepOutcome` (flows, booked money per region)."""
        return self._last_outcome

    # ------------------------------------------------------------------ spaces
    def observation_space(self, agent: str) -> spaces.Box:
        return self._space(self.observation_spaces, agent)

    def action_space(self, agent: str) -> spaces.Box:
        return self._space(self.action_spaces, agent)

    def _space(self, table: dict[str, spaces.Box], agent: str) -> spaces.Box:
        """The one shared space, for agents of this city only: a typo such as ``region_16`` in a
        16-region city is an error, not a space for an agent that never acts."""
        try:
            return table[agent]
        except (KeyError, TypeError):
            raise KeyError(f"unknown agent {agent!r}; the agents are region_0 ... region_{len(table) - 1}") from None

    # ------------------------------------------------------------------ episode
    def reset(self, seed: int | None = None, options: dict | None = None) -> tuple[dict, dict]:
        check_reset_options(options)
        if seed is not None:
            seed = as_seed(seed)  # numpy integers welcome; a negative seed is a clear error
            self._seeds = np.random.SeedSequence(seed)
            demand_seed: int | np.random.SeedSequence = seed
            self._action_space.seed(seed)
        else:
            if self._seeds is None:
                self._seeds = np.random.SeedSequence()
            demand_seed = self._seeds.spawn(1)[0]
        self._last_outcome = self.system.reset(demand_seed)
        self._steps = 0
        self.agents = list(self.possible_agents)
        infos = self._infos(self._last_outcome)
        if self.render_mode == "human":
            self.render()
        return self._observations(), infos

    def step(self, actions: dict[str, Any]) -> tuple[dict, dict, dict, dict, dict]:
        if not self.agents:
            why = "every agent was truncated" if self._last_outcome is not None else "reset() was never called"
            raise RuntimeError(f"no episode is running ({why}); call reset() first")
        target = act.targets(self.system, actions, self.agents, self.action_mode, strict=self.strict_actions)
        outcome = self._last_outcome = self.system.step(target)
        self._steps += 1
        agents = self.agents
        obs = self._observations()
        rew = agent_rewards(self.reward_mode, outcome, agents, self.reward_scale)
        infos = self._infos(outcome)
        done = self.system.done or self._steps >= self.max_cycles
        terminations = dict.fromkeys(agents, False)
        truncations = dict.fromkeys(agents, done)
        if done:
            self.agents = []
        if self.render_mode == "human":
            self.render()
        return obs, rew, terminations, truncations, infos

    # ------------------------------------------------------------------ global view
    def state(self) -> np.ndarray:
        """(N * F + 3,) float32: every region's features, then time of day and step fraction."""
        return ob.global_state(self.system, self.lookahead, self.arrivals_now)

    def graph(self) -> dict[str, np.ndarray]:
        """Node features, edge_index (2, E) and edge_attr (E, 2) for a torch-geometric model."""
        return ob.graph(self.system, self.lookahead, self.arrivals_now)

    # ------------------------------------------------------------------ rendering
    def render(self) -> np.ndarray | None:
        if self.render_mode is None:
            logger.warn("render() called without a render_mode; make the env with render_mode='rgb_array' or 'human'")
            return None
        from marl_amod.env import render as rd

        if self.render_mode == "rgb_array":
            return rd.render_rgb(self.system, *self._render_args())
        if self._viewer is None:
            self._viewer = rd.HumanViewer()
        self._viewer.show(self.system, *self._render_args())
        return None

    def close(self) -> None:
        """Close the viewer and end the simulator's run (a SUMO process); ``reset`` starts anew."""
        if self._viewer is not None:
            self._viewer.close()
            self._viewer = None
        self.system.close()

    # ------------------------------------------------------------------ helpers
    def _observations(self) -> dict[str, np.ndarray]:
        obs = ob.local_observations(self.system, self.lookahead, layout=self._layout, arrivals_now=self.arrivals_now)
        return dict(zip(self.possible_agents, obs, strict=True))  # row views, as obs[i]

    def _render_args(self) -> tuple[np.ndarray, float | None]:
        n = self.system.city.n_regions
        if self._last_outcome is None:
            return np.zeros((n, n), dtype=np.int64), None
        return self._last_outcome.rebalancing, self._last_outcome.reward

    def _infos(self, outcome: StepOutcome) -> dict[str, dict]:
        sim, city = self.system.sim, self.system.city
        # whole arrays to Python numbers at once (tolist), the same values as int()/float() per region
        served = outcome.dispatch.sum(axis=1).astype(np.int64, copy=False).tolist()
        reb_cost = outcome.region_rebalancing_cost.astype(float, copy=False).tolist()
        new = sim.demand[sim.t].sum(axis=1).astype(np.int64, copy=False).tolist()
        idle = np.asarray(sim.idle).astype(np.int64, copy=False).tolist()
        # as episode_metrics, as floats below; over the episode's steps as run (max_cycles + step 0: the horizon by default)
        metrics = metric_arrays(sim.totals, city.fleet_size, self.max_cycles + 1)
        system = {key: float(metrics[name]) for name, key in _SYSTEM_INFOS.items()}
        return {
            a: {"served": s, "demand": d, "rebalancing_cost": c, "idle": i, **system}
            for a, s, d, c, i in zip(self.possible_agents, served, new, reb_cost, idle, strict=True)
        }

    def __getstate__(self) -> dict:
        """A copy continues the running episode exactly, and draws its own later unseeded episodes: vector
        wrappers (SuperSuit's, SB3's) pickle one env into several copies, which would otherwise
        replay one demand stream in every copy. Each copy takes the next child of this env's stream."""
        state = self.__dict__.copy()
        state["_viewer"] = None  # a window cannot travel; a copy opens its own
        if self._seeds is not None:
            state["_seeds"] = self._seeds.spawn(1)[0]
        return state


def parallel_env(scenario: str | City = "synthetic", **kwargs: Any) -> AmodParallelEnv:
    """The parallel env; keyword arguments as :class:`AmodParallelEnv` (see the module doc)."""
    return AmodParallelEnv(scenario, **kwargs)


def raw_env(scenario: str | City = "synthetic", **kwargs: Any) -> AECEnv:
    """The AEC env through PettingZoo's own conversion (agents act one after another)."""
    return parallel_to_aec(parallel_env(scenario, **kwargs))


env = raw_env


def register() -> None:
    """Add the env to PettingZoo's registry once, where the installed version has one (1.27+)."""
    import pettingzoo

    if not hasattr(pettingzoo, "register"):
        return
    from pettingzoo.env_registry.registration import parallel_registry

    if ENV_ID not in parallel_registry:
        pettingzoo.register("parallel", ENV_ID, entry_point=f"marl_amod.{ENV_VERSION}:parallel_env")
        pettingzoo.register("aec", ENV_ID, entry_point=f"marl_amod.{ENV_VERSION}:raw_env")
