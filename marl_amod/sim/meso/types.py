"""The typed state of a SUMO episode: the fleet and the requests as records of aligned arrays.

M vehicles and K requests (K grows as requests are drawn, step by step). Every array of a record
has the same length; a vehicle or a request is an index into them. States are named
(:class:`VehicleState`, :class:`RequestState`) and stored as int8 codes, so whole-fleet questions
("idle vehicles of region i") are one vectorised comparison. Nothing here knows SUMO.
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from enum import IntEnum

import numpy as np


class VehicleState(IntEnum):
    """What a fleet vehicle is doing."""

    IDLE = 0  # waiting off-road at its edge, can be dispatched or rebalanced
    PICKUP = 1  # assigned to a request, driving to its pickup edge
    OCCUPIED = 2  # carrying a passenger to the drop-off edge
    REBALANCING = 3  # driving empty to a target region


class RequestState(IntEnum):
    """Where a request is in its life: upcoming -> open -> (assigned -> picked up | lost)."""

    OPEN = 0  # made and waiting to be dispatched
    ASSIGNED = 1  # a vehicle is on its way
    PICKED = 2  # the passenger is in (served)
    LOST = 3  # left unserved after its maximum wait (or at the end of the episode)
    UPCOMING = 4  # drawn for the current step, its request time not reached yet


@dataclass(eq=False)
class Fleet:
    """M vehicles; arrays aligned by vehicle index."""

    state: np.ndarray  # (M,) int8 VehicleState
    edge: np.ndarray  # (M,) int, the edge it is on (idle) or last stood on (busy)
    region: np.ndarray  # (M,) int, region of its edge when it last became idle
    target: np.ndarray  # (M,) int, the edge its current drive ends at
    dest: np.ndarray  # (M,) int, region where it becomes idle again (== region while idle)
    origin: np.ndarray  # (M,) int, region its current trip or move left (its busy time is booked there)
    request: np.ndarray  # (M,) int, request it is serving, -1 none
    eta: np.ndarray  # (M,) float, seconds since step 0 when it is expected to be idle again
    since: np.ndarray  # (M,) float, seconds since step 0 when it became busy

    @classmethod
    def idle_at(cls, edges: np.ndarray, regions: np.ndarray) -> Fleet:
        """Every vehicle idle on ``edges`` (M,) in ``regions`` (M,)."""
        m = len(edges)
        regions = np.asarray(regions, dtype=np.int64)
        return cls(
            state=np.full(m, VehicleState.IDLE, dtype=np.int8),
            edge=np.asarray(edges, dtype=np.int64),
            region=regions.copy(),
            target=np.zeros(m, dtype=np.int64),
            dest=regions.copy(),
            origin=regions.copy(),
            request=np.full(m, -1, dtype=np.int64),
            eta=np.zeros(m),
            since=np.zeros(m),
        )

    def __len__(self) -> int:
        return len(self.state)

    def idle_in(self, region: int) -> np.ndarray:
        """Indices of the idle vehicles of ``region``, in index order."""
        return np.flatnonzero((self.state == VehicleState.IDLE) & (self.region == region))

    def idle_per_region(self, n: int) -> np.ndarray:
        """(n,) idle vehicles per region."""
        return np.bincount(self.region[self.state == VehicleState.IDLE], minlength=n).astype(np.int64)

    def busy(self) -> np.ndarray:
        """Indices of the vehicles that are not idle."""
        return np.flatnonzero(self.state != VehicleState.IDLE)


@dataclass(eq=False)
class Requests:
    """K requests in the order they were drawn (step by step, by request time within a step)."""

    origin: np.ndarray  # (K,) int, origin region
    dest: np.ndarray  # (K,) int, destination region
    origin_edge: np.ndarray  # (K,) int, pickup edge
    dest_edge: np.ndarray  # (K,) int, drop-off edge (never the pickup edge)
    time: np.ndarray  # (K,) float, request time in seconds since step 0
    state: np.ndarray  # (K,) int8 RequestState

    @classmethod
    def empty(cls) -> Requests:
        z = np.zeros(0, dtype=np.int64)
        return cls(z, z.copy(), z.copy(), z.copy(), np.zeros(0), np.zeros(0, dtype=np.int8))

    def __len__(self) -> int:
        return len(self.state)

    def append(self, other: Requests) -> None:
        """Add ``other``'s requests after these (their indices continue from ``len(self)``)."""
        for f in fields(self):
            setattr(self, f.name, np.concatenate([getattr(self, f.name), getattr(other, f.name)]))

    def in_state(self, state: RequestState) -> np.ndarray:
        """Indices of the requests in ``state``, oldest drawn first."""
        return np.flatnonzero(self.state == state)

    def od_counts(self, k: np.ndarray, n: int) -> np.ndarray:
        """(n, n) how many of the requests ``k`` go from region i to region j."""
        out = np.zeros((n, n), dtype=np.int64)
        np.add.at(out, (self.origin[k], self.dest[k]), 1)
        return out
