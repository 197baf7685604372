"""SUMO scenarios -> City: a road network, its regions and a demand model, simulated in SUMO.

The returned :class:`City` is the region-level view that observations, baselines and the
coordinator read (OD rates, fares, free-flow travel times in steps, region adjacency); its
``simulator`` names a SUMO simulator and carries the built network and region map as data
(:class:`~marl_amod.scenario.simspec.SumoOptions`), so every consumer of a City runs in SUMO
without knowing it. Nothing here starts SUMO: travel times come from Dijkstra on the network's
free-flow times (what SUMO's router returns on an empty network); SUMO itself then decides how
long trips really take.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from marl_amod.data import resolve
from marl_amod.scenario.simspec import MACRO, SimSpec, SumoOptions
from marl_amod.scenario.sumo import demand as dm
from marl_amod.scenario.sumo import network as nw
from marl_amod.scenario.sumo.regions import partition
from marl_amod.scenario.sumo.traffic import background_routes
from marl_amod.scenario.types import City

if TYPE_CHECKING:
    from marl_amod.scenario.registry import SumoScenario

_CITY_KEYS = ("regions", "horizon", "tstep", "start_hour", "fleet", "requests_per_hour", "imbalance",
              "mean_trip_min", "peak", "fare_base", "fare_per_km", "beta")  # fmt: skip


def build_sumo_city(spec: SumoScenario) -> City:
    """The city of a validated SUMO scenario: its network built (cached), background traffic
    routed (cached) when it asks for some, then :func:`sumo_city`."""
    if spec.network == "osm":
        net_file = nw.build_osm(resolve(spec.osm_file))
    else:
        net_file = nw.build_grid(spec.grid_size, spec.grid_length, spec.seed)
    options: dict[str, Any] = {
        "max_wait_min": spec.max_wait_min, "backend": spec.backend, "step_length": spec.step_length,
        "sumo_seed": spec.seed, "refresh_travel_times": spec.refresh_travel_times,
        "dispatch_every_min": spec.dispatch_every_min, "extra_args": tuple(spec.sumo_args),
    }  # fmt: skip
    if spec.background_per_hour > 0 and spec.mode != "macro":
        begin = 3600.0 * spec.start_hour
        routes = background_routes(net_file, spec.background_per_hour, begin, begin + 60.0 * spec.tstep * spec.horizon, spec.seed)
        options["route_files"] = (str(routes),)
    return sumo_city(name=spec.name, net_file=net_file, region_seed=spec.seed, mode=spec.mode, taxi_device=spec.taxi_device,
                     options=options, **{k: getattr(spec, k) for k in _CITY_KEYS})  # fmt: skip


def sumo_city(
    *,
    name: str,
    net_file: Path,
    regions: int,
    region_seed: int,
    horizon: int,
    tstep: float,
    start_hour: float,
    fleet: int,
    requests_per_hour: float,
    imbalance: float,
    mean_trip_min: float,
    peak: float,
    fare_base: float,
    fare_per_km: float,
    beta: float,
    mode: str = "meso",
    taxi_device: bool = False,
    options: dict[str, Any] | None = None,
) -> City:
    """Build the city of a SUMO network (regions by k-means, demand by the gravity model).

    ``mode`` "meso" or "micro" simulates it in SUMO (the fleet as SUMO taxis with ``taxi_device``,
    else one SUMO vehicle per driving leg); "macro" gives the same city (regions, free-flow travel
    times, demand, fares, fleet) to the macro model, for training cheaply and transferring to
    SUMO zero-shot. ``options`` are further :class:`SumoOptions` fields."""
    net = nw.read_network(net_file)
    part = partition(net, regions, seed=region_seed)
    n_steps = horizon + 12  # look-ahead past the horizon for observations and MPC
    step_s = 60.0 * tstep
    rates = dm.od_rates(
        net, part, n_steps=n_steps, tstep_min=tstep, requests_per_hour=requests_per_hour,
        imbalance=imbalance, mean_trip_s=60.0 * mean_trip_min, peak=peak,
    )  # fmt: skip
    steps = np.maximum(np.ceil(part.travel_s / step_s), 1).astype(np.int64)
    reb_time = steps * (1 - np.eye(regions, dtype=np.int64))
    fare = fare_base + fare_per_km * part.distance_m / 1000.0
    share = rates[:horizon].sum(axis=(0, 2))
    initial = _apportion(fleet, share / share.sum())
    if mode == "macro":
        simulator = MACRO
    else:
        sumo = SumoOptions(
            net_file=net_file,
            of_edge=part.of_edge,
            begin_s=3600.0 * start_hour,
            region_seed=region_seed,
            mode=mode,
            **(options or {}),
        )
        simulator = SimSpec("taxi" if taxi_device else "meso", sumo)
    return City(
        name=name,
        tstep=tstep,
        horizon=horizon,
        beta=beta,
        demand_rate=rates,
        price=np.broadcast_to(fare, rates.shape).copy(),
        trip_time=np.broadcast_to(steps, rates.shape).copy(),
        reb_time=reb_time,
        initial_vehicles=initial,
        edge_index=part.adjacency.astype(np.int64),
        positions=part.centers / 1000.0,
        start_hour=start_hour,
        meta={"network": str(net_file), "edges": net.n_edges, "simulator": mode},
        simulator=simulator,
    )


def _apportion(total: int, share: np.ndarray) -> np.ndarray:
    """Integers proportional to ``share`` that sum to ``total`` (largest remainders)."""
    raw = total * share
    out = np.floor(raw).astype(np.int64)
    out[np.argsort(out - raw)[: total - out.sum()]] += 1
    return out
