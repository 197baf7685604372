"""Checks on numbers where they enter the library, so a bad value is an error naming its place.

A NaN or infinite price, a negative fleet or a NaN policy weight does not fail by itself: numpy
carries it to the end of the run (``nan ± nan``, or a NaN weight cast to the integer that means
"stay"). Every entry point (city files, :class:`~marl_amod.scenario.types.City`, the
coordinator's public functions, policy outputs, seeds) checks its arrays here once, and the
error says which array, which entry and, for region-indexed arrays, which region.
"""

from __future__ import annotations

import numbers
from typing import Any

import numpy as np

from marl_amod.errors import ConfigError, DataError, MarlAmodError


def where(index: tuple[int, ...], lead: int = 0) -> str:
    """A region-indexed position in words: (N,) 'region i', (N, N) 'regions i->j', (S, N, N) 'step t, regions i->j';
    the first ``lead`` axes are a batch of episodes ('episode b, region i')."""
    idx = tuple(int(k) for k in index)
    if lead:
        b = idx[0] if lead == 1 else idx[:lead]
        return f"episode {b}, {where(idx[lead:])}"
    if len(idx) == 1:
        return f"region {idx[0]}"
    if len(idx) == 2:
        return f"regions {idx[0]}->{idx[1]}"
    if len(idx) == 3:
        return f"step {idx[0]}, regions {idx[1]}->{idx[2]}"
    return f"index {idx}"


def check_array(
    value: Any,
    what: str,
    *,
    shape: tuple[int, ...] | None = None,
    minimum: float | None = None,
    integer: bool = False,
    error: type[MarlAmodError] = DataError,
    lead: int = 0,
) -> np.ndarray:
    """``value`` as a float or int64 array, or ``error`` naming ``what`` and the first bad entry.

    Rejects strings, booleans, complex numbers and objects; a shape other than ``shape``; NaN and
    infinity; values below ``minimum``; and, with ``integer``, non-integral values. ``lead``
    leading axes are a batch of episodes, named as such in the error.
    """
    arr = np.asarray(value)
    if arr.dtype.kind not in "iuf":
        raise error(f"{what} must be real numbers, got an array of {arr.dtype}")
    if shape is not None and arr.shape != tuple(shape):
        raise error(f"{what} must have shape {tuple(shape)}, got {arr.shape}")
    if arr.dtype.kind == "f":
        bad = ~np.isfinite(arr)
        if bad.any():
            k = np.unravel_index(int(np.argmax(bad)), arr.shape) if arr.ndim else ()
            raise error(f"{what} is not finite ({arr[k]}) at {where(k, lead)}" if arr.ndim else f"{what} is not finite ({arr})")
    if minimum is not None:
        low = arr < minimum
        if low.any():
            k = np.unravel_index(int(np.argmax(low)), arr.shape) if arr.ndim else ()
            at = f" at {where(k, lead)}" if arr.ndim else ""
            raise error(f"{what} must be >= {minimum:g}, got {arr[k]}{at}")
    if integer:
        if arr.dtype.kind == "f":
            frac = arr != np.round(arr)
            if frac.any():
                k = np.unravel_index(int(np.argmax(frac)), arr.shape) if arr.ndim else ()
                at = f" at {where(k, lead)}" if arr.ndim else ""
                raise error(f"{what} must be whole numbers, got {arr[k]}{at}")
        return arr.astype(np.int64, copy=False)  # int64 input comes back as is, never written to
    return arr


def as_seed(seed: Any, what: str = "seed") -> int:
    """A seed as a Python int: integers of any kind (numpy included), never negative or a bool."""
    return as_count(seed, what)


def as_count(value: Any, what: str, *, lower: int = 0, upper: int | None = None, why: str = "") -> int:
    """A whole number in [lower, upper] (numpy integers welcome, bools not), else a ConfigError."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral) or value < lower:
        kind = "a non-negative integer" if lower == 0 else f"an integer >= {lower}"
        raise ConfigError(f"{what} must be {kind}, got {value!r}")
    if upper is not None and value > upper:
        raise ConfigError(f"{what} must be at most {upper}{why}, got {int(value)}")
    return int(value)


def as_flag(value: Any, what: str) -> bool:
    """A bool (numpy's too), else a ConfigError: a switch given as ``"no"`` or 1 would read as on."""
    if not isinstance(value, (bool, np.bool_)):
        raise ConfigError(f"{what} must be True or False, got {value!r}")
    return bool(value)


def as_real(value: Any, what: str, *, minimum: float | None = None, above: float | None = None) -> float:
    """A finite real number, ``>= minimum`` and ``> above`` where given (numpy scalars welcome;
    strings, bools and None not), else a ConfigError: a policy option read from the command line
    as the wrong type must not fail later as a TypeError deep in a solver."""
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real) or not np.isfinite(value):
        raise ConfigError(f"{what} must be a finite number, got {value!r}")
    if minimum is not None and value < minimum:
        raise ConfigError(f"{what} must be >= {minimum:g}, got {value!r}")
    if above is not None and value <= above:
        raise ConfigError(f"{what} must be > {above:g}, got {value!r}")
    return float(value)
