"""B independent episodes of one city per array operation: :class:`MacroSim`, batched.

Every state array gains a leading episode axis (B, ...); all episodes run in lockstep (one
shared step counter ``t``, the same horizon), so each transition is a handful of numpy calls
whatever B is. The transitions are :class:`MacroSim`'s own code (written over leading axes);
this class only draws B episodes' demand and returns per-episode arrays instead of floats.
Episode b reset with ``rng_b`` draws its demand exactly as ``MacroSim.reset(rng_b)`` does, so it
agrees with a :class:`MacroSim` fed the same flows number for number (tests/test_batch.py).

Pure numpy; like :class:`MacroSim` it never solves anything (see :mod:`marl_amod.batch_system`).
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.macro import MacroSim, check_max_wait


class BatchMacroSim(MacroSim):
    """State of B episodes of one city: reset with B generators, then apply (B, N, N) flows."""

    def __init__(self, city: City, num_envs: int, *, max_wait: int = 0) -> None:
        if num_envs < 1:
            raise ValueError(f"num_envs must be >= 1, got {num_envs}")
        self.num_envs = int(num_envs)
        self._setup(city, check_max_wait(max_wait, city), (self.num_envs,))
        n = city.n_regions
        self.demand = np.zeros((self.num_envs, city.horizon, n, n), dtype=np.int64)  # (B, H, N, N): the steps an episode sees

    def reset(self, rngs: Sequence[np.random.Generator]) -> None:  # type: ignore[override]
        """Start B episodes; episode b draws its demand from ``rngs[b]`` as MacroSim.reset would."""
        if len(rngs) != self.num_envs:
            raise ValueError(f"reset needs {self.num_envs} generators, got {len(rngs)}")
        rate = self.city.demand_rate[: self.city.horizon]
        for k, rng in enumerate(rngs):
            # Poisson draws fill an array in C order, so the first H steps of MacroSim's (S, N, N)
            # draw are exactly this (H, N, N) draw; the steps past the horizon are never used
            self.demand[k] = rng.poisson(rate)
        self._start()

    def vehicles(self) -> np.ndarray:  # type: ignore[override]
        """(B,) idle plus in-transit vehicles per episode; constant over an episode (conservation)."""
        return self._vehicles()

    def apply_dispatch(self, x: np.ndarray, *, check: bool = True) -> np.ndarray:  # type: ignore[override]
        """Serve requests with passenger flows x (B, N, N); returns (B,) dispatch profits."""
        return self._apply_dispatch(x, check)

    def apply_rebalance(self, y: np.ndarray, *, check: bool = True) -> np.ndarray:  # type: ignore[override]
        """Move idle vehicles with flows y (B, N, N); returns (B,) rebalancing costs."""
        return self._apply_rebalance(y, check)
