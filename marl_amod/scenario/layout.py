"""Drawing positions for regions that come without coordinates."""

from __future__ import annotations

import numpy as np


def positions_from_travel_times(times: np.ndarray) -> np.ndarray:
    """(N, 2) positions by classical multidimensional scaling of symmetrised travel times.

    City JSON files give regions as ids only; MDS places regions so that drawn distances follow
    travel times, which is what a reader of a rebalancing map cares about.
    """
    n = times.shape[0]
    if n == 1:
        return np.zeros((1, 2))
    d = 0.5 * (times + times.T).astype(float)
    j = np.eye(n) - np.ones((n, n)) / n
    b = -0.5 * j @ (d**2) @ j
    vals, vecs = np.linalg.eigh(b)
    order = np.argsort(vals)[::-1][:2]
    coords = vecs[:, order] * np.sqrt(np.clip(vals[order], 1e-9, None))
    if coords.shape[1] < 2:
        coords = np.pad(coords, ((0, 0), (0, 2 - coords.shape[1])))
    return coords
