"""Validation of the integer flows a simulator is asked to apply, shared by every simulator.

A flow that breaks a rule is a bug in the caller (the coordinator guarantees feasibility), so
each check raises with the offending pair instead of repairing anything.
"""

from __future__ import annotations

import numpy as np


def as_flows(flows: np.ndarray, n: int, what: str) -> np.ndarray:
    """(n, n) non-negative integer flows as int64, or a ValueError saying what is wrong."""
    flows = np.asarray(flows)
    if flows.shape != (n, n):
        raise ValueError(f"{what} flows must have shape {(n, n)}, got {flows.shape}")
    if not np.all(np.isfinite(flows)):
        raise ValueError(f"{what} flows contain NaN or inf")
    rounded = np.rint(flows)
    if np.any(np.abs(flows - rounded) > 1e-6) or np.any(rounded < 0):
        raise ValueError(f"{what} flows must be non-negative integers")
    return rounded.astype(np.int64)


def check_supply(flows: np.ndarray, idle: np.ndarray, what: str) -> None:
    """No region sends away more vehicles than it has idle."""
    out = flows.sum(axis=1)
    if np.any(out > idle):
        i = int(np.argmax(out - idle))
        raise ValueError(f"{what} sends {out[i]} vehicles from region {i} which has {idle[i]} idle")


def check_dispatch(x: np.ndarray, open_requests: np.ndarray, idle: np.ndarray) -> None:
    """Passenger flows serve only open requests, with idle vehicles."""
    if np.any(x > open_requests):
        i, j = np.argwhere(x > open_requests)[0]
        raise ValueError(f"dispatch serves {x[i, j]} requests {i}->{j} but only {open_requests[i, j]} are open")
    check_supply(x, idle, "dispatch")


def check_rebalance(y: np.ndarray, idle: np.ndarray) -> None:
    """Rebalancing flows move idle vehicles between distinct regions."""
    if np.any(np.diag(y) != 0):
        raise ValueError("rebalancing flows must be zero on the diagonal (staying is implicit)")
    check_supply(y, idle, "rebalancing")
