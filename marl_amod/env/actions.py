"""From per-agent actions to the coordinator's target: validation, clipping, weights.

Each agent acts with one number ``a`` in ``Box(0, 1, (1,))``. The rule for values outside:

* a value that is not finite, or of a shape other than ``()`` or ``(1,)``, raises
  :class:`~marl_amod.errors.ActionError` naming the agent (a bug upstream);
* any other value is clipped into [0, 1], as PettingZoo's own continuous envs do, so a Gaussian
  policy (tianshou, skrl, SB3 without squashing) can act on the env unmodified;
* with ``strict=True`` (the env's ``strict_actions=True``) a finite value outside [0, 1] raises
  instead: for code that wants to catch a policy that leaves the action space.

``weight`` mode: the clipped values are the weights w; the coordinator's target is
floor(w_i / sum(w) * M) (independent Gamma(alpha_i) samples normalised this way are exactly a
Dirichlet(alpha) sample). An all-zero joint action means "stay": no rebalancing this step.

``logit`` mode: a -> logit ``LOGIT_RANGE * (2a - 1)`` in [-10, 10], then a softmax across agents
gives the weights (so an all-zero joint action asks for a uniform distribution, not "stay").
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from typing import Any, Literal

import numpy as np

from marl_amod.errors import ActionError
from marl_amod.system import FleetSystem

ActionMode = Literal["weight", "logit"]
ACTION_MODES: tuple[str, ...] = ("weight", "logit")
LOGIT_RANGE = 10.0


def joint_action(actions: Mapping[str, Any], agents: Sequence[str], *, strict: bool = False) -> np.ndarray:
    """(N,) float64 actions in [0, 1] in the order of ``agents``; raises ActionError on bad input.

    Finite values outside [0, 1] are clipped, or raise when ``strict``.
    """
    if not isinstance(actions, (dict, Mapping)):  # a dict answers without the ABC machinery
        raise ActionError(f"actions must be a dict {{agent: action}}, got {type(actions).__name__}")
    stacked = _stacked(actions, agents)
    # a finite sum means finite values (a sum that overflows merely takes the checked path below)
    if stacked is not None and math.isfinite(stacked.sum()) and not (strict and ((stacked < 0.0) | (stacked > 1.0)).any()):
        return stacked.clip(0.0, 1.0)  # np.clip's own ufunc, without np.clip's dispatch layer
    # otherwise agent by agent, so an error names the agent and what is wrong with its action
    missing = [a for a in agents if a not in actions]
    if missing:
        shown = ", ".join(missing[:5]) + (" ..." if len(missing) > 5 else "")
        raise ActionError(f"actions are missing for {len(missing)} agent(s): {shown}; every live agent must act")
    unknown = [a for a in actions if a not in set(agents)]
    if unknown:
        raise ActionError(f"actions given for unknown or finished agent(s): {', '.join(map(str, unknown[:5]))}")
    out = np.empty(len(agents))
    for k, agent in enumerate(agents):
        value = np.asarray(actions[agent], dtype=np.float64) if _numeric(actions[agent], f"action of {agent}") else None
        if value is None:
            raise ActionError(f"action of {agent} must be a number or an array of shape (1,), got {actions[agent]!r}")
        if value.shape not in ((), (1,)):
            raise ActionError(f"action of {agent} must have shape (1,), got shape {value.shape}")
        v = float(value.reshape(()))
        if not np.isfinite(v):
            raise ActionError(f"action of {agent} is not finite: {v}")
        if strict and not 0.0 <= v <= 1.0:
            raise ActionError(f"action of {agent} is {v}, outside the action space [0, 1] (strict_actions=True)")
        out[k] = v
    return np.clip(out, 0.0, 1.0)


def weights(action: np.ndarray, mode: ActionMode) -> np.ndarray:
    """(..., N) non-negative weights from clipped actions (..., N) in [0, 1]."""
    if mode == "weight":
        return action
    logits = LOGIT_RANGE * (2.0 * action - 1.0)  # leading axes: a batch of joint actions
    z = np.exp(logits - logits.max(axis=-1, keepdims=True))
    return z / z.sum(axis=-1, keepdims=True)


def targets(
    system: FleetSystem, actions: Mapping[str, Any], agents: Sequence[str], mode: ActionMode, *, strict: bool = False
) -> np.ndarray:
    """(N,) coordinator targets of a joint action: the env's step and policies written for it share this path."""
    # joint_action's values are finite and in [0, 1], their softmax too: nothing left to check
    return system.targets_from_weights(weights(joint_action(actions, agents, strict=strict), mode), check=False)


_SCALARS = frozenset({float, int, np.float64, np.float32, np.float16, np.int64, np.int32, np.int16, np.int8, np.uint8})


def _stacked(actions: Mapping[str, Any], agents: Sequence[str]) -> np.ndarray | None:
    """(N,) float64 actions in one array call when every live agent acted with a real number or
    a numeric array of shape () or (1,), and nobody else did; None otherwise (the checked path
    then finds the problem). Bools, strings and complex values never take this path."""
    if len(actions) != len(agents):
        return None
    try:
        values = [actions[a] for a in agents]
    except KeyError:
        return None
    for v in values:
        kind = type(v)
        if kind is np.ndarray:
            if v.dtype.kind not in "iuf":
                return None
        elif kind not in _SCALARS:
            return None
    try:
        stacked = np.array(values, dtype=np.float64)
    except ValueError:  # mixed shapes
        return None
    n = len(agents)
    return stacked.reshape(n) if stacked.shape in ((n,), (n, 1)) else None


def real_array(actions: Any, what: str = "actions") -> np.ndarray:
    """An array of actions for the array envs (vector, joint), refused unless it holds real numbers,
    as the ParallelEnv refuses them: numpy would read "0.5" as 0.5, drop a complex number's
    imaginary part and take bools as 0/1."""
    try:
        a = np.asarray(actions)
    except (TypeError, ValueError) as exc:  # ragged lists, tensors that live on another device
        raise ActionError(f"{what} must be a numeric array: {exc}") from exc
    except RuntimeError as exc:  # a torch tensor that requires grad
        raise ActionError(f"{what}: {GRAD_HINT} ({str(exc).splitlines()[0]})") from exc
    if a.dtype.kind not in "iuf":
        raise ActionError(f"{what} must be real numbers (an int or float array), got dtype {a.dtype}")
    return a


GRAD_HINT = "a tensor that requires grad; pass action.detach() (or act under torch.no_grad())"


def _numeric(value: Any, what: str) -> bool:
    """Real numbers only: numpy would read "0.5" as 0.5 and drop a complex number's imaginary part."""
    try:
        return np.asarray(value).dtype.kind in "iuf"
    except (TypeError, ValueError):
        return False
    except RuntimeError as exc:  # a torch tensor that requires grad: say so, not "not a number"
        raise ActionError(f"{what}: {GRAD_HINT}") from exc
