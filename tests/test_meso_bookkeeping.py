"""The SUMO simulator's bookkeeping on hand-made fleet and request records: no SUMO needed.

The driver (``MesoSim``) decides when a request time passes or a vehicle arrives; these tests
play the driver and check what changes: request states and demand/lost counts, who serves whom,
waits and busy time booked to the right regions, and conservation over a whole random episode.
"""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.sim.macro import EpisodeTotals
from marl_amod.sim.meso import bookkeeping as bk
from marl_amod.sim.meso.types import Fleet, Requests, RequestState, VehicleState

# a toy network: 6 edges on a line, x = 0..5 km; region 0 = edges 0-2, region 1 = edges 3-5
EDGE_XY = np.stack([np.arange(6) * 1000.0, np.zeros(6)], axis=1)
OF_EDGE = np.array([0, 0, 0, 1, 1, 1])
MEMBERS = [np.array([0, 1, 2]), np.array([3, 4, 5])]
CENTERS = np.array([[1000.0, 0.0], [4000.0, 0.0]])
STEP_S = 60.0


def _requests(origin, dest, oe, de, time, state=RequestState.UPCOMING) -> Requests:
    n = len(origin)
    return Requests(
        origin=np.array(origin), dest=np.array(dest), origin_edge=np.array(oe), dest_edge=np.array(de),
        time=np.array(time, dtype=float), state=np.full(n, state, dtype=np.int8),
    )  # fmt: skip


def test_reveal_opens_requests_whose_time_has_come_and_counts_them_once():
    req = _requests([0, 1, 0], [1, 0, 1], [0, 3, 1], [4, 0, 5], [0.0, 30.0, 90.0])
    tot = EpisodeTotals.zeros(2)
    np.testing.assert_array_equal(bk.reveal(req, 30.0, tot), [0, 1])
    np.testing.assert_array_equal(tot.demand, [1, 1])
    assert bk.reveal(req, 30.0, tot).size == 0 and tot.demand.sum() == 2  # not counted twice
    assert req.state[2] == RequestState.UPCOMING
    np.testing.assert_array_equal(bk.reveal(req, 90.0, tot), [2])
    np.testing.assert_array_equal(tot.demand, [2, 1])


def test_expire_loses_only_open_requests_older_than_the_cutoff():
    req = _requests([0, 1, 0, 1], [1, 0, 1, 0], [0, 3, 1, 4], [4, 0, 5, 1], [0.0, 10.0, 20.0, 0.0], RequestState.OPEN)
    req.state[3] = RequestState.ASSIGNED  # on its way: never lost
    tot = EpisodeTotals.zeros(2)
    np.testing.assert_array_equal(bk.expire(req, 15.0, tot), [0, 1])
    np.testing.assert_array_equal(req.state, [RequestState.LOST, RequestState.LOST, RequestState.OPEN, RequestState.ASSIGNED])
    np.testing.assert_array_equal(tot.lost, [1, 1])
    np.testing.assert_array_equal(bk.still_open_at(req, 100.0, max_wait_s=60.0), [])  # request 2 leaves at 80 s
    np.testing.assert_array_equal(bk.still_open_at(req, 80.0, max_wait_s=60.0), [2])


def test_dispatch_serves_the_oldest_requests_with_the_nearest_idle_vehicles():
    fleet = Fleet.idle_at(edges=np.array([0, 2, 1, 4]), regions=np.array([0, 0, 0, 1]))
    # open requests in the order drawn (by time): 0->1 at edge 2, 0->0 at edge 0, 0->1 at edge 1, 1->0
    req = _requests([0, 0, 0, 1], [1, 0, 1, 0], [2, 0, 1, 3], [3, 1, 5, 0], [5.0, 10.0, 30.0, 40.0], RequestState.OPEN)
    x = np.array([[1, 1], [0, 0]])
    k, v = bk.match_dispatch(fleet, req, x, EDGE_XY)
    np.testing.assert_array_equal(k, [0, 1])  # the oldest 0->1 (not request 2) and the 0->0, oldest first
    np.testing.assert_array_equal(v, [1, 0])  # vehicle 1 stands on edge 2, vehicle 0 on edge 0
    bk.assign(fleet, req, k, v, now=40.0, eta=np.array([200.0, 300.0]))
    np.testing.assert_array_equal(req.state, [RequestState.ASSIGNED, RequestState.ASSIGNED, RequestState.OPEN, RequestState.OPEN])
    np.testing.assert_array_equal(fleet.request, [1, 0, -1, -1])
    np.testing.assert_array_equal(fleet.state, [VehicleState.PICKUP, VehicleState.PICKUP, VehicleState.IDLE, VehicleState.IDLE])
    np.testing.assert_array_equal(fleet.dest[[1, 0]], [1, 0])
    np.testing.assert_array_equal(fleet.eta[[1, 0]], [200.0, 300.0])
    np.testing.assert_array_equal(fleet.idle_per_region(2), [1, 1])


def test_a_trip_books_the_wait_at_pickup_and_the_busy_time_at_drop_off():
    fleet = Fleet.idle_at(edges=np.array([0]), regions=np.array([0]))
    req = _requests([0], [1], [2], [5], [10.0], RequestState.OPEN)
    tot = EpisodeTotals.zeros(2)
    bk.assign(fleet, req, np.array([0]), np.array([0]), now=20.0, eta=np.array([500.0]))
    fleet.target[0] = 2  # the driver sends it to the pickup edge
    picked = bk.arrive(fleet, req, np.array([0]), 80.0, STEP_S, OF_EDGE, tot)
    np.testing.assert_array_equal(picked, [0])  # it drives on to the drop-off
    assert req.state[0] == RequestState.PICKED and fleet.state[0] == VehicleState.OCCUPIED
    np.testing.assert_allclose(tot.wait_minutes, [(80.0 - 10.0) / 60.0, 0.0])  # booked to the origin region
    fleet.target[0] = 5
    assert bk.arrive(fleet, req, np.array([0]), 200.0, STEP_S, OF_EDGE, tot).size == 0
    assert fleet.state[0] == VehicleState.IDLE and fleet.region[0] == 1 and fleet.edge[0] == 5 and fleet.request[0] == -1
    np.testing.assert_allclose(tot.busy_vehicle_steps, [(200.0 - 20.0) / STEP_S, 0.0])  # to the region it left


def test_rebalancing_moves_distinct_vehicles_nearest_to_the_target_centre():
    fleet = Fleet.idle_at(edges=np.array([0, 2, 1, 3]), regions=np.array([0, 0, 0, 1]))
    y = np.array([[0, 2], [1, 0]])
    rng = np.random.default_rng(0)
    v, dest, edges = bk.match_rebalancing(fleet, y, EDGE_XY, CENTERS, MEMBERS, rng)
    np.testing.assert_array_equal(v, [1, 2, 3])  # edges 2 and 1 are nearest to region 1's centre
    np.testing.assert_array_equal(dest, [1, 1, 0])
    assert all(OF_EDGE[e] == d for e, d in zip(edges, dest, strict=True))
    bk.go_busy(fleet, v, dest, VehicleState.REBALANCING, 0.0, 60.0)
    np.testing.assert_array_equal(fleet.origin[v], [0, 0, 1])
    np.testing.assert_array_equal(fleet.idle_per_region(2), [1, 0])
    with pytest.raises(ValueError, match="pool"):
        bk.match_rebalancing(fleet, np.array([[0, 2], [0, 0]]), EDGE_XY, CENTERS, MEMBERS, rng)


def test_end_of_episode_books_waits_of_assigned_requests_and_busy_time_so_far():
    fleet = Fleet.idle_at(edges=np.array([0, 3]), regions=np.array([0, 1]))
    req = _requests([0], [1], [2], [5], [0.0], RequestState.OPEN)
    bk.assign(fleet, req, np.array([0]), np.array([0]), now=30.0, eta=np.array([1000.0]))
    tot = EpisodeTotals.zeros(2)
    bk.book_unfinished(fleet, req, 90.0, STEP_S, tot)
    np.testing.assert_allclose(tot.wait_minutes, [1.5, 0.0])
    np.testing.assert_allclose(tot.busy_vehicle_steps, [(90.0 - 30.0 + STEP_S) / STEP_S, 0.0])  # plus the step's rest
    assert fleet.since[0] == 90.0


def test_expected_arrivals_count_busy_vehicles_at_their_destination_and_step():
    fleet = Fleet.idle_at(edges=np.array([0, 1, 3]), regions=np.array([0, 0, 1]))
    bk.go_busy(fleet, np.array([0, 1]), np.array([1, 0]), VehicleState.REBALANCING, 0.0, np.array([130.0, 10.0]))
    out = bk.expected_arrivals(fleet, t=1, n_steps=5, n=2, step_s=STEP_S)
    assert out.shape == (6, 2) and out.sum() == 2
    assert out[2, 1] == 1  # eta 130 s is in step 3 -> idle after step 2
    assert out[1, 0] == 1  # overdue (eta 10 s): counted at the current step


def test_drawn_requests_have_distinct_edges_in_their_regions_and_times_in_their_step():
    counts = np.array([[2, 3], [1, 0]])
    req = bk.draw_requests(counts, MEMBERS, t=4, step_s=STEP_S, rng=np.random.default_rng(1))
    assert len(req) == 6 and np.all(req.state == RequestState.UPCOMING)
    np.testing.assert_array_equal(req.od_counts(np.arange(6), 2), counts)
    assert np.all(OF_EDGE[req.origin_edge] == req.origin) and np.all(OF_EDGE[req.dest_edge] == req.dest)
    assert np.all(req.origin_edge != req.dest_edge)
    assert np.all((req.time > 3 * STEP_S) & (req.time <= 4 * STEP_S)) and np.all(np.diff(req.time) >= 0)
    fleet = bk.place_fleet(np.array([3, 1]), MEMBERS, np.random.default_rng(2))
    np.testing.assert_array_equal(fleet.idle_per_region(2), [3, 1])
    assert np.all(OF_EDGE[fleet.edge] == fleet.region)


def test_a_random_episode_of_bookkeeping_conserves_vehicles_and_accounts_for_every_request():
    """Play the driver with random demand, dispatch and arrivals; check the books every step."""
    rng = np.random.default_rng(7)
    n, m, steps, max_wait = 2, 5, 30, 2 * STEP_S
    fleet = bk.place_fleet(np.array([3, 2]), MEMBERS, rng)
    req, tot = Requests.empty(), EpisodeTotals.zeros(n)
    served = pickups = 0
    for t in range(steps):
        now = t * STEP_S
        req.append(bk.draw_requests(rng.poisson(0.8, size=(n, n)), MEMBERS, t, STEP_S, rng))
        bk.reveal(req, now, tot)
        bk.expire(req, now - max_wait, tot)
        # vehicles whose drive is due arrive at their target edges (pickups drive on to the drop-off)
        due = np.flatnonzero((fleet.state != VehicleState.IDLE) & (fleet.eta <= now))
        picked = bk.arrive(fleet, req, due, now, STEP_S, OF_EDGE, tot)
        pickups += len(picked)
        fleet.target[picked] = req.dest_edge[fleet.request[picked]]
        fleet.eta[picked] = now + STEP_S
        # dispatch as much as idle vehicles allow, origin by origin
        open_now = req.od_counts(req.in_state(RequestState.OPEN), n)
        x = np.zeros((n, n), dtype=np.int64)
        for i, left in enumerate(fleet.idle_per_region(n)):
            for j in range(n):
                x[i, j] = min(open_now[i, j], left)
                left -= x[i, j]
        k, v = bk.match_dispatch(fleet, req, x, EDGE_XY)
        bk.assign(fleet, req, k, v, now, now + 2 * STEP_S)
        fleet.target[v] = req.origin_edge[k]
        fleet.eta[v] = now + STEP_S
        served += len(k)
        states = np.bincount(fleet.state, minlength=4)
        assert states.sum() == m and len(fleet) == m  # no vehicle created or lost
        assert np.all(fleet.request[fleet.state == VehicleState.IDLE] == -1)
        n_open = len(req.in_state(RequestState.OPEN))
        assert tot.demand.sum() == served + tot.lost.sum() + n_open
        assert np.sum(req.state == RequestState.PICKED) == pickups  # every pickup served one request
    assert served > 0 and tot.lost.sum() > 0 and tot.busy_vehicle_steps.sum() > 0
