"""marl_amod: robo-taxi fleet coordination as a multi-agent RL benchmark.

``parallel_env(...)`` makes the PettingZoo ParallelEnv (every region an agent), ``env(...)`` its
AEC version; see :mod:`marl_amod.env.parallel` for the documentation. ``vector_env(...)`` runs B
episodes of one city in lockstep with (B, N, ...) arrays (:mod:`marl_amod.env.vector`).
``evaluate(policy, ...)`` scores any policy (a name, a checkpoint, a callable on observations) on
the benchmark's seeds; ``load_policy(path)`` returns a trained policy as such a callable.
Importing the package loads numpy-level code only (no torch); the env's modules load on first use.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

# ``marl_amod.env`` is the env subpackage, made callable: ``marl_amod.env(...)`` builds the AEC env.
from marl_amod import env

__version__ = "0.1.0"
__all__ = ["amod_v0", "env", "evaluate", "load_policy", "parallel_env", "vector_env"]

if TYPE_CHECKING:
    from pathlib import Path

    from marl_amod.baselines.base import WeightPolicy
    from marl_amod.env.parallel import AmodParallelEnv
    from marl_amod.env.vector import AmodVectorEnv
    from marl_amod.policies import PolicyLike
    from marl_amod.scenario.types import City


def parallel_env(scenario: str | City = "synthetic", **kwargs: Any) -> AmodParallelEnv:
    """The PettingZoo ParallelEnv: every region an agent (arguments: :mod:`marl_amod.env.parallel`).

    Keywords: reward_mode="team"|"local", action_mode="weight"|"logit", lookahead=6, max_wait=0,
    objective="profit", reward_scale=1.0|"auto", strict_actions=False, max_cycles=None, arrivals_now=False,
    render_mode=None, and scenario overrides such as horizon=10.
    """
    from marl_amod.env.parallel import parallel_env as make

    return make(scenario, **kwargs)


def vector_env(scenario: str | City = "synthetic", num_envs: int = 16, **kwargs: Any) -> AmodVectorEnv:
    """B episodes of one city in lockstep, arrays (B, N, ...) in and out (:mod:`marl_amod.env.vector`).

    Takes the ParallelEnv's keywords (reward_mode, action_mode, lookahead, max_wait, objective and
    scenario overrides); ``reset(seed=s)`` gives episode b the ParallelEnv's episode of seed s + b.
    """
    from marl_amod.env.vector import AmodVectorEnv

    return AmodVectorEnv(scenario, num_envs, **kwargs)


def evaluate(
    policy: PolicyLike, scenario: str | City = "synthetic", episodes: int = 10, seed: int = 0, **options: Any
) -> dict[str, Any]:
    """Score ``policy`` as ``marl-amod evaluate`` does, on the same demand draws (episode k: (seed, k)).

    ``policy``: a name (``marl-amod evaluate --help``), a checkpoint path (``.pt``), or any
    callable from the env's observations dict to its actions dict (PettingZoo convention; an SB3
    or TorchRL policy wrapped in a function). Options: ``max_wait``, ``objective``, ``solver``, ``validate``,
    and the policy's own (a callable's ``lookahead`` and ``action_mode``, MPC's ``horizon``).
    Returns exactly the JSON that ``marl-amod evaluate --output`` writes.
    """
    from marl_amod.evaluation import evaluate as run

    return run(policy, scenario, episodes, seed, **options)


def load_policy(path: str | Path, scenario: str | City | None = None, **options: Any) -> WeightPolicy:
    """A trained policy (``.pt``, or an ensemble ``.yaml`` of them) for the simulator and, unless
    it is a meta-policy (which reads the simulator), as a callable on the env's observations
    (default city: its card's). ``options``: ``selection`` and ``adaptation``, as
    :func:`marl_amod.checkpoints.load_policy` takes them."""
    from marl_amod.checkpoints import load_policy as load

    return load(path, scenario, **options)


def __getattr__(name: str) -> Any:
    if name == "amod_v0":
        from importlib import import_module

        return import_module("marl_amod.amod_v0")
    raise AttributeError(f"module 'marl_amod' has no attribute {name!r}")
