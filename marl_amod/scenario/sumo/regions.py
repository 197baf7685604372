"""Regions of a road network: k-means on edge midpoints, and region-level travel times.

Edge midpoints rather than junctions are clustered because edges are what requests and
vehicles live on: every edge belongs to exactly one region, and a region's share of edges is
the activity proxy of the demand model. k-means (Lloyd, k-means++ start, seeded) gives compact
regions of similar extent, as the paper's 10 regions of about 2 km^2.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from marl_amod.scenario.sumo.network import RoadNetwork

TRAVEL_SAMPLES = 12  # sampled edges per region that region-to-region travel times average over


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


def sample_edges(of_edge: np.ndarray, n_regions: int, samples: int, seed: int) -> list[np.ndarray]:
    """Up to ``samples`` random edges of every region (seeded): the points region times average over."""
    rng = np.random.default_rng(seed)
    members = [np.flatnonzero(of_edge == r) for r in range(n_regions)]
    return [rng.choice(m, size=min(samples, len(m)), replace=False) for m in members]


def region_means(picks: list[np.ndarray], table: np.ndarray) -> np.ndarray:
    """(N, N) mean of ``table`` (sum(picks), E) rows from region i's picks to region j's picks,
    leaving out same-edge pairs (a trip needs distinct origin and destination edges)."""
    src = np.concatenate(picks)
    owner = np.repeat(np.arange(len(picks)), [len(p) for p in picks])
    sub = table[:, src]  # (P, P) pick-to-pick times
    off = ~np.equal.outer(src, src)
    n = len(picks)
    sums = np.zeros((n, n))
    counts = np.zeros((n, n))
    np.add.at(sums, (owner[:, None], owner[None, :]), np.where(off, sub, 0.0))
    np.add.at(counts, (owner[:, None], owner[None, :]), off)
    return sums / counts


def region_travel(net: RoadNetwork, picks: list[np.ndarray], edge_time: np.ndarray | None = None) -> np.ndarray:
    """(N, N) mean seconds between sampled edges of region i and of region j: one Dijkstra per
    sampled edge, O(N * samples), never O(N^2) routing calls."""
    return region_means(picks, net.travel_times(np.concatenate(picks), edge_time))


def partition(net: RoadNetwork, n_regions: int, seed: int = 0, samples: int = TRAVEL_SAMPLES) -> Regions:
    """Cluster the network into regions, with free-flow travel statistics between them."""
    labels, centers = kmeans(net.midpoint, n_regions, seed)
    picks = sample_edges(labels, n_regions, samples, seed)
    coo = net.successors.tocoo()
    pairs = np.unique(np.stack([labels[coo.row], labels[coo.col]]), axis=1)
    return Regions(
        of_edge=labels,
        centers=centers,
        travel_s=region_travel(net, picks),
        distance_m=region_means(picks, net.distances(np.concatenate(picks))),
        adjacency=pairs[:, pairs[0] != pairs[1]],
    )
