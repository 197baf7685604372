"""The paper's per-region features, computed from the system state after dispatch.

For region i at step t, with look-ahead T (6 by default) and scale 0.01:

* ``idle``: idle vehicles now (after dispatch), 1 column;
* ``supply[k]``: idle now plus vehicles arriving at i in step t+k, k = 1..T (T columns);
* ``value[k]``: expected requests out of i in step t+k times their price, summed over
  destinations, k = 1..T (T columns); expected = ``city.forecast_rate``, which does not know a
  scenario's events (policies see a demand shock only through the state it leaves);
* ``arrivals_now`` (opt-in, ``arrivals_now=True``): vehicles arriving at i during step t, idle
  from t+1 (1 column). ``supply[1]`` counts idle now plus the arrivals of step t+1, so these are in
  no other column, yet they are the fleet MPC's plan starts from at its first step; the paper's
  observation leaves them out, so the default does too (docs/studies/synthetic_city.md).

Steps past the tabulated horizon count as zero (:func:`~marl_amod.scenario.types.step_rows`).
"""

from __future__ import annotations

import functools
import weakref

import numpy as np

from marl_amod.scenario.types import City, step_rows
from marl_amod.system import FleetSystem

FEATURE_SCALE = 0.01


def n_features(lookahead: int, arrivals_now: bool = False) -> int:
    """F = 1 + 2T (+ 1 with ``arrivals_now``): columns of :func:`node_features` for a look-ahead of T steps."""
    return 1 + 2 * lookahead + int(arrivals_now)


def feature_names(lookahead: int = 6, arrivals_now: bool = False) -> list[str]:
    """Column names of :func:`node_features`."""
    steps = range(1, lookahead + 1)
    return ["idle"] + [f"supply_t+{k}" for k in steps] + [f"value_t+{k}" for k in steps] + ["arrivals_now"] * arrivals_now


def node_features(system: FleetSystem, lookahead: int = 6, scale: float = FEATURE_SCALE, arrivals_now: bool = False) -> np.ndarray:
    """(N, F) float32 features of every region (the paper's GNN input, F = :func:`n_features`)."""
    sim = system.sim
    return state_features(system.city, sim.t, sim.idle, sim.arrivals, lookahead, scale, arrivals_now)


def state_features(
    city: City, t: int, idle: np.ndarray, arrivals: np.ndarray, lookahead: int = 6, scale: float = FEATURE_SCALE,
    arrivals_now: bool = False,
) -> np.ndarray:
    """(..., N, F) float32 features from idle (..., N) and arrivals (..., L, N) at step t.

    The leading axes are a batch of episodes in lockstep (:mod:`marl_amod.sim.batch`); the single
    env passes none, so both paths run this one function. Every value is the float64 count or
    value times ``scale``, rounded once to float32 (the multiplications write float32 directly).
    """
    length = arrivals.shape[-2]
    if t + lookahead < length:  # rows t+1..t+T all inside the buffer: a view
        arriving = arrivals[..., t + 1 : t + 1 + lookahead, :]  # (..., T, N)
    else:  # nothing arrives past the buffer, as in step_rows
        rows, inside = _arrival_rows(t, length, lookahead)
        arriving = arrivals[..., rows, :] * inside
    feats = np.empty((*idle.shape, n_features(lookahead, arrivals_now)), dtype=np.float32)  # (..., N, F)
    np.multiply(idle, scale, out=feats[..., 0])
    supply = idle[..., None, :] + arriving  # (..., T, N) idle now plus arrivals in t+1..t+T
    np.multiply(supply, scale, out=feats[..., 1 : 1 + lookahead].swapaxes(-1, -2))
    feats[..., 1 + lookahead : 1 + 2 * lookahead] = _value_table(city, lookahead, scale)[t]  # value, the same in every episode
    if arrivals_now:  # arriving during step t (nothing past the buffer)
        if t < length:
            np.multiply(arrivals[..., t, :], scale, out=feats[..., -1])
        else:
            feats[..., -1] = 0.0
    return feats


@functools.lru_cache(maxsize=4096)
def _arrival_rows(t: int, length: int, lookahead: int) -> tuple[np.ndarray, np.ndarray]:
    """Rows t+1..t+T of an arrivals buffer of ``length`` rows (clamped), and (T, 1) 'inside the
    buffer' (nothing arrives past it, as in step_rows); the same small arrays every episode."""
    steps = np.arange(t + 1, t + lookahead + 1)
    rows, inside = np.minimum(steps, length - 1), (steps < length)[:, None]
    rows.setflags(write=False)
    inside.setflags(write=False)
    return rows, inside


_VALUES: weakref.WeakKeyDictionary = weakref.WeakKeyDictionary()


def _value_table(city: City, lookahead: int, scale: float) -> np.ndarray:
    """(S, N, T) float32 expected request value out of each region in steps t+1..t+T (zero past
    the table), times ``scale``.

    Depends on the city's tables alone, so it is computed once per city, look-ahead and scale
    instead of every step (the same products and sums as before, so the same numbers).
    """
    per_city = _VALUES.setdefault(city, {})
    if (lookahead, scale) not in per_city:
        steps = np.arange(city.n_steps)[:, None] + np.arange(1, lookahead + 1)[None, :]  # (S, T)
        value = step_rows(city.expected_fares, steps)  # (S, T, N) float64
        table = (np.swapaxes(value, -1, -2) * scale).astype(np.float32)
        table.setflags(write=False)
        per_city[(lookahead, scale)] = table
    return per_city[(lookahead, scale)]


def feature_high(city: City, lookahead: int = 6, scale: float = FEATURE_SCALE, arrivals_now: bool = False) -> np.ndarray:
    """(F,) finite upper bounds of :func:`node_features` on ``city``.

    Idle, supply and the arrivals now count disjoint vehicles, so none exceeds the fleet; the
    request value is a function of the city's tables alone. Finite bounds keep observation spaces
    usable by learners that normalise or sample them.
    """
    fleet = city.fleet_size * scale
    value = float(city.expected_fares.max()) * scale
    high = np.concatenate([np.full(1 + lookahead, fleet), np.full(lookahead, value), np.full(int(arrivals_now), fleet)])
    return (high * (1 + 1e-6)).astype(np.float32)
