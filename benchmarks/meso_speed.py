"""Wall time of the SUMO scenarios: meso vs micro, libsumo vs TraCI, and where the time goes.

Runs one episode of equal-distribution rebalancing per configuration (mode:backend:fleet, the
fleet as plain SUMO vehicles per leg or as SUMO taxis) and prints a markdown table: simulated
hours, wall seconds, wall seconds per simulated hour, and the shares spent in the simulator (SUMO
start-up and stepping, bookkeeping, travel-time refresh), in SUMO's simulation steps and in
starting moves (our routing, adding legs or persons, dispatching taxis), both part of the
simulator's share, and in the coordinator (dispatch + min-cost flow).
Run on one core:  OMP_NUM_THREADS=1 python benchmarks/meso_speed.py [--scenario lux]
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time

os.environ.setdefault("OMP_NUM_THREADS", "1")

import numpy as np  # noqa: E402

from marl_amod.coordinator.coordinator import Coordinator  # noqa: E402
from marl_amod.scenario import load_city  # noqa: E402
from marl_amod.scenario.simspec import SimSpec  # noqa: E402
from marl_amod.system import FleetSystem  # noqa: E402

CONFIGS = ["meso:libsumo:legs", "meso:libsumo:legs:sumo", "meso:traci:legs", "micro:libsumo:legs", "meso:libsumo:taxi"]
ROUTERS = ("table", "sumo")  # the routing table on SUMO's costs (default), or findRoute per leg
MOVES = {  # the methods that start vehicle moves, per fleet mechanism
    "legs": ("_drive",),
    "taxi": ("_on_open", "_send_rebalancing", "_taxi_pickup", "_dispatch_pending"),
}


def _timed(obj, name: str, clock: dict) -> None:
    """Wrap ``obj.name`` so that its wall time accumulates in ``clock[name]``."""
    inner = getattr(obj, name)

    def wrapper(*args, **kwargs):
        t0 = time.perf_counter()
        try:
            return inner(*args, **kwargs)
        finally:
            clock[name] = clock.get(name, 0.0) + time.perf_counter() - t0

    setattr(obj, name, wrapper)


COORDINATOR_CLOCK: dict[str, float] = {}
for _name in ("dispatch", "rebalance"):  # on the class, once: FleetSystem renews its coordinator
    _timed(Coordinator, _name, COORDINATOR_CLOCK)


def run(scenario: str, mode: str, backend: str, fleet: str, router: str = "table", horizon: int | None = None) -> dict:
    if router not in ROUTERS:
        raise SystemExit(f"router must be one of {ROUTERS}, got {router!r}")
    city = load_city(scenario, **({"horizon": horizon} if horizon else {}))
    options = dataclasses.replace(city.simulator.sumo, mode=mode, backend=backend, sumo_router=router == "sumo")
    city = dataclasses.replace(city, simulator=SimSpec("taxi" if fleet == "taxi" else "meso", options))
    system = FleetSystem(city)
    clock = COORDINATOR_CLOCK
    clock.clear()
    for name in ("advance", "advance_round", "apply_dispatch", "apply_rebalance", "reset"):
        _timed(system.sim, name, clock)
    moves: dict[str, float] = {}
    for name in MOVES[fleet]:
        _timed(system.sim, name, moves)
    t0 = time.perf_counter()
    system.reset(0)
    api = system.sim.sumo  # the libsumo module (shared by every run in this process) or a TraCI connection
    step = api.simulationStep
    _timed(api, "simulationStep", clock)
    try:
        while not system.done:
            system.step(system.targets_from_weights(np.ones(city.n_regions)))
    finally:
        api.simulationStep = step  # the next run must not count its steps twice
    wall = time.perf_counter() - t0
    used = "table" if system.sim._router is not None else "sumo" if router == "sumo" else "sumo (table refused)"
    system.sim.close()
    hours = (city.horizon - 1) * city.tstep / 60.0
    sim = sum(clock.get(k, 0.0) for k in ("reset", "advance", "advance_round", "apply_dispatch", "apply_rebalance"))
    coord = clock.get("dispatch", 0.0) + clock.get("rebalance", 0.0)
    return {
        "scenario": city.name, "mode": mode, "backend": backend, "fleet": fleet, "router": used, "simulated_h": hours,
        "wall_s": wall, "wall_s_per_sim_h": wall / hours, "startup_s": clock["reset"], "simulator_share": sim / wall,
        "sumo_step_share": clock["simulationStep"] / wall, "moves_share": sum(moves.values()) / wall,
        "coordinator_share": coord / wall,
        "served": float(system.sim.totals.served.sum()),
    }  # fmt: skip


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="lux")
    parser.add_argument("--horizon", type=int, default=None, help="control steps (default: the scenario's)")
    parser.add_argument("--configs", nargs="*", default=CONFIGS, help="mode:backend:fleet[:router], fleet legs|taxi, router table|sumo")
    parser.add_argument("--output", default=None)
    args = parser.parse_args()
    rows = [run(args.scenario, *c.split(":"), horizon=args.horizon) for c in args.configs]
    print(
        "| scenario | mode | backend | fleet | router | simulated h | wall s | wall s / sim h | SUMO start | simulator "
        "| of which SUMO steps | of which starting moves | coordinator | served |"
    )
    print("|---|---|---|---|---|---:|---:|---:|---:|---:|---:|---:|---:|---:|")
    for r in rows:
        print(
            f"| {r['scenario']} | {r['mode']} | {r['backend']} | {r['fleet']} | {r['router']} | {r['simulated_h']:.2f} | {r['wall_s']:.1f} "
            f"| {r['wall_s_per_sim_h']:.1f} | {r['startup_s']:.1f} s | {r['simulator_share']:.0%} | {r['sumo_step_share']:.0%} "
            f"| {r['moves_share']:.0%} | {r['coordinator_share']:.1%} | {r['served']:,.0f} |"
        )
    if args.output:
        with open(args.output, "w") as fh:
            json.dump(rows, fh, indent=2)


if __name__ == "__main__":
    main()
