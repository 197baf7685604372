"""What a rebalancing policy is to the evaluation loop, and the three shapes its output takes.

Every policy ends in the same place: after each dispatch, :meth:`Policy.target` returns per-region
targets of idle vehicles, which the coordinator meets at least cost. How a policy gets there
differs, so each shape has its own base class instead of one that pretends all output weights:

* :class:`Policy`: targets directly (INF, DTV);
* :class:`WeightPolicy`: the paper's desired distribution as non-negative weights (ED, PROP,
  trained actors); the coordinator floors w_i / sum(w) * M;
* :class:`FlowPolicy`: planned region-to-region moves (MPC, plus-one), turned into the targets
  that make the coordinator move vehicles as planned.

A policy written against the env's observations instead is wrapped by
:class:`~marl_amod.baselines.observation.ObservationPolicy`.
"""

from __future__ import annotations

from abc import ABC, abstractmethod

import numpy as np

from marl_amod.errors import ConfigError
from marl_amod.scenario.types import City
from marl_amod.system import FleetSystem


def check_bound_city(name: str, bound: City, system: FleetSystem) -> None:
    """A policy built for ``bound`` (its graph, its region count, its adaptation) refuses a system of another
    city, which it would read with the wrong graph or fail on with a shape error deep in torch. The
    system's view of the same city (a SUMO city's travel times change) has the same regions and graph."""
    city = system.city
    if city.n_regions != bound.n_regions or not np.array_equal(np.asarray(city.edge_index), np.asarray(bound.edge_index)):
        raise ConfigError(f"{name} was loaded for {bound.name} ({bound.n_regions} regions); this system is {city.name} "
                          f"({city.n_regions} regions): load it for that city, e.g. marl_amod.load_policy(path, {city.name!r})")  # fmt: skip


class Policy(ABC):
    """Maps the system after dispatch to per-region targets of idle vehicles.

    ``target`` returns (N,) integers summing to at most the idle fleet; -1 means "no wish"
    (that region's vehicles stay unless others need them). ``reset`` runs before every episode
    with the episode's own random generator, so stochastic policies are reproducible.
    """

    name: str = "policy"

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        self.rng = rng

    @abstractmethod
    def target(self, system: FleetSystem) -> np.ndarray: ...


class WeightPolicy(Policy):
    """A policy that outputs the paper's desired distribution as non-negative weights."""

    @abstractmethod
    def weights(self, system: FleetSystem) -> np.ndarray:
        """(N,) non-negative weights; all zeros means "stay" (no rebalancing)."""

    def target(self, system: FleetSystem) -> np.ndarray:
        return system.targets_from_weights(self.weights(system))

    def executed(self, weights: np.ndarray) -> None:
        """The weights taken this step in this policy's place (an ensemble's mean): a policy that
        reads its own last action next step reads these instead; the others ignore them."""


class FlowPolicy(Policy):
    """A policy that plans rebalancing moves; the coordinator's min-cost flow then realises them."""

    @abstractmethod
    def flows(self, system: FleetSystem) -> np.ndarray:
        """(N, N) non-negative planned moves of idle vehicles i -> j (may be fractional; diagonal = stay)."""

    def target(self, system: FleetSystem) -> np.ndarray:
        return target_from_flows(system.sim.idle, self.flows(system))


def round_preserving_sum(values: np.ndarray, total: int) -> np.ndarray:
    """Non-negative integers close to ``values`` that sum to ``total`` (largest remainder)."""
    values = np.maximum(values, 0.0)
    base = np.floor(values + 1e-9).astype(np.int64)
    short = int(total - base.sum())
    if short > 0:
        base[np.argsort(-(values - base), kind="stable")[:short]] += 1
    elif short < 0:  # only from float noise: take from the largest entries
        for idx in np.argsort(-values, kind="stable")[: -short]:
            base[idx] -= 1 if base[idx] > 0 else 0
    return base


def target_from_flows(idle: np.ndarray, flows: np.ndarray) -> np.ndarray:
    """Per-region targets that make the coordinator's min-cost flow move vehicles as ``flows`` plans.

    Fractional plans are rounded by largest remainder, which keeps the idle fleet's size;
    integral plans give exactly idle + inflow - outflow.
    """
    off = flows * (1.0 - np.eye(flows.shape[0]))
    dist = idle + off.sum(axis=0) - off.sum(axis=1)
    return round_preserving_sum(dist, int(np.asarray(idle).sum()))
