"""Local and global observations of the multi-agent env: one fixed layout for every region.

Every agent (region i) sees a float32 vector of length ``D = F + 3 + K * (F + 1)`` where
``F = 1 + 2T`` node features (T = ``lookahead``, 13 by default; one more, last, with the opt-in
``arrivals_now`` column: :mod:`marl_amod.env.features`) and ``K = max_degree`` neighbour
slots (the largest in-degree of the city graph unless given). In order:

===================  =========  =====================================================================
block                size       meaning and scaling
===================  =========  =====================================================================
own features         F          :func:`marl_amod.env.features.node_features` row of region i, times 0.01:
                                ``idle`` (idle vehicles after this step's dispatch), ``supply_t+k``
                                (idle now plus vehicles arriving at i in step t+k, k = 1..T),
                                ``value_t+k`` (expected requests out of i in step t+k times their
                                fare, summed over destinations); all >= 0
time of day          2          ``sin`` and ``cos`` of 2*pi*h/24, h = ``city.start_hour`` + t*tstep/60
step fraction        1          t / horizon, in [0, 1)
neighbour features   K * F      the F features of each in-neighbour j (edges j -> i of
                                ``city.edge_index``), sorted by j; empty slots are zeros
neighbour mask       K          1.0 for a real neighbour slot, 0.0 for padding
===================  =========  =====================================================================

:func:`split_local` cuts such a vector (or a batch of them, numpy or torch) back into the blocks,
so a shared-parameter message-passing layer runs from one agent's observation alone. The global
state (:func:`global_state`) is the N x F feature matrix, flattened, followed by the 3 time values.
:class:`LocalLayout` and :func:`state_from_features` build both layouts from features with
leading batch axes (B, N, F): the batched env (:mod:`marl_amod.env.vector`) and the single env run
the same code.
"""

from __future__ import annotations

import functools
from typing import Any

import numpy as np

from marl_amod.env.features import n_features, node_features
from marl_amod.scenario.types import City
from marl_amod.system import FleetSystem

N_CONTEXT = 3  # sin(time of day), cos(time of day), step fraction


def agent_names(n_regions: int) -> list[str]:
    """The agents' names, region by region: ``region_0`` ... ``region_{N-1}``."""
    return [f"region_{i}" for i in range(n_regions)]


def max_in_degree(city: City) -> int:
    """Largest number of in-neighbours of any region (at least 1, so the layout is never empty)."""
    if city.edge_index.size == 0:
        return 1
    return max(1, int(np.bincount(city.edge_index[1], minlength=city.n_regions).max()))


def neighbour_table(city: City, max_degree: int | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(N, K) int64 indices of in-neighbours j of each region i (edges j -> i, sorted by j) and (N, K) mask.

    Padding slots hold index 0 and mask 0, so a gather followed by a multiply by the mask is exact.
    """
    n = city.n_regions
    k = max_in_degree(city) if max_degree is None else int(max_degree)
    src, dst = np.asarray(city.edge_index, dtype=np.int64)
    idx = np.zeros((n, k), dtype=np.int64)
    mask = np.zeros((n, k), dtype=np.float32)
    if src.size == 0:
        return idx, mask
    order = np.lexsort((src, dst))  # group by target, then by source
    src, dst = src[order], dst[order]
    counts = np.bincount(dst, minlength=n)
    if counts.max() > k:
        raise ValueError(f"max_degree={k} is smaller than the largest in-degree {counts.max()} of {city.name}")
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    slot = np.arange(src.size) - starts[dst]
    idx[dst, slot] = src
    mask[dst, slot] = 1.0
    return idx, mask


def time_features(city: City, t: int) -> np.ndarray:
    """(3,) float32: sin and cos of the clock time of step t, and t / horizon."""
    return _time_features(city.start_hour, city.tstep, city.horizon, t).copy()


@functools.lru_cache(maxsize=4096)
def _time_features(start_hour: float, tstep: float, horizon: int, t: int) -> np.ndarray:
    """:func:`time_features` by value, computed once per step of a clock (every episode asks again)."""
    hour = start_hour + t * tstep / 60.0
    angle = 2.0 * np.pi * hour / 24.0
    return np.array([np.sin(angle), np.cos(angle), t / horizon], dtype=np.float32)


def local_observations(
    system: FleetSystem,
    lookahead: int = 6,
    max_degree: int | None = None,
    *,
    table: tuple[np.ndarray, np.ndarray] | None = None,
    layout: LocalLayout | None = None,
    arrivals_now: bool = False,
) -> np.ndarray:
    """(N, D) float32 local observations of every region (layout in the module docstring).

    ``layout`` (a cached :class:`LocalLayout` of this city and look-ahead, what the envs pass) or
    ``table`` (a cached :func:`neighbour_table`) skip rebuilding them.
    """
    if layout is None:
        layout = LocalLayout(table if table is not None else neighbour_table(system.city, max_degree), n_features(lookahead, arrivals_now))
    city = system.city
    return layout(node_features(system, lookahead, arrivals_now=arrivals_now), _time_features(city.start_hour, city.tstep, city.horizon, system.t))


class LocalLayout:
    """The local observations of one city as one gather, built once per env (look-ahead fixed).

    Entry (i, d) of the (N, D) observations is entry ``index[i * D + d]`` of the source vector
    [features of every region (N * F, row by row), time features (3), 0, 1]: own features, time,
    each neighbour slot's features (the 0 for a padding slot), the mask (1 or 0). One ``take``
    then builds every region's observation, of B episodes at once, instead of a dozen block copies
    and a masked gather; the values are the same float32 numbers (features are finite and >= 0,
    so copying a neighbour's features equals multiplying them by a mask of 1, and 0 by a mask of 0).
    """

    def __init__(self, table: tuple[np.ndarray, np.ndarray], n_features: int) -> None:
        idx, mask = table
        n, k = idx.shape
        f = int(n_features)
        zero, one = n * f + N_CONTEXT, n * f + N_CONTEXT + 1
        real = np.asarray(mask) > 0
        columns = np.arange(f)
        own = np.arange(n)[:, None] * f + columns  # (N, F)
        context = np.broadcast_to(n * f + np.arange(N_CONTEXT), (n, N_CONTEXT))
        neighbours = np.where(real[:, :, None], np.asarray(idx)[:, :, None] * f + columns, zero).reshape(n, k * f)
        flags = np.where(real, one, zero)  # (N, K)
        self.index = np.concatenate([own, context, neighbours, flags], axis=1).reshape(-1)  # (N * D,)
        self.shape = (n, f + N_CONTEXT + k * (f + 1))  # (N, D)
        self.n_features = f
        self._constants = np.array([0.0, 1.0], dtype=np.float32)

    def __call__(self, feats: np.ndarray, context: np.ndarray) -> np.ndarray:
        """(..., N, D) float32 observations from features (..., N, F) and time features (3,)."""
        *lead, n, f = feats.shape
        if (n, f) != (self.shape[0], self.n_features):
            raise ValueError(f"features of shape {(n, f)} do not fit a layout for {(self.shape[0], self.n_features)}")
        if lead:
            tail = np.broadcast_to(np.concatenate([context, self._constants]), (*lead, N_CONTEXT + 2))
            source = np.concatenate([feats.reshape(*lead, n * f), tail], axis=-1)
        else:
            source = np.concatenate([feats.reshape(n * f), context, self._constants])
        return source.take(self.index, axis=-1).reshape(*lead, *self.shape).astype(np.float32, copy=False)


def local_bounds(feature_high: np.ndarray, max_degree: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of one local observation: features in [0, feature_high], time in [-1, 1], mask in [0, 1]."""
    f = len(feature_high)
    low = np.concatenate([np.zeros(f), [-1.0, -1.0, 0.0], np.zeros(max_degree * f), np.zeros(max_degree)])
    high = np.concatenate([feature_high, [1.0, 1.0, 1.0], np.tile(feature_high, max_degree), np.ones(max_degree)])
    return low.astype(np.float32), high.astype(np.float32)


def state_bounds(feature_high: np.ndarray, n_regions: int) -> tuple[np.ndarray, np.ndarray]:
    """Bounds of the global state: every region's features, then time of day and step fraction."""
    f = len(feature_high)
    low = np.concatenate([np.zeros(n_regions * f), [-1.0, -1.0, 0.0]])
    high = np.concatenate([np.tile(feature_high, n_regions), [1.0, 1.0, 1.0]])
    return low.astype(np.float32), high.astype(np.float32)


def split_local(obs: Any, n_features: int = 13) -> tuple[Any, Any, Any, Any]:
    """Cut local observations (..., D) into own (..., F), context (..., 3), neighbours (..., K, F), mask (..., K).

    Works on numpy arrays and torch tensors alike (slicing and reshape only; no torch import).
    """
    f = n_features
    d = obs.shape[-1]
    k, rest = divmod(d - f - N_CONTEXT, f + 1)
    if rest or k < 0:
        raise ValueError(f"an observation of length {d} does not fit the layout F + 3 + K*(F+1) with F={f}")
    lead = tuple(obs.shape[:-1])
    own = obs[..., :f]
    context = obs[..., f : f + N_CONTEXT]
    start = f + N_CONTEXT
    neighbours = obs[..., start : start + k * f].reshape(lead + (k, f))
    mask = obs[..., start + k * f :]
    return own, context, neighbours, mask


def global_state(system: FleetSystem, lookahead: int = 6, arrivals_now: bool = False) -> np.ndarray:
    """(N*F + 3,) float32: every region's features, row by row, then the time features."""
    return state_from_features(node_features(system, lookahead, arrivals_now=arrivals_now), time_features(system.city, system.t))


def state_from_features(feats: np.ndarray, context: np.ndarray) -> np.ndarray:
    """(..., N*F + 3) float32 global state from features (..., N, F) and time features (3,)."""
    *lead, n, f = feats.shape
    ctx = np.broadcast_to(context, (*lead, N_CONTEXT))
    return np.concatenate([feats.reshape(*lead, n * f), ctx], axis=-1).astype(np.float32)


def graph(system: FleetSystem, lookahead: int = 6, arrivals_now: bool = False) -> dict[str, np.ndarray]:
    """The city as a torch-geometric style graph of numpy arrays (``torch.from_numpy`` each one).

    ``x`` (N, F) float32 node features, ``edge_index`` (2, E) int64 source -> target,
    ``edge_attr`` (E, 2) float32: rebalancing time in steps and rebalancing cost of the edge.
    """
    return {"x": node_features(system, lookahead, arrivals_now=arrivals_now), **graph_edges(system.city)}


def graph_edges(city: City) -> dict[str, np.ndarray]:
    """``edge_index`` (2, E) int64 and ``edge_attr`` (E, 2) float32 of the city, shared by a batch."""
    edge_index = np.asarray(city.edge_index, dtype=np.int64)
    src, dst = edge_index
    edge_attr = np.stack([city.reb_time[src, dst], city.reb_cost[src, dst]], axis=1).astype(np.float32)
    return {"edge_index": edge_index.copy(), "edge_attr": edge_attr}
