"""The fleet as SUMO taxis: requests are persons with a taxi stage, dispatched through the taxi device.

Same region-level contract as :class:`~marl_amod.sim.meso.sumo_sim.MesoSim` (which it extends):
the coordinator's flows choose *which* vehicle serves *which* request, nearest first; SUMO's
taxi device then does the driving, the boarding and the drop-off. Differences from the
plain-leg mechanism, all SUMO's own behaviour rather than ours:

- every fleet vehicle is one SUMO taxi for the whole episode (``has.taxi.device``), so the fleet
  size SUMO reports must equal ours after every step; idle taxis park off the road where they
  dropped off (``--device.taxi.idle-algorithm stop``);
- an open request is a SUMO person waiting at the middle of its origin edge with a driving stage
  ``lines="taxi"`` to its destination; SUMO turns it into a reservation after one simulation
  step, so a dispatch is sent to SUMO (``vehicle.dispatchTaxi``) at the next step (1 s later);
  a request that leaves after its maximum wait is removed from SUMO;
- rebalancing uses a placeholder person at the target edge with a ride to the nearest other edge
  of the target region: a parked taxi in meso cannot be moved by ``changeTarget``/``setStop``,
  but it does answer a reservation. The vehicle is idle again when the placeholder gets out;
- pickups and drop-offs are read from SUMO's taxi fleet states (empty / occupied) once per
  simulation step, as set differences, not per-vehicle calls.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from marl_amod.sim.meso import bookkeeping as bk
from marl_amod.sim.meso.sumo_sim import MesoSim
from marl_amod.sim.meso.types import VehicleState

TAXI_TYPE = "marl_amod_taxi"
EMPTY, OCCUPIED_FLEET, PICKUP_AND_OCCUPIED, ALL = 0, 2, 3, -1  # vehicle.getTaxiFleet filters


class TaxiMesoSim(MesoSim):
    """One episode with the fleet as SUMO taxis (simulator kind "taxi": ``taxi_device: true`` in a SUMO scenario)."""

    taxi_device = True

    # ------------------------------------------------------------------ fleet
    def _init_fleet(self) -> None:
        super()._init_fleet()
        self._taxi = [f"taxi{v}" for v in range(len(self.fleet))]
        self._index = {tid: v for v, tid in enumerate(self._taxi)}
        self._pending: list[tuple[int, str, int, float]] = []  # (vehicle, person, pickup edge, since) not yet sent
        self._to_pickup: set[str] = set()  # taxis driving to a passenger
        self._carrying: set[str] = set()  # taxis with a passenger or on a rebalancing move
        self._placeholders = 0

    def _place_fleet(self) -> None:
        """Add every vehicle as a taxi on its edge; its first route has two edges (a one-edge route
        silently leaves the network in meso); the idle algorithm parks it soon after insertion."""
        api = self.sumo
        api.vehicletype.copy("DEFAULT_VEHTYPE", TAXI_TYPE)
        api.vehicletype.setParameter(TAXI_TYPE, "has.taxi.device", "true")
        for v, tid in enumerate(self._taxi):
            start = self.fleet.edge[v]
            first = self._route(start, self._other_edge(start, self.fleet.region[v]))[0][:2]
            api.route.add(tid, first)
            api.vehicle.add(tid, tid, typeID=TAXI_TYPE, depart="now", departSpeed="max")

    def _other_edge(self, edge: int, region: int) -> int:
        """The edge of ``region`` nearest to ``edge`` other than itself (a short, real hop)."""
        members = self.members[region]
        d = np.linalg.norm(self.net.midpoint[members] - self.net.midpoint[edge], axis=1)
        d[members == edge] = np.inf
        if not np.isfinite(d).any():
            raise RuntimeError(f"region {region} has a single edge; taxis need two")
        return int(members[np.argmin(d)])

    def vehicles(self) -> int:
        """Fleet taxis SUMO holds, driving, parked or waiting for insertion (conservation)."""
        return self.vehicles_in_sumo()

    def vehicles_in_sumo(self) -> int:
        api = self.sumo
        pending = sum(vid in self._index for vid in api.simulation.getPendingVehicles())
        return len(api.vehicle.getTaxiFleet(ALL)) + pending

    def _check_fleet(self, api: Any) -> None:
        held = self.vehicles_in_sumo()
        if held != len(self._taxi):
            raise RuntimeError(f"SUMO holds {held} of the {len(self._taxi)} fleet taxis")

    # ------------------------------------------------------------------ requests as persons
    def _on_open(self, new: np.ndarray) -> None:
        api, edges, req = self.sumo, self.net.edges, self.ride_requests
        for k in new:
            pid = f"req{k}"
            e = req.origin_edge[k]
            api.person.add(pid, edges[e], float(self.net.length[e]) / 2.0, depart=-3)  # -3: now
            api.person.appendDrivingStage(pid, edges[req.dest_edge[k]], "taxi")

    def _on_lost(self, gone: np.ndarray) -> None:
        if self._api is None:
            return
        api = self.sumo
        for k in gone:
            api.person.remove(f"req{k}")

    # ------------------------------------------------------------------ moves
    def _send_to_pickup(self, v: int, k: int) -> None:
        """The taxi is sent once SUMO has opened the person's reservation (see :meth:`_dispatch_pending`)."""
        self.fleet.target[v] = self.ride_requests.dest_edge[k]
        self._pending.append((v, f"req{k}", self.ride_requests.origin_edge[k], self.now))

    def _send_rebalancing(self, v: int, to_edge: int) -> None:
        """A placeholder person at ``to_edge`` rides one hop inside the target region."""
        api, edges = self.sumo, self.net.edges
        hop = self._other_edge(to_edge, self.options.of_edge[to_edge])
        self._placeholders += 1
        pid = f"reb{self._placeholders}"
        api.person.add(pid, edges[to_edge], float(self.net.length[to_edge]) / 2.0, depart=-3)
        api.person.appendDrivingStage(pid, edges[hop], "taxi")
        self.fleet.target[v] = hop
        self.fleet.eta[v] = self.now + self._route(self.fleet.edge[v], to_edge)[1]
        self._pending.append((v, pid, to_edge, self.now))

    def _after_sumo_step(self, api: Any) -> None:
        """Pickups (a taxi sent to a passenger is now occupied), drop-offs (a carrying taxi is
        empty again), then the dispatches whose reservations SUMO has opened meanwhile."""
        self.teleports += sum(vid in self._index for vid in api.simulation.getStartingTeleportIDList())
        if self._to_pickup or self._carrying:
            empty = set(api.vehicle.getTaxiFleet(EMPTY))
            occupied = set(api.vehicle.getTaxiFleet(OCCUPIED_FLEET)) | set(api.vehicle.getTaxiFleet(PICKUP_AND_OCCUPIED))
            picked = sorted((occupied | empty) & self._to_pickup)
            self._to_pickup -= set(picked)
            self._carrying |= set(picked)
            self._taxi_pickup([self._index[tid] for tid in picked])
            dropped = sorted(empty & self._carrying)
            self._carrying -= set(dropped)
            self._taxi_dropoff([self._index[tid] for tid in dropped], api)
        if self._pending:
            self._dispatch_pending(api)

    def _dispatch_pending(self, api: Any) -> None:
        """Send the assignments whose reservation exists and whose taxi can take it now. A taxi
        still moving on the pickup edge waits until it parks: meso skips a stop added on the
        segment a vehicle is already driving, and the taxi would then leave the network."""
        reservation = {r.persons[0]: r.id for r in api.person.getTaxiReservations(0)}
        inserted = set(api.vehicle.getTaxiFleet(ALL))
        waiting = []
        for v, pid, edge, since in self._pending:
            tid = self._taxi[v]
            ready = pid in reservation and tid in inserted
            if ready and api.vehicle.getRoadID(tid) == self.net.edges[edge]:
                ready = self._parked(api, tid)
            if not ready:
                waiting.append((v, pid, edge, since))
                continue
            api.vehicle.dispatchTaxi(tid, [reservation[pid]])
            (self._to_pickup if self.fleet.state[v] == VehicleState.PICKUP else self._carrying).add(tid)
        self._pending = waiting

    @property
    def longest_dispatch_wait_s(self) -> float:
        """Seconds the oldest assignment not yet sent to SUMO has waited (for its reservation, and
        on its own pickup edge for the taxi to park): a few seconds, never minutes."""
        return max((self.now - since for *_, since in self._pending), default=0.0)

    @staticmethod
    def _parked(api: Any, tid: str) -> bool:
        """Whether the taxi has reached its stop (parked, off the road). Meso reports a parked taxi
        with speed 0 and no stop state, so this reads whether its next stop has an arrival time."""
        stops = api.vehicle.getStops(tid, 1)
        return bool(stops) and stops[0].arrival >= 0

    def _taxi_pickup(self, vs: list[int]) -> None:
        """The passengers are in: their waits end; each ride's ETA comes from SUMO's router."""
        if not vs:
            return
        fleet, req = self.fleet, self.ride_requests
        bk.pick_up(fleet, req, np.array(vs), self.now, self.totals)
        for v in vs:
            k = fleet.request[v]
            fleet.eta[v] = self.now + self._route(req.origin_edge[k], req.dest_edge[k])[1]

    def _taxi_dropoff(self, vs: list[int], api: Any) -> None:
        """Empty again: idle on the edge SUMO has them on (their drop-off edge)."""
        if not vs:
            return
        for v in vs:
            self.fleet.edge[v] = self.net.index.get(api.vehicle.getRoadID(self._taxi[v]), self.fleet.target[v])
        bk.become_idle(self.fleet, np.array(vs), self.now, self.step_s, self.options.of_edge, self.totals)
