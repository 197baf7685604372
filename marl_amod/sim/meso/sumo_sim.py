"""The mesoscopic simulator: the fleet drives on real roads in SUMO, same interface as MacroSim.

Region-level flows from the coordinator become concrete moves here:

- requests are drawn per control step from the city's OD rates (one Poisson draw per pair and
  step, as in the macro model), each with an origin and a destination edge in its regions and
  a request time inside the step; a request not dispatched within ``max_wait_min`` leaves;
- dispatch x[i, j] serves the oldest open i->j requests, each with the nearest idle vehicle of
  region i; the vehicle drives to the pickup edge (the wait ends there), then to the drop-off;
- rebalancing y[i, j] sends the idle vehicles of i nearest to j's centre to random edges of j.

Mechanism (the default; ``taxi_device: true`` selects SUMO's taxi device instead, see
:mod:`marl_amod.sim.meso.taxi_sim`): every driving leg is a plain SUMO vehicle added with a
router-computed route of at least two edges (single-edge routes vanish in meso); its arrival is
read back from SUMO each simulation step. Idle vehicles wait
off-road at their last edge (parked meso vehicles cannot be re-routed anyway), so the fleet
is conserved by construction and checked against SUMO's own vehicle count. Travel times, and
so vehicle availability and waits, come from SUMO's mesoscopic queues, not from a table.
Fares and trip costs are the city's region-level estimates, the same numbers the coordinator
optimises, so rewards are comparable with the macro model.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.scenario.types import City
from marl_amod.sim.flows import as_flows, check_dispatch, check_rebalance
from marl_amod.sim.macro import EpisodeTotals
from marl_amod.sim.meso import engine
from marl_amod.sim.meso.network import read_network
from marl_amod.sim.meso.regions import TRAVEL_SAMPLES, region_travel, sample_edges

IDLE, PICKUP, OCCUPIED, REBALANCING = 0, 1, 2, 3
FLEET_PREFIX = "fleet"  # SUMO ids of the fleet's legs; other traffic has other ids
OPEN, ASSIGNED, PICKED, LOST, UPCOMING = 0, 1, 2, 3, 4


@dataclass(frozen=True, eq=False)
class MesoOptions:
    """How a SUMO scenario is simulated; called with a city it builds a :class:`MesoSim`."""

    net_file: Path
    of_edge: np.ndarray = field(repr=False)  # (E,) region of every usable edge of the network
    max_wait_min: float = 10.0
    mode: str = "meso"  # "meso" (--mesosim) or "micro"
    backend: engine.Backend = "libsumo"
    step_length: float = 1.0  # SUMO seconds per simulation step
    sumo_seed: int = 0
    begin_s: float = 0.0  # clock time of step 0, in seconds of the day
    time_to_teleport: float = 300.0
    refresh_travel_times: bool = True  # re-estimate region travel times from SUMO every step
    dispatch_every_min: float | None = None  # match requests this often inside a step (None: once)
    taxi_device: bool = False  # the fleet as SUMO taxis and requests as persons (TaxiMesoSim); else legs
    route_files: tuple[str, ...] = ()  # other traffic SUMO loads next to the fleet (ids not "fleet*"/"taxi*")
    region_seed: int = 0  # seeds the edges that region travel times average over
    quiet: bool = True  # silence SUMO's warnings (pass extra_args=("--log", file) to keep them)
    extra_args: tuple[str, ...] = ()

    def __call__(self, city: City, max_wait: int = 0) -> MesoSim:
        """The simulator for ``city``; a positive ``max_wait`` (steps) overrides ``max_wait_min``."""
        minutes = max_wait * city.tstep if max_wait > 0 else self.max_wait_min
        if self.taxi_device:
            from marl_amod.sim.meso.taxi_sim import TaxiMesoSim

            return TaxiMesoSim(city, self, max_wait_min=minutes)
        return MesoSim(city, self, max_wait_min=minutes)

    def sumo_args(self) -> list[str]:
        args = [
            "--net-file", str(self.net_file),
            "--begin", str(self.begin_s),
            "--step-length", str(self.step_length),
            "--seed", str(self.sumo_seed),
            "--time-to-teleport", str(self.time_to_teleport),
            "--no-step-log", "true",
            "--no-warnings", str(self.quiet).lower(),
            "--duration-log.disable", "true",
            "--routing-algorithm", "astar",  # exact like Dijkstra, ~40% cheaper per findRoute here
        ]  # fmt: skip
        if self.mode == "meso":
            args += ["--mesosim", "true"]
        if self.route_files:
            args += ["--route-files", ",".join(self.route_files)]
        if self.taxi_device:  # we dispatch; idle taxis park off the road where they drop off
            args += ["--device.taxi.dispatch-algorithm", "traci", "--device.taxi.idle-algorithm", "stop"]
        return [*args, *self.extra_args]


class MesoSim:
    """One episode of a city in SUMO; reset with a random generator, then apply flows step by step."""

    def __init__(self, city: City, options: MesoOptions, *, max_wait_min: float = 10.0) -> None:
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
        self.region_center = np.array([self.net.midpoint[m].mean(axis=0) for m in self.members])
        self.step_s = 60.0 * city.tstep
        every = city.tstep if options.dispatch_every_min is None else options.dispatch_every_min
        self.dispatch_rounds = int(round(city.tstep / every))
        if self.dispatch_rounds < 1 or abs(self.dispatch_rounds * every - city.tstep) > 1e-9:
            raise ValueError(f"dispatch_every_min={every} must divide the control step of {city.tstep} min")
        self._round = 0  # dispatch rounds already run inside the current control step
        self._picks = sample_edges(options.of_edge, n, TRAVEL_SAMPLES, options.region_seed)
        self._api: Any = None
        self._rng = np.random.default_rng(options.sumo_seed)  # replaced by reset()'s generator
        self.t = 0
        self.totals = EpisodeTotals.zeros(n)
        self.demand = np.zeros((city.n_steps, n, n), dtype=np.int64)
        self.last_dispatch = np.zeros((n, n), dtype=np.int64)
        self.last_rebalance = np.zeros((n, n), dtype=np.int64)
        self.teleports = 0
        self._init_fleet()
        self._init_requests()

    # ------------------------------------------------------------------ lifecycle
    def reset(self, rng: np.random.Generator) -> None:
        """Start an episode: (re)start SUMO, place the fleet, draw every step's OD counts."""
        self.close()
        self._api = engine.start(self.options.sumo_args(), self.options.backend, owner=self)
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
        self._init_requests()
        self._place_fleet()
        self._round = 0
        self._new_requests(0)
        self._reveal()

    def close(self) -> None:
        """End the SUMO run (also called by reset); the simulator can be reset again later."""
        if self._api is not None:
            if self.options.backend != "libsumo" or engine.owns(self):
                self._api.close()
            self._api = None

    def __getstate__(self) -> dict:
        """Picklable: the live SUMO connection is dropped; the copy needs a reset."""
        state = self.__dict__.copy()
        state["_api"] = None
        return state

    @property
    def sumo(self) -> Any:
        """The live SUMO connection; libsumo runs one simulation per process, so a simulator
        whose run was replaced by another's says so instead of driving the wrong simulation."""
        if self._api is None:
            raise RuntimeError("the SUMO simulation is not running; call reset()")
        if self.options.backend == "libsumo" and not engine.owns(self):
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
        return np.bincount(self.v_region[self.v_state == IDLE], minlength=self.city.n_regions).astype(np.int64)

    @property
    def arrivals(self) -> np.ndarray:
        """(S + 1, N) busy vehicles expected to become idle after step k (as in MacroSim)."""
        out = np.zeros((self.city.n_steps + 1, self.city.n_regions), dtype=np.int64)
        busy = self.v_state != IDLE
        step = np.ceil(self.v_eta[busy] / self.step_s).astype(np.int64) - 1
        np.add.at(out, (np.clip(step, self.t, self.city.n_steps), self.v_dest[busy]), 1)
        return out

    def requests(self) -> np.ndarray:
        """(N, N) open requests right now."""
        return self._od_counts(self._open())

    def carried_over(self) -> np.ndarray:
        """(N, N) requests open now that will not have left by the next control step."""
        k = self._open()
        return self._od_counts(k[self.r_time[k] + self.max_wait_s >= (self.t + 1) * self.step_s])

    def _od_counts(self, k: np.ndarray) -> np.ndarray:
        n = self.city.n_regions
        out = np.zeros((n, n), dtype=np.int64)
        np.add.at(out, (self.r_o[k], self.r_d[k]), 1)
        return out

    def vehicles(self) -> int:
        """Idle vehicles plus driving legs (every busy vehicle has exactly one); constant over an
        episode (conservation)."""
        return int(np.sum(self.v_state == IDLE) + len(self._leg))

    def vehicles_in_sumo(self) -> int:
        """Fleet vehicles SUMO itself holds (driving or waiting for insertion); with the legs
        added since SUMO's last step it equals the number of driving legs (advance checks it)."""
        api = self.sumo
        if not self.options.route_files:  # the fleet alone: SUMO's counts are ours
            return int(api.vehicle.getIDCount() + len(api.simulation.getPendingVehicles()))
        held = (*api.vehicle.getIDList(), *api.simulation.getPendingVehicles())
        return sum(vid.startswith(FLEET_PREFIX) for vid in held)

    # ------------------------------------------------------------------ transitions
    def apply_dispatch(self, x: np.ndarray) -> float:
        """Serve open requests with passenger flows x (N, N); returns the step's dispatch profit."""
        c, t = self.city, self.t
        x = as_flows(x, c.n_regions, "dispatch")
        check_dispatch(x, self.requests(), self.idle)
        open_k = self._open()
        now = self.now
        for i in np.flatnonzero(x.sum(axis=1)):
            chosen = np.concatenate(
                [open_k[(self.r_o[open_k] == i) & (self.r_d[open_k] == j)][: x[i, j]] for j in np.flatnonzero(x[i])]
            )
            chosen = chosen[np.argsort(self.r_time[chosen], kind="stable")]  # oldest first
            cars = self._nearest(np.flatnonzero((self.v_state == IDLE) & (self.v_region == i)), self.net.midpoint[self.r_oe[chosen]])
            for k, v in zip(chosen, cars, strict=True):
                self.r_status[k] = ASSIGNED
                self.v_req[v] = k
                self.v_dest[v] = self.r_d[k]
                self._go_busy(v, i, now + self.step_s * c.trip_time[t, i, self.r_d[k]])
                self._send_to_pickup(v, k)
        self.totals.served += x.sum(axis=1)
        self.last_dispatch = self.last_dispatch + x  # summed over the step's dispatch rounds
        return self.totals.book_trips(x, c, t)

    def apply_rebalance(self, y: np.ndarray) -> float:
        """Send idle vehicles y (N, N) to random edges of their target regions; returns the cost."""
        c = self.city
        y = as_flows(y, c.n_regions, "rebalancing")
        check_rebalance(y, self.idle)
        now = self.now
        for i, j in zip(*np.nonzero(y), strict=True):
            pool = np.flatnonzero((self.v_state == IDLE) & (self.v_region == i))
            cars = self._nearest(pool, np.repeat(self.region_center[j][None], y[i, j], axis=0))
            targets = self._rng.choice(self.members[j], size=len(cars))
            for v, e in zip(cars, targets, strict=True):
                self.v_dest[v] = j
                self._go_busy(v, i, now + self.step_s * c.reb_time[i, j])
                self._send_rebalancing(v, e)
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
        """React to what SUMO did in one simulation step: legs that arrived."""
        self._fresh.clear()
        for vid in api.simulation.getArrivedIDList():
            v = self._leg.pop(vid, None)
            if v is not None:
                self._arrive(v)
        self.teleports += sum(vid in self._leg for vid in api.simulation.getStartingTeleportIDList())

    def _check_fleet(self, api: Any) -> None:
        """SUMO holds exactly the driving legs we think it does (none lost, none extra)."""
        if self.vehicles_in_sumo() + len(self._fresh) != len(self._leg):
            known = set(api.vehicle.getIDList()) | set(api.simulation.getPendingVehicles()) | self._fresh
            lost = sorted(set(self._leg) - known)
            raise RuntimeError(f"SUMO lost fleet vehicles {lost[:5]} (holds {self.vehicles_in_sumo()}, {len(self._leg)} driving)")

    def finish(self) -> None:
        """End of episode: open requests are lost; busy time and waits so far are booked."""
        self._expire(np.inf)
        now = self.now
        waiting = np.flatnonzero(self.r_status == ASSIGNED)
        np.add.at(self.totals.wait_minutes, self.r_o[waiting], (now - self.r_time[waiting]) / 60.0)
        for v in np.flatnonzero(self.v_state != IDLE):
            tail = min(max(self.v_eta[v] - now, 0.0), self.step_s)
            self.totals.busy_vehicle_steps[self.v_origin[v]] += (now - self.v_since[v] + tail) / self.step_s
            self.v_since[v] = now

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
        rng = self._rng
        regions = np.repeat(np.arange(self.city.n_regions), self.city.initial_vehicles)
        m = len(regions)
        self.v_region = regions.astype(np.int64)
        self.v_edge = np.array([rng.choice(self.members[r]) for r in regions], dtype=np.int64)
        self.v_state = np.full(m, IDLE, dtype=np.int64)
        self.v_dest = regions.astype(np.int64).copy()
        self.v_origin = regions.astype(np.int64).copy()
        self.v_req = np.full(m, -1, dtype=np.int64)
        self.v_eta = np.zeros(m)
        self.v_since = np.zeros(m)
        self.v_target = np.zeros(m, dtype=np.int64)
        self._leg: dict[str, int] = {}  # SUMO vehicle id of a driving leg -> fleet vehicle
        self._fresh: set[str] = set()  # legs added since the last simulation step
        self._legs_started = 0

    def _nearest(self, pool: np.ndarray, points: np.ndarray) -> np.ndarray:
        """Greedy nearest vehicles of ``pool`` to ``points`` (P, 2), in order; one each."""
        if len(points) > len(pool):
            raise ValueError(f"asked for {len(points)} vehicles from a pool of {len(pool)}")
        d = np.linalg.norm(self.net.midpoint[self.v_edge[pool]][None] - points[:, None], axis=2)
        out = np.empty(len(points), dtype=np.int64)
        for p in range(len(points)):
            k = int(np.argmin(d[p]))
            out[p] = pool[k]
            d[:, k] = np.inf
        return out

    def _go_busy(self, v: int, origin: int, eta: float) -> None:
        self.v_origin[v] = origin
        self.v_since[v] = self.now
        self.v_eta[v] = eta

    def _place_fleet(self) -> None:
        """Put the fleet into a fresh SUMO run; with legs, idle vehicles are off-road (nothing to add)."""

    def _send_to_pickup(self, v: int, k: int) -> None:
        """Vehicle v, just assigned request k, goes to its pickup edge."""
        if self.v_edge[v] == self.r_oe[k]:
            self._pickup(v)
        else:
            self._drive(v, self.r_oe[k], PICKUP)

    def _send_rebalancing(self, v: int, to_edge: int) -> None:
        """Idle vehicle v drives empty to ``to_edge`` in its target region."""
        self._drive(v, to_edge, REBALANCING)

    def _drive(self, v: int, to_edge: int, state: int) -> None:
        """Start a SUMO leg from the vehicle's edge to ``to_edge`` (distinct edges)."""
        api = self.sumo
        edges = self.net.edges
        route = api.simulation.findRoute(edges[self.v_edge[v]], edges[to_edge])
        if len(route.edges) < 2:
            raise RuntimeError(f"no route of >= 2 edges from {edges[self.v_edge[v]]} to {edges[to_edge]}")
        self._legs_started += 1
        leg = f"{FLEET_PREFIX}{v}.{self._legs_started}"
        api.route.add(leg, list(route.edges))
        api.vehicle.add(leg, leg, depart="now", departSpeed="max")
        self._leg[leg] = v
        self._fresh.add(leg)  # SUMO lists it from the next simulation step on
        self.v_state[v] = state
        self.v_target[v] = to_edge
        if state != PICKUP:
            self.v_eta[v] = self.now + route.travelTime

    def _arrive(self, v: int) -> None:
        """A leg ended at its target edge: pick the passenger up, or become idle there."""
        self.v_edge[v] = self.v_target[v]
        if self.v_state[v] == PICKUP:
            self._pickup(v)
            return
        self._become_idle(v)

    def _become_idle(self, v: int) -> None:
        """A trip or a rebalancing move ended at the vehicle's edge: book its busy time; idle there."""
        if self.v_state[v] == OCCUPIED:
            self.v_req[v] = -1
        self.totals.busy_vehicle_steps[self.v_origin[v]] += (self.now - self.v_since[v]) / self.step_s
        self.v_state[v] = IDLE
        self.v_region[v] = self.options.of_edge[self.v_edge[v]]

    def _pickup(self, v: int) -> None:
        k = self.v_req[v]
        self.r_status[k] = PICKED
        self.totals.wait_minutes[self.r_o[k]] += (self.now - self.r_time[k]) / 60.0
        self._drive(v, self.r_de[k], OCCUPIED)

    # ------------------------------------------------------------------ requests
    def _init_requests(self) -> None:
        self.r_o = np.zeros(0, dtype=np.int64)
        self.r_d = np.zeros(0, dtype=np.int64)
        self.r_oe = np.zeros(0, dtype=np.int64)
        self.r_de = np.zeros(0, dtype=np.int64)
        self.r_time = np.zeros(0)
        self.r_status = np.zeros(0, dtype=np.int64)

    def _new_requests(self, t: int) -> None:
        """Requests of step t: the drawn OD counts, with edges and request times inside the step;
        they stay upcoming until the clock passes their request time (see :meth:`_reveal`)."""
        rng = self._rng
        counts = self.demand[t]
        pi, pj = np.nonzero(counts)
        o, d = np.repeat(pi, counts[pi, pj]), np.repeat(pj, counts[pi, pj])
        oe = np.array([rng.choice(self.members[i]) for i in o], dtype=np.int64)
        de = np.array([rng.choice(self.members[j]) for j in d], dtype=np.int64)
        for k in np.flatnonzero(oe == de):  # a trip needs two distinct edges
            while de[k] == oe[k]:
                de[k] = rng.choice(self.members[d[k]])
        when = np.zeros(len(o)) if t == 0 else (t - rng.random(len(o))) * self.step_s
        order = np.argsort(when, kind="stable")
        self.r_o = np.concatenate([self.r_o, o[order]])
        self.r_d = np.concatenate([self.r_d, d[order]])
        self.r_oe = np.concatenate([self.r_oe, oe[order]])
        self.r_de = np.concatenate([self.r_de, de[order]])
        self.r_time = np.concatenate([self.r_time, when[order]])
        self.r_status = np.concatenate([self.r_status, np.full(len(o), UPCOMING, dtype=np.int64)])

    def _reveal(self) -> None:
        """Upcoming requests whose time has come become open (and count as demand)."""
        new = np.flatnonzero((self.r_status == UPCOMING) & (self.r_time <= self.now + 1e-6))
        self.r_status[new] = OPEN
        self.totals.demand += np.bincount(self.r_o[new], minlength=self.city.n_regions)
        self._on_open(new)

    def _on_open(self, new: np.ndarray) -> None:
        """Requests ``new`` just opened (legs: nothing for SUMO to know)."""

    def _on_lost(self, gone: np.ndarray) -> None:
        """Requests ``gone`` just left unserved (legs: nothing for SUMO to know)."""

    def _open(self) -> np.ndarray:
        return np.flatnonzero(self.r_status == OPEN)

    def _expire(self, cutoff: float) -> None:
        """Requests still open and made before ``cutoff`` leave."""
        gone = np.flatnonzero((self.r_status == OPEN) & (self.r_time < cutoff))
        self.r_status[gone] = LOST
        self.totals.lost += np.bincount(self.r_o[gone], minlength=self.city.n_regions)
        self._on_lost(gone)
