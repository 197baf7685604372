"""Road networks: built once with netconvert / netgenerate into a user cache, then read as arrays.

A network file is keyed by the tool, its options, the source file's content hash and the SUMO
version, and written atomically, so concurrent runs share it and a changed input rebuilds it.
The cache lives in ``$MARL_AMOD_CACHE``, else ``$XDG_CACHE_HOME/marl_amod``, else
``~/.cache/marl_amod``; never in the repository.

``RoadNetwork`` keeps what the region model and the simulator need: normal (non-internal)
edges that lie in the largest strongly connected component of the lane-connection graph (so
every edge can reach every other), their lengths, free-flow times and midpoints.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import tempfile
import xml.etree.ElementTree as ET
from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property, lru_cache
from pathlib import Path

import numpy as np
from scipy.sparse import csr_matrix
from scipy.sparse.csgraph import connected_components, dijkstra

from marl_amod.errors import DataError
from marl_amod.scenario.sumo import install

CACHE_ENV = "MARL_AMOD_CACHE"

# netconvert options for an OpenStreetMap extract: cars only, guessed signals and ramps,
# joined clusters of junctions (fewer spurious intersections), no isolated pieces
OSM_OPTIONS = (
    "--geometry.remove",
    "--ramps.guess",
    "--junctions.join",
    "--tls.guess-signals",
    "--tls.discard-simple",
    "--tls.join",
    "--keep-edges.by-vclass",
    "passenger",
    "--remove-edges.isolated",
)


def cache_dir() -> Path:
    """The folder generated networks are written to (created on demand)."""
    root = os.environ.get(CACHE_ENV)
    if root:
        path = Path(root).expanduser()
    else:
        path = Path(os.environ.get("XDG_CACHE_HOME", Path.home() / ".cache")).expanduser() / "marl_amod"
    path.mkdir(parents=True, exist_ok=True)
    return path


def cached_output(stem: str, suffix: str, key_parts: list[str], command: Callable[[Path], list[str]], what: str) -> Path:
    """The cached file ``<stem>-<key><suffix>``, made by ``command(target)`` the first time.

    The key hashes ``key_parts`` (which name the SUMO version). The command runs with SUMO_HOME set, in a
    scratch folder inside the cache that is removed afterwards, and writes ``target`` there; the
    result is moved into place atomically, so concurrent runs share one file."""
    key = hashlib.sha1("\0".join(key_parts).encode()).hexdigest()[:16]
    out = cache_dir() / f"{stem}-{key}{suffix}"
    if out.is_file():
        return out
    with tempfile.TemporaryDirectory(dir=cache_dir(), prefix=f".{stem}-") as work:
        target = Path(work) / f"out{suffix}"
        proc = subprocess.run(
            command(target), capture_output=True, text=True, cwd=work, env={**os.environ, "SUMO_HOME": str(install.sumo_home())}
        )
        if proc.returncode != 0 or not target.is_file():
            raise DataError(f"{what} failed ({proc.returncode}) building {out.name}: {proc.stderr.strip()[-2000:]}")
        target.replace(out)
    return out


def _build(tool: str, args: list[str], key_parts: list[str], stem: str) -> Path:
    """A network built by a SUMO tool (``netconvert``, ``netgenerate``); its name is its content key."""
    return cached_output(
        stem, ".net.xml", [tool, install.version(), *args, *key_parts],
        lambda target: [install.binary(tool), *args, "--output-file", str(target), "--no-warnings"], tool,
    )  # fmt: skip


def build_osm(osm_file: Path) -> Path:
    """Road network of an OpenStreetMap file (cached; a few seconds the first time)."""
    if not osm_file.is_file():
        raise DataError(f"OpenStreetMap file not found: {osm_file}")
    digest = hashlib.sha1(osm_file.read_bytes()).hexdigest()
    return _build("netconvert", ["--osm-files", str(osm_file), *OSM_OPTIONS], [digest], osm_file.stem)


def build_grid(size: int, length: float, seed: int) -> Path:
    """A ``size x size`` junction grid with two-way one-lane streets ``length`` metres long (cached)."""
    args = [
        "--grid",
        "--grid.number", str(size),
        "--grid.length", str(length),
        "--default.lanenumber", "1",
        "--default.speed", "13.89",
        "--seed", str(seed),
    ]  # fmt: skip
    return _build("netgenerate", args, [], f"grid{size}x{size}")


@dataclass(frozen=True, eq=False)
class RoadNetwork:
    """The usable edges of a SUMO network; E edges, arrays aligned with ``edges``."""

    path: Path
    edges: tuple[str, ...]  # (E,) edge ids in the largest strongly connected component
    length: np.ndarray  # (E,) metres
    free_time: np.ndarray  # (E,) seconds at the speed limit
    midpoint: np.ndarray  # (E, 2) metres, network coordinates
    successors: csr_matrix  # (E, E) 1 where a lane connection leads from edge a to edge b

    @property
    def n_edges(self) -> int:
        return len(self.edges)

    @cached_property
    def index(self) -> dict[str, int]:
        """Position of every usable edge id in ``edges`` (SUMO reports edges by id)."""
        return {e: k for k, e in enumerate(self.edges)}

    def travel_times(self, sources: np.ndarray, edge_time: np.ndarray | None = None) -> np.ndarray:
        """(len(sources), E) seconds from the start of each source edge to the end of every edge
        (Dijkstra over the connection graph). ``edge_time`` (E,) defaults to free flow, what
        SUMO's router sees on an empty network; pass SUMO's current edge times for congestion."""
        cost = self.free_time if edge_time is None else edge_time
        weights = self.successors.multiply(cost[None, :]).tocsr()
        dist = dijkstra(weights, directed=True, indices=sources)
        return dist + cost[sources][:, None]

    def distances(self, sources: np.ndarray) -> np.ndarray:
        """(len(sources), E) metres along the shortest route (what fares are charged on)."""
        weights = self.successors.multiply(self.length[None, :]).tocsr()
        dist = dijkstra(weights, directed=True, indices=sources)
        return dist + self.length[sources][:, None]


@lru_cache(maxsize=8)
def read_network(path: Path) -> RoadNetwork:
    """Parse a ``.net.xml`` into a :class:`RoadNetwork` (once per process per file)."""
    ids: list[str] = []
    lengths: list[float] = []
    speeds: list[float] = []
    mids: list[tuple[float, float]] = []
    links: list[tuple[str, str]] = []
    try:
        for _, elem in ET.iterparse(path, events=("end",)):
            if elem.tag == "edge":
                if elem.get("function") is None and not elem.get("id", ":").startswith(":"):
                    lane = elem.find("lane")
                    if lane is not None:
                        pts = np.array([p.split(",")[:2] for p in lane.get("shape", "").split()], dtype=float)
                        ids.append(elem.get("id"))
                        lengths.append(float(lane.get("length")))
                        speeds.append(float(lane.get("speed")))
                        mids.append(tuple(pts.mean(axis=0)))
                elem.clear()
            elif elem.tag == "connection":
                a, b = elem.get("from"), elem.get("to")
                if not a.startswith(":") and not b.startswith(":"):
                    links.append((a, b))
                elem.clear()
    except (ET.ParseError, OSError) as exc:
        raise DataError(f"cannot read SUMO network {path}: {exc}") from exc
    if not ids:
        raise DataError(f"SUMO network {path} has no drivable edges")
    index = {e: k for k, e in enumerate(ids)}
    pairs = np.array([(index[a], index[b]) for a, b in links if a in index and b in index], dtype=np.int64).reshape(-1, 2)
    n = len(ids)
    graph = csr_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, label = connected_components(graph, directed=True, connection="strong")
    keep = np.flatnonzero(label == np.bincount(label).argmax())
    sub = graph[keep][:, keep].tocsr()
    sub.data[:] = 1.0
    length = np.maximum(np.array(lengths)[keep], 0.1)
    return RoadNetwork(
        path=path,
        edges=tuple(ids[k] for k in keep),
        length=length,
        free_time=length / np.maximum(np.array(speeds)[keep], 0.1),
        midpoint=np.array(mids, dtype=float)[keep],
        successors=sub,
    )
