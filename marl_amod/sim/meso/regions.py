"""Regions of a road network: k-means on edge midpoints, and region-level travel times.

Edge midpoints rather than junctions are clustered because edges are what requests and
vehicles live on: every edge belongs to exactly one region, and a region's share of edges is
the activity proxy of the demand model. k-means (Lloyd, k-means++ start, seeded) gives compact
regions of similar extent, as the paper's 10 regions of about 2 km^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marl_amod.sim.meso.network import RoadNetwork


def kmeans(points: np.ndarray, k: int, seed: int = 0, iters: int = 50) -> tuple[np.ndarray, np.ndarray]:
    """(labels (P,), centers (k, 2)) of ``points`` (P, 2); deterministic for a seed."""
    if not 2 <= k <= len(points):
        raise ValueError(f"need 2 <= regions <= {len(points)} edges, got {k}")
    rng = np.random.default_rng(seed)
    centers = points[[rng.integers(len(points))]]
    for _ in range(k - 1):  # k-means++: spread the starting centres
        d2 = ((points[:, None, :] - centers[None]) ** 2).sum(-1).min(axis=1)
        centers = np.vstack([centers, points[rng.choice(len(points), p=d2 / d2.sum())]])
    labels = np.zeros(len(points), dtype=np.int64)
    for _ in range(iters):
        labels = ((points[:, None, :] - centers[None]) ** 2).sum(-1).argmin(axis=1)
        new = np.array([points[labels == c].mean(axis=0) if np.any(labels == c) else centers[c] for c in range(k)])
        if np.allclose(new, centers):
            break
        centers = new
    # number regions west-to-east, south-to-north, so names do not depend on the start
    order = np.lexsort((centers[:, 0].round(-2), centers[:, 1].round(-2)))
    rank = np.empty(k, dtype=np.int64)
    rank[order] = np.arange(k)
    return rank[labels], centers[order]


@dataclass(frozen=True, eq=False)
class Regions:
    """A partition of a network's edges into N regions, with region-level travel statistics."""

    of_edge: np.ndarray  # (E,) region of every edge
    centers: np.ndarray  # (N, 2) metres
    travel_s: np.ndarray  # (N, N) mean free-flow seconds between edges of region i and of region j
    distance_m: np.ndarray  # (N, N) mean route length in metres between edges of i and of j
    adjacency: np.ndarray  # (2, E') directed region pairs joined by a road (no self loops)

    @property
    def n(self) -> int:
        return len(self.centers)

    def members(self, region: int) -> np.ndarray:
        return np.flatnonzero(self.of_edge == region)


def partition(net: RoadNetwork, n_regions: int, seed: int = 0, samples: int = 12) -> Regions:
    """Cluster the network into regions; travel statistics from ``samples`` random edges per
    region (one Dijkstra per sampled edge: O(N * samples), never O(N^2) routing calls)."""
    labels, centers = kmeans(net.midpoint, n_regions, seed)
    rng = np.random.default_rng(seed)
    picks = [rng.choice(np.flatnonzero(labels == r), size=min(samples, int(np.sum(labels == r))), replace=False) for r in range(n_regions)]
    src = np.concatenate(picks)
    owner = np.repeat(np.arange(n_regions), [len(p) for p in picks])
    times, dists = net.travel_times(src), net.distances(src)
    travel = np.zeros((n_regions, n_regions))
    distance = np.zeros((n_regions, n_regions))
    for j, p in enumerate(picks):
        t = times[:, p]
        d = dists[:, p]
        for i in range(n_regions):
            rows = owner == i
            off = ~np.equal.outer(src[rows], p)  # a trip needs distinct origin and destination edges
            travel[i, j] = t[rows][off].mean()
            distance[i, j] = d[rows][off].mean()
    coo = net.successors.tocoo()
    pairs = np.unique(np.stack([labels[coo.row], labels[coo.col]]), axis=1)
    adjacency = pairs[:, pairs[0] != pairs[1]]
    return Regions(of_edge=labels, centers=centers, travel_s=travel, distance_m=distance, adjacency=adjacency)
