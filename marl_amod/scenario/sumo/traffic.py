"""Background traffic: other cars on the roads, so the fleet's travel times meet congestion.

The data folder holds Luxembourg's roads but not the LuST day of traffic, so background traffic is
generated with SUMO's own ``randomTrips.py`` (routes by ``duarouter``): departures at a constant
rate over the window, origins and destinations drawn in proportion to edge length, at least
500 m apart, cars only. The route file is built once per (network, rate, window, seed, SUMO
version) into the same cache as the networks and is loaded by SUMO next to the fleet; its
vehicle ids start with ``bg`` so the simulators can tell them from the fleet.
"""

from __future__ import annotations

import sys
from pathlib import Path

from marl_amod.scenario.sumo import install
from marl_amod.scenario.sumo.network import cached_output

PREFIX = "bg"


def background_routes(net_file: Path, per_hour: float, begin_s: float, end_s: float, seed: int) -> Path:
    """Route file of random background cars for ``[begin_s, end_s)`` at ``per_hour`` departures (cached).

    ``net_file`` is a network from the cache, whose name is already its content key."""
    if per_hour <= 0 or end_s <= begin_s:
        raise ValueError(f"background traffic needs a positive rate and window, got {per_hour}/h over [{begin_s}, {end_s})")
    args = [
        "-n", str(net_file),
        "-b", str(begin_s), "-e", str(end_s),
        "--insertion-rate", str(per_hour),
        "--seed", str(seed),
        "--prefix", PREFIX,
        "--length",
        "--min-distance", "500",
        "--vclass", "passenger",
    ]  # fmt: skip
    script = install.sumo_home() / "tools" / "randomTrips.py"
    return cached_output(
        "background", ".rou.xml", ["randomTrips", install.version(), Path(net_file).name, *args[2:]],
        lambda target: [sys.executable, str(script), *args, "-o", str(target.with_name("trips.xml")), "-r", str(target)],
        "randomTrips.py",
    )  # fmt: skip
