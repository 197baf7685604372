"""The offline datasets in other libraries' formats, so their algorithms run on our data.

Both libraries are single-agent, so both get the centralised view: the observation is
``env.state()`` (N F + 3), the action the joint action (N,) on the simplex (the env's normalised
weights: what the Dirichlet policy outputs), the reward the team reward; terminations and
truncations stay apart (the env never terminates; the horizon truncates).

* :func:`to_d3rlpy` -> ``d3rlpy.dataset.MDPDataset`` (``pip install "marl-amod[d3rlpy]"``;
  d3rlpy 2.8 pins gymnasium 1.0.0, so it installs beside the base package, not beside the
  rllib or torchrl extras, which need gymnasium >= 1.1).
* :func:`to_minari` -> a Minari dataset (``pip install "marl-amod[minari]"``; Minari 0.5 has no
  multi-agent datasets). It is written where Minari keeps datasets (``MINARI_DATASETS_PATH``).

:func:`state_policy` goes the way back: a policy learnt on that view (state -> joint action) as
the observations -> actions callable that ``marl_amod.evaluate`` scores (each agent's observation
holds its region's features and the time values, so the state is rebuilt exactly).
"""

from __future__ import annotations

import re
from collections.abc import Callable
from typing import Any

import numpy as np

from marl_amod.datasets import OfflineDataset, action_share
from marl_amod.env.observations import split_local, state_from_features
from marl_amod.errors import ConfigError, DataError
from marl_amod.metrics import SCORE_ANCHORS
from marl_amod.validation import as_count


def centralised_arrays(data: OfflineDataset) -> dict[str, np.ndarray]:
    """(T, D) observations and next observations, (T, N) actions, (T,) rewards, terminations, truncations."""
    return {
        "observations": np.asarray(data.states, dtype=np.float32),
        "next_observations": np.asarray(data.next_states, dtype=np.float32),
        "actions": action_share(data.actions).astype(np.float32),
        "rewards": np.asarray(data.team_rewards, dtype=np.float32),
        "terminations": np.asarray(data.terminations, dtype=bool),
        "truncations": np.asarray(data.truncations, dtype=bool),
    }


def episodes(data: OfflineDataset) -> list[slice]:
    """Row ranges of the episodes, in the order they were logged (rows are episode-major)."""
    ids = np.asarray(data.episode_ids)
    starts = np.flatnonzero(np.r_[True, ids[1:] != ids[:-1]])
    ends = np.r_[starts[1:], len(ids)]
    return [slice(int(a), int(b)) for a, b in zip(starts, ends, strict=True)]


def _need(module: str, extra: str) -> Any:
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise ConfigError(f"exporting to {extra} needs it installed: pip install \"marl-amod[{extra}]\"") from None


def to_d3rlpy(data: OfflineDataset) -> Any:
    """A ``d3rlpy.dataset.MDPDataset`` of the centralised view (continuous actions on the simplex).

    d3rlpy marks an episode's end by ``terminals`` (a true end: no bootstrap) or ``timeouts``
    (cut by the horizon: bootstrap); our episodes end by truncation, so they are timeouts.
    """
    d3rlpy = _need("d3rlpy", "d3rlpy")
    a = centralised_arrays(data)
    return d3rlpy.dataset.MDPDataset(
        observations=a["observations"], actions=a["actions"], rewards=a["rewards"][:, None],
        terminals=a["terminations"].astype(np.float32), timeouts=a["truncations"].astype(np.float32),
        action_space=d3rlpy.constants.ActionSpace.CONTINUOUS,
    )  # fmt: skip


def to_minari(data: OfflineDataset, dataset_id: str, *, card: dict[str, Any] | None = None) -> Any:
    """A Minari dataset ``dataset_id`` (e.g. ``"marl_amod/nyc_brooklyn/prop-v0"``) of the centralised
    view; ``card`` (the dataset card) adds the ED / MPC-Oracle references as Minari's score range, in
    episode profit as ``marl_amod.evaluate`` reports it (the reset's dispatch included, which no
    reward carries: a sum of the env's rewards is that much lower)."""
    minari = _need("minari", "minari")
    from gymnasium import spaces
    from minari.data_collector import EpisodeBuffer

    # checked before anything is written: a failure after create_dataset_from_buffers left a dataset that blocks the retry
    if not isinstance(dataset_id, str) or not re.fullmatch(r"[\w./-]+-v\d+", dataset_id):
        raise ConfigError(f"dataset_id {dataset_id!r}: Minari ids end in a version, e.g. 'marl_amod/nyc_brooklyn/prop-v0'")
    if card is not None and not isinstance(card, dict):
        raise ConfigError(f"card must be the dataset card as a dict (marl_amod.datasets.read_card(path)), got {type(card).__name__}")
    refs = (card or {}).get("reference_scores", {})
    if refs and not set(SCORE_ANCHORS) <= set(refs):
        raise DataError(f"the card's reference_scores hold {sorted(refs)}; the score range needs {', '.join(SCORE_ANCHORS)}")
    a = centralised_arrays(data)
    buffers = []
    for k, rows in enumerate(episodes(data)):
        obs = np.concatenate([a["observations"][rows], a["next_observations"][rows][-1:]])  # (T + 1, D)
        buffers.append(EpisodeBuffer(id=k, observations=obs, actions=a["actions"][rows], rewards=a["rewards"][rows],
                                     terminations=a["terminations"][rows], truncations=a["truncations"][rows]))  # fmt: skip
    meta = data.meta
    dataset = minari.create_dataset_from_buffers(
        dataset_id, buffers, algorithm_name=str(meta.get("policy")), author="marl_amod", data_format="arrow",
        observation_space=spaces.Box(-np.inf, np.inf, a["observations"].shape[1:], np.float32),
        action_space=spaces.Box(0.0, 1.0, a["actions"].shape[1:], np.float32),
        description=f"marl_amod {meta.get('scenario')} logged by {meta.get('policy')}: centralised view (env.state(), joint action "
                    "on the simplex, team reward); the per-agent view is in the .npz (marl_amod.datasets)",
    )  # fmt: skip
    if refs:  # Minari stores ref_min/max_score only beside an eval env (we have no gymnasium id): written apart
        dataset.storage.update_metadata(
            dict(zip(("ref_min_score", "ref_max_score"), (refs[name]["mean"] for name in SCORE_ANCHORS), strict=True))
        )
    return dataset


def state_policy(predict: Callable[[np.ndarray], Any], n_features: int = 13) -> Callable[[dict[str, Any]], dict[str, np.ndarray]]:
    """``predict`` (``env.state()`` (N F + 3,) -> the joint action (N,), e.g. ``lambda s: algo.predict(s[None])[0]``)
    as a callable on the env's observations dict, for ``marl_amod.evaluate``; ``n_features`` is the
    dataset's F (``data.n_features``: 13 at look-ahead 6, one more with ``arrivals_now``), and the
    env's observations must hold as many (``evaluate(..., lookahead=T, arrivals_now=...)``): else a
    ConfigError, since on some cities another F also splits them, into a state of wrong numbers."""
    as_count(n_features, "n_features", lower=3)  # F = 1 + 2T (+ 1) with T >= 1
    lookahead, arrivals_now = divmod(int(n_features) - 1, 2)  # F = 1 + 2T (+ 1)
    options = f"lookahead={lookahead}" + (", arrivals_now=True" if arrivals_now else "")

    def act(observations: dict[str, Any]) -> dict[str, np.ndarray]:
        agents = sorted(observations, key=lambda a: int(a.rsplit("_", 1)[1]))  # region_0 .. region_{N-1}
        local = np.stack([np.asarray(observations[a]) for a in agents])
        try:
            own, context, _, mask = split_local(local, n_features)
            fits = _layout_fits(context, mask)
        except ValueError:  # no K fits its length
            fits = False
        if not fits:
            raise ConfigError(
                f"observations of length {local.shape[-1]} do not hold n_features={n_features} features a region: "
                f"evaluate the policy on the env it was learnt on ({options})"
            )
        joint = np.asarray(predict(state_from_features(own, context[0])), dtype=np.float32)
        if joint.size != len(agents):  # a predictor learnt on another city
            raise ConfigError(f"the predictor answered {joint.size} weights for this city's {len(agents)} regions: "
                              "evaluate it on the city its dataset was logged on")  # fmt: skip
        joint = joint.reshape(len(agents))
        return {a: joint[i : i + 1] for i, a in enumerate(agents)}

    act.name = "state-policy"  # type: ignore[attr-defined]  # evaluate's record (and the results tables) name it so; name= overrides
    return act


def _layout_fits(context: np.ndarray, mask: np.ndarray) -> bool:
    """Whether a split of every agent's observation found the blocks where they are: one clock for
    all (sin, cos on the unit circle, a step fraction in [0, 1]) and a mask of zeros and ones."""
    sin, cos, frac = context[0]
    return bool(
        (context == context[0]).all()
        and abs(sin * sin + cos * cos - 1.0) < 1e-3
        and 0.0 <= frac <= 1.0
        and np.isin(mask, (0.0, 1.0)).all()
    )
