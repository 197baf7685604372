"""Background traffic: other cars on the roads, so the fleet's travel times meet congestion.

The data folder holds Luxembourg's roads but not the LuST day of traffic, so background traffic is
generated with SUMO's own ``randomTrips.py`` (routes by ``duarouter``): departures at a constant
rate over the window, origins and destinations drawn in proportion to edge length, at least
500 m apart, cars only. The route file is built once per (network, rate, window, seed, SUMO
version) into the same cache as the networks and is loaded by SUMO next to the fleet; its
vehicle ids start with ``bg`` so the simulators can tell them from the fleet.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
from pathlib import Path

from marl_amod.errors import DataError
from marl_amod.sim.meso import engine
from marl_amod.sim.meso.network import cache_dir

PREFIX = "bg"


def background_routes(net_file: Path, per_hour: float, begin_s: float, end_s: float, seed: int) -> Path:
    """Route file of random background cars for ``[begin_s, end_s)`` at ``per_hour`` departures (cached)."""
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
    net_digest = hashlib.sha1(Path(net_file).read_bytes()).hexdigest()
    key = hashlib.sha1("\0".join([engine.version(), net_digest, *args[2:]]).encode()).hexdigest()[:16]
    out = cache_dir() / f"background-{key}.rou.xml"
    if out.is_file():
        return out
    work = out.with_name(f"{out.stem}.{os.getpid()}.tmp")
    work.mkdir(exist_ok=True)
    script = engine.sumo_home() / "tools" / "randomTrips.py"
    proc = subprocess.run(
        [sys.executable, str(script), *args, "-o", str(work / "trips.xml"), "-r", str(work / "routes.rou.xml")],
        capture_output=True,
        text=True,
        cwd=work,
        env={**os.environ, "SUMO_HOME": str(engine.sumo_home())},
    )
    routes = work / "routes.rou.xml"
    if proc.returncode != 0 or not routes.is_file():
        raise DataError(f"randomTrips.py failed ({proc.returncode}) for {net_file}: {proc.stderr.strip()[-2000:]}")
    routes.replace(out)
    for leftover in work.iterdir():
        leftover.unlink()
    work.rmdir()
    return out
