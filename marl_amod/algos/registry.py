"""The algorithms by name: what ``marl-amod train``, ``compare`` and the policy card look up.

Adding an algorithm is one file (an ``Args`` model extending
:class:`~marl_amod.algos.common.RunArgs` and a ``train`` function with the signature of
:class:`TrainFn`) plus one line in :data:`ALGOS`, plus a config under ``configs/<algo>/``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

from marl_amod.algos import a2c, bc, cql, iql, meta, meta_imitation, sac
from marl_amod.algos.common import Progress, RunArgs, check_not_interrupted
from marl_amod.config import load_config, make_args
from marl_amod.errors import ConfigError
from marl_amod.files import check_destination, check_folder


class TrainFn(Protocol):
    def __call__(
        self, args: Any, *, resume: str | None = None, progress: Progress | None = None, config_path: str | None = None
    ) -> dict[str, Any]:
        """Train; write the policy and its card to ``args.policy_out``; return {card, result[, policy]}."""


@dataclass(frozen=True)
class Algorithm:
    """One registry entry: the algorithm's validated arguments and its training function."""

    args: type[RunArgs]
    train: TrainFn
    summary: str = ""


ALGOS: dict[str, Algorithm] = {
    "a2c": Algorithm(a2c.Args, a2c.train, "advantage actor-critic, Dirichlet policy (on-policy)"),
    "sac": Algorithm(sac.Args, sac.train, "soft actor-critic, Dirichlet policy, twin GNN critics (off-policy)"),
    "bc": Algorithm(bc.Args, bc.train, "behaviour cloning from an offline dataset, Dirichlet likelihood"),
    "iql": Algorithm(iql.Args, iql.train, "implicit Q-learning from an offline dataset (expectile V, advantage-weighted actor)"),
    "cql": Algorithm(cql.Args, cql.train, "conservative Q-learning from an offline dataset (SAC with a CQL penalty)"),
    "meta": Algorithm(meta.Args, meta.train, "meta-RL through recurrence (RL2): a recurrent GNN over trials on ten cities"),
    "meta-bc": Algorithm(meta_imitation.Args, meta_imitation.train, "the recurrent meta-policy imitating MPC-Forecast on the training cities (RL2's warm start)"),
}


def _models() -> Mapping[str, type[RunArgs]]:
    return {name: algo.args for name, algo in ALGOS.items()}


def algorithm(name: str) -> Algorithm:
    if name not in ALGOS:
        raise ConfigError(f"unknown algorithm {name!r}; known: {', '.join(sorted(ALGOS))}")
    return ALGOS[name]


def args_for(name: str, values: Mapping[str, Any], where: str = "config") -> RunArgs:
    """``values`` validated as algorithm ``name``'s Args (bounds, unknown and ignored keys)."""
    return make_args(_models(), name, values, where)  # type: ignore[return-value]


def load_train_config(path: str | Path) -> tuple[str, RunArgs]:
    """(algo, Args) from a YAML training config (``extends:`` resolved)."""
    return load_config(path, _models())  # type: ignore[return-value]


def run_training(
    name: str, args: RunArgs, resume: str | None = None, progress: Progress | None = None, config_path: str | None = None
) -> dict[str, Any]:
    """Train with the registered algorithm ``name``; returns the summary (card, final evaluation, policy path).

    The policy's destination and the run folder are checked first, so a bad ``policy_out`` or
    ``run_dir`` fails now, not after training.
    """
    entry = algorithm(name)
    if args.policy_out:
        check_destination(args.policy_out, what="policy_out")
    check_folder(args.run_dir, what="run_dir")
    check_not_interrupted(args.run_dir, resume)
    return entry.train(args, resume=resume, progress=progress, config_path=config_path)
