"""Validation of the integer flows a simulator is asked to apply, shared by every simulator
(leading axes: a batch of episodes, :mod:`marl_amod.sim.batch`).

A flow that breaks a rule is a bug in the caller (the coordinator guarantees feasibility), so
each check raises with the offending pair instead of repairing anything.
"""

from __future__ import annotations

import numpy as np


def as_flows(flows: np.ndarray, n: int, what: str, batch: tuple[int, ...] = ()) -> np.ndarray:
    """(*batch, n, n) non-negative integer flows as int64, or a ValueError saying what is wrong."""
    flows = np.asarray(flows)
    if flows.shape != (*batch, n, n):
        raise ValueError(f"{what} flows must have shape {(*batch, n, n)}, got {flows.shape}")
    if flows.dtype.kind in "iu":  # the coordinator's own output: only the sign can be wrong
        if flows.dtype.kind == "i" and (flows < 0).any():
            raise ValueError(f"{what} flows must be non-negative integers")
        return flows.astype(np.int64)  # a copy: the simulator keeps it as last_dispatch/last_rebalance
    if not np.all(np.isfinite(flows)):
        raise ValueError(f"{what} flows contain NaN or inf")
    rounded = np.rint(flows)
    if np.any(np.abs(flows - rounded) > 1e-6) or np.any(rounded < 0):
        raise ValueError(f"{what} flows must be non-negative integers")
    return rounded.astype(np.int64)


def check_supply(flows: np.ndarray, idle: np.ndarray, what: str) -> None:
    """No region sends away more vehicles than it has idle."""
    out = flows.sum(axis=-1)
    if (out > idle).any():
        at = np.unravel_index(np.argmax(out - idle), out.shape)  # (region,) or (episode, region)
        raise ValueError(f"{what} sends {out[at]} vehicles from region {at[-1]} which has {idle[at]} idle" + _episode(at))


def check_dispatch(x: np.ndarray, open_requests: np.ndarray, idle: np.ndarray) -> None:
    """Passenger flows serve only open requests, with idle vehicles."""
    if (x > open_requests).any():
        at = tuple(np.argwhere(x > open_requests)[0])
        i, j = at[-2:]
        raise ValueError(f"dispatch serves {x[at]} requests {i}->{j} but only {open_requests[at]} are open" + _episode(at[:-1]))
    check_supply(x, idle, "dispatch")


def check_rebalance(y: np.ndarray, idle: np.ndarray) -> None:
    """Rebalancing flows move idle vehicles between distinct regions."""
    if np.diagonal(y, axis1=-2, axis2=-1).any():
        raise ValueError("rebalancing flows must be zero on the diagonal (staying is implicit)")
    check_supply(y, idle, "rebalancing")


def _episode(at: tuple) -> str:
    """' in episode b' for a batched index (episode, region), empty for a single episode."""
    return f" in episode {at[0]}" if len(at) > 1 else ""
