"""Where real-city data lives.

One setting finds it: the ``MARL_AMOD_DATA`` environment variable (or ``--data-dir`` on the CLI,
which sets it). The folder holds ``macro/`` (RL4AMOD city JSON files and
``calibrated_parameters.json``) and ``lux/`` (the LuST OpenStreetMap network). Nothing here is
ever copied into the repository; the synthetic default scenario needs no data at all.
"""

from __future__ import annotations

import json
import os
from collections.abc import Hashable
from pathlib import Path
from typing import Any

import yaml

from marl_amod.errors import ConfigError, DataError

ENV_VAR = "MARL_AMOD_DATA"


def data_dir() -> Path:
    """The data root, or a clear error saying how to set it."""
    value = os.environ.get(ENV_VAR)
    if not value:
        raise DataError(
            f"real-city scenarios need the data directory: set {ENV_VAR}=/path/to/data "
            "(the folder holding macro/ and lux/) or pass --data-dir. "
            "The synthetic scenarios need no data."
        )
    root = Path(value).expanduser()
    if not root.is_dir():
        raise DataError(f"the data directory {value!r} (--data-dir, or {ENV_VAR}) is not a directory")
    return root


def resolve(relative: str | Path) -> Path:
    """Absolute path of a data file named relative to the data root; errors name the file."""
    path = Path(relative)
    if not path.is_absolute():
        path = data_dir() / path
    if not path.is_file():
        raise DataError(f"data file not found: {path}")
    return path


def read_json(path: Path) -> Any:
    """Parse a JSON file; a syntax error names the file, line and column."""
    try:
        with path.open("r", encoding="utf-8") as fh:
            return json.load(fh)
    except json.JSONDecodeError as exc:
        raise DataError(f"malformed JSON in {path}: {exc.msg} at line {exc.lineno}, column {exc.colno}") from exc
    except OSError as exc:
        raise DataError(f"cannot read {path}: {exc}") from exc


class _UniqueKeyLoader(yaml.SafeLoader):
    """PyYAML's safe loader, except that a key given twice in one mapping is an error: plain YAML
    keeps the last value, so a duplicated ``tstep:`` silently overrides the first."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        seen: set = set()
        for key_node, _ in node.value:
            key = self.construct_object(key_node, deep=True)
            if not isinstance(key, Hashable):
                continue  # the parent reports unhashable keys itself
            if key in seen:
                raise yaml.constructor.ConstructorError(None, None, f"duplicate key {key!r}", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep)


def read_yaml(path: str | Path, what: str = "config") -> dict[str, Any]:
    """Parse a YAML mapping (a scenario or an experiment config); every failure (a duplicate key
    included) is a :class:`ConfigError` naming the file, never a parser traceback. An empty file
    is ``{}``."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"{what} {path} not found")
    try:
        raw = yaml.load(path.read_text(encoding="utf-8"), Loader=_UniqueKeyLoader) or {}  # noqa: S506 (a SafeLoader)
    except yaml.YAMLError as exc:
        raise ConfigError(f"malformed YAML in {path}: {exc}") from exc
    except UnicodeDecodeError as exc:
        raise ConfigError(f"{path} is not UTF-8 text (byte {exc.start}): save it as UTF-8") from None
    if not isinstance(raw, dict):
        raise ConfigError(f"{path}: expected a mapping of keys")
    return raw
