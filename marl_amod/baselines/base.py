"""What a rebalancing policy is to the evaluation loop."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import numpy as np

from marl_amod.system import FleetSystem


@runtime_checkable
class Policy(Protocol):
    """Maps the system after dispatch to per-region targets of idle vehicles.

    ``target`` returns (N,) integers summing to at most the idle fleet; -1 means "no wish"
    (that region's vehicles stay unless others need them).
    """

    name: str

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None: ...

    def target(self, system: FleetSystem) -> np.ndarray: ...


class WeightPolicy:
    """A policy that outputs the paper's desired distribution as non-negative weights."""

    name = "weights"

    def reset(self, system: FleetSystem, rng: np.random.Generator) -> None:
        self.rng = rng

    def weights(self, system: FleetSystem) -> np.ndarray:
        raise NotImplementedError

    def target(self, system: FleetSystem) -> np.ndarray:
        return system.targets_from_weights(self.weights(system))
