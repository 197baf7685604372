"""Exceptions that tell the user what to fix (a file, a key, a shape), never just that something failed."""


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
