"""Training configs: one loader, ``extends:``, value bounds, and one readable line per problem.

A config file names an algorithm and its arguments::

    extends: nyc_brooklyn.yaml     # optional: start from another config (path relative to this file)
    algo: a2c
    args: {conv: sage, episodes: 30000}

``args`` are validated by the algorithm's pydantic model (every native algorithm's ``Args``
extends :class:`~marl_amod.algos.common.RunArgs`, RLlib's extends :class:`CommonArgs` too), so a
typo, an out-of-range value or a key the chosen mode ignores is a :class:`ConfigError` naming the
file and the key, before any training starts.
"""

from __future__ import annotations

from collections.abc import Mapping
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ConfigDict, Field, ValidationError, model_validator

from marl_amod.data import read_yaml
from marl_amod.errors import UNKNOWN_KEY, ConfigError, pydantic_problem

REPORT_SEED = 0  # the report streams: `marl-amod evaluate --seed 0`, scored once per shipped change


def problems(where: str, exc: ValidationError, prefix: str = "") -> ConfigError:
    """One ``where: key: message`` line per pydantic error, never pydantic's multi-line dump."""
    lines = []
    for err in exc.errors():
        key, msg = pydantic_problem(err, (prefix,) if prefix else (), UNKNOWN_KEY)
        lines.append(f"{where}: {key or 'config'}: {msg}")
    return ConfigError("\n".join(lines))


class CommonArgs(BaseModel):
    """What every training run has, native or RLlib: the city, the features, the evaluation, the files.

    Each field is documented by the string under it, as in single-file RL scripts.
    """

    model_config = ConfigDict(extra="forbid", use_attribute_docstrings=True, validate_assignment=True)

    scenario: str = "synthetic"
    """scenario name or YAML path"""
    lookahead: int = Field(6, ge=1)
    """look-ahead steps T of the node features (F = 1 + 2T)"""
    hidden: int = Field(32, ge=1)
    """hidden units of the actor (and critic) MLPs"""
    gamma: float = Field(0.97, gt=0, le=1)
    """discount factor (the paper's)"""
    reward_scale: float = Field(0.01, gt=0)
    """multiplies the money reward so returns are O(1..100)"""
    seed: int = Field(0, ge=0)
    """torch/numpy seed and training demand stream"""
    eval_every: int = Field(200, ge=1)
    """episodes (RLlib: iterations) between validation evaluations"""
    eval_episodes: int = Field(5, ge=1)
    """validation episodes (deterministic policy)"""
    eval_seed: int = Field(1000, ge=0)
    """validation demand seed; the best validation actor is kept (never the report seeds)"""
    final_eval_episodes: int = Field(10, ge=1)
    """episodes of the final report evaluation"""
    final_eval_seed: int = Field(0, ge=0)
    """report seed: same streams as `marl-amod evaluate --seed 0`"""
    time_limit_s: float = Field(0.0, ge=0)
    """stop early after this much wall time (0: no limit)"""
    run_dir: str = "runs/train"
    """logs, the resumable training state and the final evaluation"""
    policy_out: str = ""
    """where the final policy .pt (+ .json/.md cards) goes; empty: do not write one"""

    def ignored_keys(self) -> dict[str, str]:
        """Keys this run does not read, with the reason; giving one is an error, not a silent no-op."""
        return {}

    @model_validator(mode="before")
    @classmethod
    def _no_switch_for_a_number(cls, values: Any) -> Any:
        """pydantic's lax mode reads YAML's true/false as 1/0 in a number field: ``hidden: true`` is a slip, not 1 unit."""
        if isinstance(values, Mapping):
            for key, value in values.items():
                field = cls.model_fields.get(key)
                if field is not None and field.annotation in (int, float) and isinstance(value, bool):
                    raise ValueError(f"{key} must be a number, got {value!r}")
        return values

    @model_validator(mode="after")
    def _reject_ignored(self) -> CommonArgs:
        bad = {k: why for k, why in self.ignored_keys().items() if k in self.model_fields_set}
        if bad:
            raise ValueError("; ".join(f"{k} is not read: {why}" for k, why in bad.items()))
        return self

    @model_validator(mode="after")
    def _policy_file(self) -> CommonArgs:
        if self.policy_out and not self.policy_out.endswith(".pt"):  # it was written as .pt while the card named the other
            raise ValueError(f"policy_out {self.policy_out!r}: a policy file is a .pt (its cards go beside it as .json and .md)")
        return self

    @model_validator(mode="after")
    def _validation_apart_from_report(self) -> CommonArgs:
        # the kept actor would be chosen on the episodes it is reported on: the run's final evaluation's, or the
        # report streams of `marl-amod evaluate --seed 0` (a config that moves final_eval_seed elsewhere still has them)
        report = {self.final_eval_seed: "final_eval_seed's", REPORT_SEED: "the report seed (marl-amod evaluate --seed 0)"}
        if self.eval_seed in report:
            raise ValueError(f"eval_seed {self.eval_seed} is {report[self.eval_seed]}: validation must not run on the report streams")
        return self


def _read_config(path: Path, chain: tuple[Path, ...] = ()) -> dict[str, Any]:
    """The file's keys over those of the config it ``extends:`` (``args`` merged key by key)."""
    raw = read_yaml(path)
    if "args" in raw and raw["args"] is None:  # "args:" with only comments under it: no keys, not "no args"
        raw["args"] = {}
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if not isinstance(base, str):
        raise ConfigError(f"{path}: extends: must name one config file, got {base!r}")
    base_path = (path.parent / base).resolve()
    if base_path in (*chain, path.resolve()):
        raise ConfigError(f"{path}: extends: {base} makes a cycle")
    if not base_path.is_file():
        raise ConfigError(f"{path}: extends: {base} not found (looked for {base_path})")
    parent = _read_config(base_path, (*chain, path.resolve()))
    merged = {**parent, **raw}
    if isinstance(parent.get("args"), Mapping) and isinstance(raw.get("args"), Mapping):
        merged["args"] = {**parent["args"], **raw["args"]}
    return merged


def read_config(path: str | Path) -> dict[str, Any]:
    """A config file's keys with ``extends:`` resolved; errors name the file."""
    return _read_config(Path(path))


def make_args(models: Mapping[str, type[BaseModel]], algo: str, values: Mapping[str, Any], where: str = "config") -> BaseModel:
    """Validate ``values`` against ``models[algo]``; every problem is one ``where: key: message`` line."""
    if algo not in models:
        raise ConfigError(f"{where}: algo: unknown algorithm {algo!r}; known: {', '.join(sorted(models))}")
    if not isinstance(values, Mapping):
        raise ConfigError(f"{where}: args: expected a mapping of keys")
    try:
        return models[algo].model_validate(dict(values))
    except ValidationError as exc:
        raise problems(where, exc, "args") from None


def load_config(path: str | Path, models: Mapping[str, type[BaseModel]]) -> tuple[str, BaseModel]:
    """(algo, validated args) from a training config whose ``algo`` is one of ``models``."""
    raw = read_config(path)
    unknown = sorted(set(raw) - {"algo", "args"})
    if unknown:
        raise ConfigError("\n".join(f"{path}: {k}: unknown key (a config has extends, algo and args)" for k in unknown))
    if "algo" not in raw:
        raise ConfigError(f"{path}: algo: missing; known: {', '.join(sorted(models))}")
    return raw["algo"], make_args(models, str(raw["algo"]), raw.get("args", {}) or {}, str(path))
