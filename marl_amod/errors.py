"""Exceptions that tell the user what to fix (a file, a key, a shape), never just that something failed."""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any


class MarlAmodError(Exception):
    """Base class for every error raised on purpose by marl_amod."""


class DataError(MarlAmodError):
    """A data file is missing, unreadable or malformed."""


class ConfigError(MarlAmodError):
    """A scenario or experiment configuration is invalid (unknown key, bad value, unknown name)."""


class ActionError(MarlAmodError, ValueError):
    """An action has the wrong shape, is not finite, or (strict_actions) lies outside the action space."""


class SolverError(MarlAmodError):
    """An optimisation problem could not be solved; never silently replaced by a wrong action."""


class OutputError(MarlAmodError):
    """A result cannot be written where it was asked to go (a folder, a read-only place, a full disk)."""


UNKNOWN_KEY = {"extra_forbidden": "unknown key"}  # pydantic's "Extra inputs are not permitted", in a config's words


def pydantic_problem(err: Mapping[str, Any], prefix: tuple[str, ...] = (), words: Mapping[str, str] | None = None) -> tuple[str, str]:
    """``(key, message)`` of one error of a pydantic ``ValidationError`` (``exc.errors()``), in the
    library's words: the key its dotted location (``prefix`` first; "" for the whole model), the
    message without pydantic's ``Value error, `` or, for an error type in ``words``, the words given
    there (:data:`UNKNOWN_KEY`)."""
    key = ".".join(str(p) for p in (*prefix, *err["loc"]))
    return key, (words or {}).get(err["type"], err["msg"].removeprefix("Value error, "))


def pydantic_problems(exc: Any, words: Mapping[str, str] | None = None) -> str:
    """A ``ValidationError``'s errors on one line, ``key: message; key: message``
    (:func:`pydantic_problem`), never pydantic's multi-line report."""
    return "; ".join(f"{key}: {msg}" if key else msg for key, msg in (pydantic_problem(e, words=words) for e in exc.errors()))
