"""The mesoscopic simulator: the fleet drives on real roads in SUMO, same interface as MacroSim.

Region-level flows from the coordinator become concrete moves here:

- requests are drawn per control step from the city's OD rates (one Poisson draw per pair and
  step, as in the macro model), each with an origin and a destination edge in its regions and
  a request time inside the step; a request not dispatched within ``max_wait_min`` leaves;
- dispatch x[i, j] serves the oldest open i->j requests, each with the nearest idle vehicle of
  region i; the vehicle drives to the pickup edge (the wait ends there), then to the drop-off;
- rebalancing y[i, j] sends the idle vehicles of i nearest to j's centre to random edges of j.

This module is the SUMO driver: it decides when things happen (SUMO's clock, arrivals read back
from SUMO) and starts the drives. The state is typed (:mod:`~marl_amod.sim.meso.types`: a
:class:`Fleet` and :class:`Requests` record) and what changes in it is pure numpy
(:mod:`~marl_amod.sim.meso.bookkeeping`).

Mechanism (the simulator kind "meso"; kind "taxi" uses SUMO's taxi device instead, see
:mod:`marl_amod.sim.meso.taxi_sim`): every driving leg is a plain SUMO vehicle added with a
route that costs what SUMO's router says (from :mod:`~marl_amod.sim.meso.routing`, or SUMO's
``findRoute`` with ``SumoOptions.sumo_router``) of at least two edges (single-edge routes vanish in meso); its arrival is
read back from SUMO each simulation step. Idle vehicles wait off-road at their last edge (parked
meso vehicles cannot be re-routed anyway), so the fleet is conserved by construction and checked
against SUMO's own vehicle count. Travel times, and so vehicle availability and waits, come from
SUMO's mesoscopic queues, not from a table. Fares and trip costs are the city's region-level
estimates, the same numbers the coordinator optimises, so rewards are comparable with the macro
model.

A run started by ``reset`` is ended by ``close`` (the TraCI ``sumo`` process exits; the libsumo
simulation is unloaded), or, if the simulator is dropped without ``close``, when it is garbage
collected or the interpreter exits.
"""

from __future__ import annotations

import dataclasses
import weakref
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.scenario.simspec import SumoOptions
from marl_amod.scenario.sumo.network import read_network
from marl_amod.scenario.sumo.regions import TRAVEL_SAMPLES, region_travel, sample_edges
from marl_amod.scenario.types import City
from marl_amod.sim.flows import as_flows, check_dispatch, check_rebalance
from marl_amod.sim.macro import EpisodeTotals
from marl_amod.sim.meso import bookkeeping as bk
from marl_amod.sim.meso import engine
from marl_amod.sim.meso.options import dispatch_rounds, sumo_args
from marl_amod.sim.meso.routing import EdgeRouter, router_for
from marl_amod.sim.meso.types import Fleet, Requests, RequestState, VehicleState

FLEET_PREFIX = "fleet"  # SUMO ids of the fleet's legs; other traffic has other ids


class MesoSim:
    """One episode of a city in SUMO; reset with a random generator, then apply flows step by step."""

    taxi_device = False  # the fleet as one SUMO vehicle per driving leg

    def __init__(self, city: City, options: SumoOptions, *, max_wait_min: float = 10.0) -> None:
        if max_wait_min < 0:
            raise ValueError(f"max_wait_min must be >= 0, got {max_wait_min}")
        self.city = city  # the region view; its travel times follow SUMO's state during an episode
        self.base_city = city
        self.options = options
        self.max_wait_s = 60.0 * max_wait_min
        self.net = read_network(Path(options.net_file))
        n = city.n_regions
        if len(options.of_edge) != self.net.n_edges or options.of_edge.max() >= n:
            raise ValueError(f"the region map does not fit {options.net_file} with {n} regions")
        self.members = [np.flatnonzero(options.of_edge == r) for r in range(n)]
        self.region_center = np.array([self.net.midpoint[m].mean(axis=0) for m in self.members])  # (N, 2)
        self.step_s = 60.0 * city.tstep
        self.dispatch_rounds = dispatch_rounds(options, city.tstep)
        self._round = 0  # dispatch rounds already run inside the current control step
        self._picks = sample_edges(options.of_edge, n, TRAVEL_SAMPLES, options.region_seed)
        self._api: Any = None
        self._router: EdgeRouter | None = None  # routes on SUMO's routing costs, set by reset
        self._run: object | None = None  # token of the SUMO run this simulator started
        self._closer: weakref.finalize | None = None  # ends that run if the simulator is dropped
        self._rng = np.random.default_rng(options.sumo_seed)  # replaced by reset()'s generator
        self.t = 0
        self.totals = EpisodeTotals.zeros(n)
        self.demand = np.zeros((city.n_steps, n, n), dtype=np.int64)
        self.last_dispatch = np.zeros((n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((n, n), dtype=np.int64)
        self.teleports = 0
        self._init_fleet()
        self.ride_requests = Requests.empty()

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: (re)start SUMO, place the fleet, draw every step's OD counts."""
        self.close()
        self._run = object()
        self._api = engine.start(self.sumo_args(), self.options.backend, owner=self._run)
        self._closer = weakref.finalize(self, engine.stop, self._api, self.options.backend, self._run)
        self._router = None if self.options.sumo_router else router_for(self._api, self.net, tuple(self.sumo_args()))
        self._rng = rng
        self.city = self.base_city
        n = self.city.n_regions
        self.t = 0
        self.totals = EpisodeTotals.zeros(n)
        self.teleports = 0
        self.last_dispatch = np.zeros((n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((n, n), dtype=np.int64)
        self.demand = rng.poisson(self.city.demand_rate).astype(np.int64)
        self._init_fleet()
        self.ride_requests = Requests.empty()
        self._place_fleet()
        self._round = 0
        self._new_requests(0)
        self._reveal()

    def close(self) -> None:
        """End the SUMO run this simulator started (also called by reset); it can be reset again."""
        if self._closer is not None:
            self._closer()  # runs engine.stop once
        self._closer = None
        self._api = None
        self._run = None

    def sumo_args(self) -> list[str]:
        """SUMO's command line (after the binary) for this simulator's runs."""
        return sumo_args(self.options, taxi_device=self.taxi_device)

    def __getstate__(self) -> dict:
        """Picklable: the live SUMO run is not copied; the copy needs a reset."""
        state = self.__dict__.copy()
        state.update(_api=None, _run=None, _closer=None, _router=None)
        return state

    @property
    def sumo(self) -> Any:
        """The live SUMO connection; libsumo runs one simulation per process, so a simulator
        whose run was replaced by another's says so instead of driving the wrong simulation."""
        if self._api is None:
            raise RuntimeError("the SUMO simulation is not running; call reset()")
        if self.options.backend == "libsumo" and not engine.owns(self._run):
            raise RuntimeError(
                "another MesoSim started libsumo in this process (one simulation per process); "
                "reset this one again, or use backend 'traci' to run several side by side"
            )
        return self._api

    @property
    def now(self) -> float:
        """Seconds since step 0 (the control clock; SUMO's is offset by ``begin_s``)."""
        return self.t * self.step_s if self._api is None else self.sumo.simulation.getTime() - self.options.begin_s

    @property
    def done(self) -> bool:
        return self.t >= self.city.horizon - 1

    @property
    def idle(self) -> np.ndarray:
        """(N,) idle vehicles per region."""
        return self.fleet.idle_per_region(self.city.n_regions)

    @property
    def arrivals(self) -> np.ndarray:
        """(S + 1, N) busy vehicles expected to become idle after step k (as in MacroSim)."""
        return bk.expected_arrivals(self.fleet, self.t, self.city.n_steps, self.city.n_regions, self.step_s)

    def requests(self) -> np.ndarray:
        """(N, N) open requests right now."""
        return self.ride_requests.od_counts(self.ride_requests.in_state(RequestState.OPEN), self.city.n_regions)

    def carried_over(self) -> np.ndarray:
        """(N, N) requests open now that will not have left by the next control step."""
        k = bk.still_open_at(self.ride_requests, (self.t + 1) * self.step_s, self.max_wait_s)
        return self.ride_requests.od_counts(k, self.city.n_regions)

    def vehicles(self) -> int:
        """Idle vehicles plus driving legs (every busy vehicle has exactly one); constant over an
        episode (conservation)."""
        return int(np.sum(self.fleet.state == VehicleState.IDLE) + len(self._leg))

    def vehicles_in_sumo(self) -> int:
        """Fleet vehicles SUMO itself holds (driving or waiting for insertion); with the legs
        added since SUMO's last step it equals the number of driving legs (advance checks it)."""
        api = self.sumo
        if not self.options.route_files:  # the fleet alone: SUMO's counts are ours
            return int(api.vehicle.getIDCount() + len(api.simulation.getPendingVehicles()))
        held = (*api.vehicle.getIDList(), *api.simulation.getPendingVehicles())
        return sum(vid.startswith(FLEET_PREFIX) for vid in held)

    # ------------------------------------------------------------------ transitions
    def apply_dispatch(self, x: np.ndarray, *, check: bool = True) -> float:
        """Serve open requests with passenger flows x (N, N); returns the step's dispatch profit
        (``check=False``: x is the coordinator's feasible int64 output, as in MacroSim)."""
        c, t, req = self.city, self.t, self.ride_requests
        if check:
            x = as_flows(x, c.n_regions, "dispatch")
            check_dispatch(x, self.requests(), self.idle)
        now = self.now
        k, v = bk.match_dispatch(self.fleet, req, x, self.net.midpoint)
        bk.assign(self.fleet, req, k, v, now, now + self.step_s * c.trip_time[t, req.origin[k], req.dest[k]])
        for kk, vv in zip(k, v, strict=True):
            self._send_to_pickup(vv, kk)
        self.totals.served += x.sum(axis=1)
        self.last_dispatch = self.last_dispatch + x  # summed over the step's dispatch rounds
        return self.totals.book_trips(x, c, t)

    def apply_rebalance(self, y: np.ndarray, *, check: bool = True) -> float:
        """Send idle vehicles y (N, N) to random edges of their target regions; returns the cost
        (``check`` as in :meth:`apply_dispatch`)."""
        c = self.city
        if check:
            y = as_flows(y, c.n_regions, "rebalancing")
            check_rebalance(y, self.idle)
        now = self.now
        v, dest, edges = bk.match_rebalancing(self.fleet, y, self.net.midpoint, self.region_center, self.members, self._rng)
        eta = now + self.step_s * c.reb_time[self.fleet.region[v], dest]
        bk.go_busy(self.fleet, v, dest, VehicleState.REBALANCING, now, eta)
        for vv, e in zip(v, edges, strict=True):
            self._send_rebalancing(vv, e)
        cost = (y * c.reb_cost).sum(axis=1)
        self.totals.rebalancing_cost += cost
        self.totals.rebalanced += y.sum(axis=1)
        self.last_rebalance = y
        return float(cost.sum())

    def advance_round(self) -> None:
        """Run SUMO to the next dispatch round inside the control step (``dispatch_rounds`` - 1
        of them per step): requests made meanwhile appear, those past their maximum wait leave."""
        if self._round >= self.dispatch_rounds - 1:
            raise RuntimeError(f"only {self.dispatch_rounds - 1} rounds run inside a control step")
        self._start_interval()
        self._round += 1
        self._run_until(self.t * self.step_s + self._round * self.step_s / self.dispatch_rounds)
        self._reveal()
        self._expire(self.now - self.max_wait_s)

    def advance(self) -> None:
        """Run SUMO to the next control step, handling pickups and arrivals as they happen;
        then travel times are refreshed, the step's requests appear and those past their
        maximum wait leave."""
        if self.done:
            raise RuntimeError("the episode is over; call reset()")
        self._start_interval()
        self._run_until((self.t + 1) * self.step_s)
        self.t += 1
        self._round = 0
        if self.options.refresh_travel_times:
            self._refresh_travel_times()
        self._reveal()
        self._expire(self.now - self.max_wait_s)
        self.last_rebalance = np.zeros_like(self.last_rebalance)

    def finish(self) -> None:
        """End of episode: open requests are lost; busy time and waits so far are booked."""
        self._expire(np.inf)
        bk.book_unfinished(self.fleet, self.ride_requests, self.now, self.step_s, self.totals)

    def _start_interval(self) -> None:
        """First move inside a control step: draw its requests (they appear over the step) and
        start summing its dispatch rounds."""
        if self._round == 0:
            self._new_requests(self.t + 1)
            self.last_dispatch = np.zeros_like(self.last_dispatch)

    def _run_until(self, when: float) -> None:
        """Step SUMO to ``when`` seconds after step 0, reacting to every arrival as it happens;
        then check that SUMO still holds every driving leg."""
        api = self.sumo
        end = self.options.begin_s + when
        while api.simulation.getTime() < end - 1e-6:
            api.simulationStep()
            self._after_sumo_step(api)
        self._check_fleet(api)

    def _after_sumo_step(self, api: Any) -> None:
        """React to what SUMO did in one simulation step: legs that arrived (a pickup drives on
        to the drop-off; any other arrival makes the vehicle idle)."""
        self._fresh.clear()
        ended = [self._leg.pop(vid) for vid in api.simulation.getArrivedIDList() if vid in self._leg]
        if ended:
            fleet, req = self.fleet, self.ride_requests
            picked = bk.arrive(fleet, req, np.array(ended), self.now, self.step_s, self.options.of_edge, self.totals)
            for v in picked:
                self._drive(v, req.dest_edge[fleet.request[v]], VehicleState.OCCUPIED)
        self.teleports += sum(vid in self._leg for vid in api.simulation.getStartingTeleportIDList())

    def _check_fleet(self, api: Any) -> None:
        """SUMO holds exactly the driving legs we think it does (none lost, none extra)."""
        if self.vehicles_in_sumo() + len(self._fresh) != len(self._leg):
            known = set(api.vehicle.getIDList()) | set(api.simulation.getPendingVehicles()) | self._fresh
            lost = sorted(set(self._leg) - known)
            raise RuntimeError(f"SUMO lost fleet vehicles {lost[:5]} (holds {self.vehicles_in_sumo()}, {len(self._leg)} driving)")

    def _refresh_travel_times(self) -> None:
        """Region travel times (in steps) from SUMO's current edge travel times: one vectorised
        Dijkstra from a few sampled edges per region instead of N^2 routing calls. The city is
        replaced only when a rounded travel time changes, from the current step on."""
        api = self.sumo
        edge_time = np.fromiter((api.edge.getTraveltime(e) for e in self.net.edges), float, self.net.n_edges)
        edge_time = np.where(np.isfinite(edge_time) & (edge_time > 0), edge_time, self.net.free_time)
        steps = np.maximum(np.ceil(region_travel(self.net, self._picks, edge_time) / self.step_s), 1).astype(np.int64)
        if np.array_equal(steps, self.city.trip_time[self.t]):
            return
        trip = self.city.trip_time.copy()
        trip[self.t :] = steps
        np.fill_diagonal(steps, 0)
        self.city = dataclasses.replace(self.city, trip_time=trip, reb_time=steps)

    # ------------------------------------------------------------------ vehicles
    def _init_fleet(self) -> None:
        """Place the fleet on random edges of its initial regions (all idle)."""
        self.fleet: Fleet = bk.place_fleet(self.city.initial_vehicles, self.members, self._rng)
        self._leg: dict[str, int] = {}  # SUMO vehicle id of a driving leg -> fleet vehicle
        self._fresh: set[str] = set()  # legs added since the last simulation step
        self._legs_started = 0

    def _place_fleet(self) -> None:
        """Put the fleet into a fresh SUMO run; with legs, idle vehicles are off-road (nothing to add)."""

    def _send_to_pickup(self, v: int, k: int) -> None:
        """Vehicle v, just assigned request k, goes to its pickup edge."""
        req = self.ride_requests
        if self.fleet.edge[v] == req.origin_edge[k]:  # already there: the passenger gets in now
            bk.pick_up(self.fleet, req, np.array([v]), self.now, self.totals)
            self._drive(v, req.dest_edge[k], VehicleState.OCCUPIED)
        else:
            self._drive(v, req.origin_edge[k], VehicleState.PICKUP)

    def _send_rebalancing(self, v: int, to_edge: int) -> None:
        """Idle vehicle v drives empty to ``to_edge`` in its target region."""
        self._drive(v, to_edge, VehicleState.REBALANCING)

    def _drive(self, v: int, to_edge: int, state: VehicleState) -> None:
        """Start a SUMO leg from the vehicle's edge to ``to_edge`` (distinct edges)."""
        api, fleet = self.sumo, self.fleet
        edges = self.net.edges
        route, travel_time = self._route(fleet.edge[v], to_edge)
        if len(route) < 2:
            raise RuntimeError(f"no route of >= 2 edges from {edges[fleet.edge[v]]} to {edges[to_edge]}")
        self._legs_started += 1
        leg = f"{FLEET_PREFIX}{v}.{self._legs_started}"
        api.route.add(leg, route)
        api.vehicle.add(leg, leg, depart="now", departSpeed="max")
        self._leg[leg] = v
        self._fresh.add(leg)  # SUMO lists it from the next simulation step on
        fleet.state[v] = state
        fleet.target[v] = to_edge
        if state != VehicleState.PICKUP:  # a pickup's eta is the whole trip's, set at dispatch
            fleet.eta[v] = self.now + travel_time

    def _route(self, source: int, target: int) -> tuple[list[str], float]:
        """(edge ids, seconds) of the route SUMO's router would give from edge ``source`` to
        ``target``: from the routing table when there is one (see :mod:`~marl_amod.sim.meso.routing`)."""
        if self._router is not None:
            path, travel_time = self._router.route(source, target)
            return [self.net.edges[e] for e in path], travel_time
        route = self.sumo.simulation.findRoute(self.net.edges[source], self.net.edges[target])
        return list(route.edges), float(route.travelTime)

    # ------------------------------------------------------------------ requests
    def _new_requests(self, t: int) -> None:
        """Requests of step t: upcoming until the clock passes their request time (see :meth:`_reveal`)."""
        self.ride_requests.append(bk.draw_requests(self.demand[t], self.members, t, self.step_s, self._rng))

    def _reveal(self) -> None:
        """Upcoming requests whose time has come become open (and count as demand)."""
        self._on_open(bk.reveal(self.ride_requests, self.now, self.totals))

    def _expire(self, cutoff: float) -> None:
        """Requests still open and made before ``cutoff`` leave."""
        self._on_lost(bk.expire(self.ride_requests, cutoff, self.totals))

    def _on_open(self, new: np.ndarray) -> None:
        """Requests ``new`` just opened (legs: nothing for SUMO to know)."""

    def _on_lost(self, gone: np.ndarray) -> None:
        """Requests ``gone`` just left unserved (legs: nothing for SUMO to know)."""
