"""The bookkeeping of a SUMO episode as pure numpy on the typed records: no SUMO in here.

The SUMO driver (:mod:`marl_amod.sim.meso.sumo_sim`) decides *when* things happen (a request
time passes, a vehicle arrives); these functions say *what changes* in the fleet and request
records and in the episode totals, so tests drive them on hand-made records.

Every function that books money, demand or time adds to an
:class:`~marl_amod.sim.macro.EpisodeTotals` ((N,) arrays); several items of one call are added
in index order (``np.add.at``), exactly as one at a time would.
"""

from __future__ import annotations

import numpy as np

from marl_amod.sim.macro import EpisodeTotals
from marl_amod.sim.meso.types import Fleet, Requests, RequestState, VehicleState

_EPS_S = 1e-6  # clock tolerance in seconds: a request made "now" is revealed now


# ---------------------------------------------------------------------- drawing
def place_fleet(initial: np.ndarray, members: list[np.ndarray], rng: np.random.Generator) -> Fleet:
    """Every vehicle idle on a random edge of its initial region; ``initial`` (N,) vehicles per region."""
    regions = np.repeat(np.arange(len(initial)), initial)
    edges = np.array([rng.choice(members[r]) for r in regions], dtype=np.int64)
    return Fleet.idle_at(edges, regions)


def draw_requests(counts: np.ndarray, members: list[np.ndarray], t: int, step_s: float, rng: np.random.Generator) -> Requests:
    """The requests of step t from its drawn OD counts (N, N): random distinct pickup and drop-off
    edges in their regions, request times uniform over the step (all at 0 for step 0), sorted by
    time; all upcoming until :func:`reveal` sees their time pass."""
    pi, pj = np.nonzero(counts)
    o, d = np.repeat(pi, counts[pi, pj]), np.repeat(pj, counts[pi, pj])
    oe = np.array([rng.choice(members[i]) for i in o], dtype=np.int64)
    de = np.array([rng.choice(members[j]) for j in d], dtype=np.int64)
    for k in np.flatnonzero(oe == de):  # a trip needs two distinct edges
        while de[k] == oe[k]:
            de[k] = rng.choice(members[d[k]])
    when = np.zeros(len(o)) if t == 0 else (t - rng.random(len(o))) * step_s
    order = np.argsort(when, kind="stable")
    return Requests(
        origin=o[order], dest=d[order], origin_edge=oe[order], dest_edge=de[order], time=when[order],
        state=np.full(len(o), RequestState.UPCOMING, dtype=np.int8),
    )  # fmt: skip


# ---------------------------------------------------------------------- requests
def reveal(requests: Requests, now: float, totals: EpisodeTotals) -> np.ndarray:
    """Upcoming requests whose time has come open and count as demand; returns their indices."""
    new = np.flatnonzero((requests.state == RequestState.UPCOMING) & (requests.time <= now + _EPS_S))
    requests.state[new] = RequestState.OPEN
    totals.demand += np.bincount(requests.origin[new], minlength=len(totals.demand))
    return new


def expire(requests: Requests, cutoff: float, totals: EpisodeTotals) -> np.ndarray:
    """Open requests made before ``cutoff`` leave unserved; returns their indices."""
    gone = np.flatnonzero((requests.state == RequestState.OPEN) & (requests.time < cutoff))
    requests.state[gone] = RequestState.LOST
    totals.lost += np.bincount(requests.origin[gone], minlength=len(totals.lost))
    return gone


def still_open_at(requests: Requests, when: float, max_wait_s: float) -> np.ndarray:
    """Open requests that will not have left by ``when`` (seconds since step 0)."""
    k = requests.in_state(RequestState.OPEN)
    return k[requests.time[k] + max_wait_s >= when]


# ---------------------------------------------------------------------- matching
def nearest(pool: np.ndarray, pool_xy: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Greedy nearest members of ``pool`` (positions ``pool_xy`` (len(pool), 2)) to ``points``
    (P, 2), in the order of the points; each member used once."""
    if len(points) > len(pool):
        raise ValueError(f"asked for {len(points)} vehicles from a pool of {len(pool)}")
    d = np.linalg.norm(pool_xy[None] - points[:, None], axis=2)  # (P, len(pool))
    out = np.empty(len(points), dtype=np.int64)
    for p in range(len(points)):
        k = int(np.argmin(d[p]))
        out[p] = pool[k]
        d[:, k] = np.inf
    return out


def match_dispatch(fleet: Fleet, requests: Requests, x: np.ndarray, edge_xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(requests, vehicles) that serve passenger flows x (N, N), paired in the order they go:
    region by region, the oldest open i->j requests (x[i, j] of them), oldest first, each with
    the idle vehicle of region i nearest to its pickup edge. ``edge_xy`` (E, 2) edge positions."""
    open_k = requests.in_state(RequestState.OPEN)
    ks, vs = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for i in np.flatnonzero(x.sum(axis=1)):
        from_i = open_k[requests.origin[open_k] == i]
        chosen = np.concatenate([from_i[requests.dest[from_i] == j][: x[i, j]] for j in np.flatnonzero(x[i])])
        chosen = chosen[np.argsort(requests.time[chosen], kind="stable")]  # oldest first
        pool = fleet.idle_in(i)
        ks.append(chosen)
        vs.append(nearest(pool, edge_xy[fleet.edge[pool]], edge_xy[requests.origin_edge[chosen]]))
    return np.concatenate(ks), np.concatenate(vs)


def match_rebalancing(
    fleet: Fleet, y: np.ndarray, edge_xy: np.ndarray, centers: np.ndarray, members: list[np.ndarray], rng: np.random.Generator
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vehicles, from regions, to regions, target edges) moving rebalancing flows y (N, N), pair
    by pair: the idle vehicles of i nearest to j's centre (``centers`` (N, 2)), each to a random
    edge of j."""
    taken = np.zeros(len(fleet), dtype=bool)
    cars, dest, edges = [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)], [np.zeros(0, dtype=np.int64)]
    for i, j in zip(*np.nonzero(y), strict=True):
        pool = fleet.idle_in(i)
        pool = pool[~taken[pool]]
        chosen = nearest(pool, edge_xy[fleet.edge[pool]], np.repeat(centers[j][None], y[i, j], axis=0))
        taken[chosen] = True
        cars.append(chosen)
        dest.append(np.full(len(chosen), j, dtype=np.int64))
        edges.append(np.asarray(rng.choice(members[j], size=len(chosen)), dtype=np.int64))
    return np.concatenate(cars), np.concatenate(dest), np.concatenate(edges)


# ---------------------------------------------------------------------- vehicles
def go_busy(fleet: Fleet, v: np.ndarray, dest: np.ndarray, state: VehicleState, now: float, eta: np.ndarray | float) -> None:
    """Idle vehicles ``v`` leave their region for ``dest``: their busy time starts now."""
    fleet.origin[v] = fleet.region[v]
    fleet.dest[v] = dest
    fleet.state[v] = state
    fleet.since[v] = now
    fleet.eta[v] = eta


def assign(fleet: Fleet, requests: Requests, k: np.ndarray, v: np.ndarray, now: float, eta: np.ndarray) -> None:
    """Vehicles ``v`` take requests ``k`` (pairwise) and head for the pickups; ``eta`` (len(k),)
    when each is expected to be idle again at the drop-off."""
    requests.state[k] = RequestState.ASSIGNED
    fleet.request[v] = k
    go_busy(fleet, v, requests.dest[k], VehicleState.PICKUP, now, eta)


def pick_up(fleet: Fleet, requests: Requests, v: np.ndarray, now: float, totals: EpisodeTotals) -> None:
    """Vehicles ``v`` reached their passengers: the requests are served, their waits booked."""
    k = fleet.request[v]
    requests.state[k] = RequestState.PICKED
    np.add.at(totals.wait_minutes, requests.origin[k], (now - requests.time[k]) / 60.0)
    fleet.state[v] = VehicleState.OCCUPIED


def become_idle(fleet: Fleet, v: np.ndarray, now: float, step_s: float, of_edge: np.ndarray, totals: EpisodeTotals) -> None:
    """Vehicles ``v`` finished a trip or a move on their edge: their busy time is booked to the
    region they left; they are idle in their edge's region."""
    np.add.at(totals.busy_vehicle_steps, fleet.origin[v], (now - fleet.since[v]) / step_s)
    fleet.request[v] = -1
    fleet.state[v] = VehicleState.IDLE
    fleet.region[v] = of_edge[fleet.edge[v]]


def arrive(
    fleet: Fleet, requests: Requests, v: np.ndarray, now: float, step_s: float, of_edge: np.ndarray, totals: EpisodeTotals
) -> np.ndarray:
    """The drives of vehicles ``v`` ended at their target edges. Those driving to a pickup take
    their passenger in (returned: they drive on to the drop-off); the others become idle there."""
    fleet.edge[v] = fleet.target[v]
    picking = fleet.state[v] == VehicleState.PICKUP
    pick_up(fleet, requests, v[picking], now, totals)
    become_idle(fleet, v[~picking], now, step_s, of_edge, totals)
    return v[picking]


def book_unfinished(fleet: Fleet, requests: Requests, now: float, step_s: float, totals: EpisodeTotals) -> None:
    """End of episode: waits of assigned passengers not yet picked up, and busy time so far
    (plus what remains of the current step) of vehicles still driving, are booked."""
    waiting = requests.in_state(RequestState.ASSIGNED)
    np.add.at(totals.wait_minutes, requests.origin[waiting], (now - requests.time[waiting]) / 60.0)
    busy = fleet.busy()
    tail = np.minimum(np.maximum(fleet.eta[busy] - now, 0.0), step_s)
    np.add.at(totals.busy_vehicle_steps, fleet.origin[busy], (now - fleet.since[busy] + tail) / step_s)
    fleet.since[busy] = now


def expected_arrivals(fleet: Fleet, t: int, n_steps: int, n: int, step_s: float) -> np.ndarray:
    """(S + 1, N) busy vehicles expected to become idle after step k, by destination region
    (as MacroSim's arrivals; overdue vehicles count in the current step t)."""
    out = np.zeros((n_steps + 1, n), dtype=np.int64)
    busy = fleet.busy()
    step = np.ceil(fleet.eta[busy] / step_s).astype(np.int64) - 1
    np.add.at(out, (np.clip(step, t, n_steps), fleet.dest[busy]), 1)
    return out
