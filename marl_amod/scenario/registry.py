"""Scenario names -> cities, through one small YAML file per scenario.

The bundled scenarios live in the repository's ``envs/`` folder (shipped inside the wheel as
``marl_amod/_scenarios``). A user's own scenario is any YAML path with the same keys. Keys are
validated strictly: a typo is an error naming the key, never a silent default.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal, get_args

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, PrivateAttr, ValidationError, model_validator

from marl_amod.data import read_yaml, resolve
from marl_amod.errors import UNKNOWN_KEY, ConfigError, pydantic_problem
from marl_amod.scenario.events import DemandEvent, apply_events
from marl_amod.scenario.json_city import load_json_city
from marl_amod.scenario.synthetic import grid_city
from marl_amod.scenario.types import City
from marl_amod.scenario.variants import parse as parse_variant

DEFAULT_SCENARIO = "synthetic"


class _Spec(BaseModel):
    # allow_inf_nan=False: an infinite tstep or fare is a config error, not an `inf` result
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    name: str
    description: str = ""
    horizon: int = Field(20, ge=1, le=100_000, description="control steps (dispatch rounds) per episode")
    events: list[DemandEvent] = Field(default_factory=list, description="demand shocks the forecast does not know (scenario/events.py)")
    _source: str = PrivateAttr("")  # the YAML file, so errors found while building name it

    @model_validator(mode="before")
    @classmethod
    def _numbers_are_numbers(cls, raw: Any) -> Any:
        """``rows: true`` or ``tstep: "3"`` would pass pydantic's lax coercion (True == 1); a
        number field takes a number (numpy scalars included), never a bool or a string."""
        if isinstance(raw, dict):
            for key, value in raw.items():
                field = cls.model_fields.get(key)
                if field is None or not _is_numeric(field.annotation):
                    continue
                if isinstance(value, (bool, np.bool_, str)):
                    raise ValueError(f"{key} must be a number, got {value!r}")
        return raw


class JsonScenario(_Spec):
    """A real city from an RL4AMOD JSON file under the data directory."""

    source: Literal["json"]
    data_file: str = Field(description="path relative to MARL_AMOD_DATA")
    tstep: float = Field(3.0, gt=0, description="minutes per step")
    start_hour: int = Field(ge=0, le=23, description="json_hr: clock hour of step 0")
    demand_ratio: float = Field(gt=0, description="multiplier on the data's demand")
    beta: float = Field(ge=0, description="operating cost per minute of driving")
    fleet: int | None = Field(None, gt=0, description="total vehicles; default from totalAcc")


class SyntheticScenario(_Spec):
    """A generated grid city; needs no data."""

    source: Literal["synthetic"]
    rows: int = Field(4, ge=1)
    cols: int = Field(4, ge=1)
    seed: int = 0
    tstep: float = Field(3.0, gt=0)
    beta: float = Field(0.5, ge=0)
    step_time: int = Field(1, ge=1)
    requests_per_region: float = Field(3.0, gt=0)
    imbalance: float = Field(0.8, ge=0, lt=1)
    trip_length_preference: float = 0.5
    fare_per_step: float = Field(4.0, gt=0)
    vehicles_per_region: int = Field(12, ge=1)  # an empty fleet serves nobody: a typo, not a scenario

    @model_validator(mode="after")
    def _two_regions(self) -> SyntheticScenario:
        if self.rows * self.cols < 2:
            raise ValueError(f"a grid city needs at least 2 regions, got rows x cols = {self.rows}x{self.cols}")
        return self


class SumoScenario(_Spec):
    """A road network simulated in SUMO (mesoscopic by default): an OSM extract or a grid."""

    source: Literal["sumo"]
    network: Literal["osm", "grid"]
    osm_file: str | None = Field(None, description="OpenStreetMap file relative to MARL_AMOD_DATA (network: osm)")
    grid_size: int = Field(6, ge=2, description="junctions per side (network: grid)")
    grid_length: float = Field(400.0, gt=0, description="metres between junctions (network: grid)")
    seed: int = Field(0, description="seeds netgenerate, the k-means regions and SUMO")
    regions: int = Field(10, ge=2)
    tstep: float = Field(3.0, gt=0, description="minutes per control step (dispatch and rebalancing)")
    start_hour: float = Field(16.0, ge=0, lt=24)
    fleet: int = Field(gt=0)
    requests_per_hour: float = Field(gt=0, description="expected requests per hour, whole city")
    imbalance: float = Field(0.5, ge=0, description="centre-to-periphery skew of the evening peak")
    mean_trip_min: float = Field(10.0, gt=0, description="gravity-model deterrence scale")
    peak: float = Field(0.3, ge=0, description="demand mid-window is (1 + peak) x the base")
    fare_base: float = Field(2.6, ge=0)
    fare_per_km: float = Field(1.9, ge=0)
    beta: float = Field(0.3, ge=0, description="operating cost per minute of driving")
    max_wait_min: float = Field(10.0, ge=0, description="a request leaves after waiting this long")
    mode: Literal["meso", "micro", "macro"] = Field("meso", description="macro: the same city in the macro model")
    backend: Literal["libsumo", "traci"] = "libsumo"
    step_length: float = Field(1.0, gt=0, description="SUMO seconds per simulation step")
    refresh_travel_times: bool = Field(True, description="region travel times follow SUMO's edge times each step")
    dispatch_every_min: float | None = Field(None, gt=0, description="match requests this often (divides tstep)")
    taxi_device: bool = Field(False, description="fleet as SUMO taxis, requests as persons (else one vehicle per leg)")
    background_per_hour: float = Field(0.0, ge=0, description="random background cars per hour (SUMO's randomTrips.py)")
    sumo_args: list[str] = Field(default_factory=list, description="extra SUMO options, e.g. [--tripinfo-output, t.xml]")

    @model_validator(mode="after")
    def _network_source(self) -> SumoScenario:
        if self.network == "osm" and not self.osm_file:
            raise ValueError("network 'osm' needs osm_file (a path under MARL_AMOD_DATA)")
        if self.network == "grid" and self.osm_file:
            raise ValueError("network 'grid' takes no osm_file")
        if self.dispatch_every_min is not None:
            rounds = self.tstep / self.dispatch_every_min
            if abs(rounds - round(rounds)) > 1e-9 or rounds < 1:
                raise ValueError(f"dispatch_every_min {self.dispatch_every_min} must divide tstep {self.tstep}")
        return self


def _is_numeric(annotation: Any) -> bool:
    """True for int, float and their optionals (``int | None``)."""
    return annotation in (int, float) or any(a in (int, float) for a in get_args(annotation))


ScenarioSpec = JsonScenario | SyntheticScenario | SumoScenario


def scenario_dirs() -> list[Path]:
    """Folders searched for bundled scenario YAML files (repo checkout, then installed wheel)."""
    here = Path(__file__).resolve().parent.parent
    return [p for p in (here.parent / "envs", here / "_scenarios") if p.is_dir()]


def available() -> list[str]:
    """Names of the bundled scenarios."""
    names = {p.stem for d in scenario_dirs() for p in d.glob("*.yaml")}
    return sorted(names)


def _find(name_or_path: str) -> Path:
    path = Path(name_or_path)
    if path.suffix in (".yaml", ".yml"):
        if not path.is_file():
            raise ConfigError(f"scenario file not found: {path}")
        return path
    for d in scenario_dirs():
        candidate = d / f"{name_or_path}.yaml"
        if candidate.is_file():
            return candidate
    raise ConfigError(f"unknown scenario {name_or_path!r}; known: {', '.join(available())} (or give a .yaml path)")


def _read_scenario(path: Path, chain: tuple[Path, ...]) -> dict[str, Any]:
    """A scenario's keys; ``extends: <scenario>`` starts from another scenario's keys (so a
    variant names only what it changes instead of copying its base). The base's ``name`` is never
    inherited: a variant without one is named after its file, since results, policy cards and
    ``results_tables.py --add`` file everything under the city's name."""
    raw = read_yaml(path, "scenario file")
    base = raw.pop("extends", None)
    if base is None:
        return raw
    if not isinstance(base, str):
        raise ConfigError(f"{path}: 'extends' must name one scenario, got {base!r}")
    if not base.endswith((".yaml", ".yml")) and base not in available() and (path.parent / f"{base}.yaml").is_file():
        raise ConfigError(f"{path}: 'extends: {base}' names a bundled scenario; for {base}.yaml beside it write 'extends: {base}.yaml'")
    base_path = _find(str(path.parent / base) if base.endswith((".yaml", ".yml")) else base)
    if base_path.resolve() in (*chain, path.resolve()):
        raise ConfigError(f"{path}: 'extends: {base}' makes a cycle")
    return {**_read_scenario(base_path, (*chain, path.resolve())), "name": path.stem, **raw}


def load_spec(name_or_path: str, **overrides: Any) -> ScenarioSpec:
    """Read and validate a scenario YAML; keyword overrides replace its keys."""
    path = _find(name_or_path)
    raw = _read_scenario(path, ())
    raw.update({k: v for k, v in overrides.items() if v is not None})
    source = raw.get("source")
    model = {"json": JsonScenario, "synthetic": SyntheticScenario, "sumo": SumoScenario}.get(source)
    if model is None:
        if not raw:
            raise ConfigError(f"{path}: the scenario file is empty; a scenario needs at least 'source' (json, synthetic or sumo)")
        raise ConfigError(f"{path}: 'source' must be 'json', 'synthetic' or 'sumo', got {source!r}")
    try:
        spec = model(**raw)
    except ValidationError as exc:
        problems = "; ".join(_problem(e, model, source, overrides) for e in exc.errors())
        raise ConfigError(f"invalid scenario {path}: {problems}") from exc
    spec._source = str(path)
    return spec


def _problem(err: Any, model: type[_Spec], source: str, overrides: dict[str, Any]) -> str:
    """One pydantic error as ``key: message``; an unknown top-level key (a typo, or a keyword
    override such as ``fleet=`` on a scenario that has no fleet) lists the keys that exist."""
    loc = err["loc"]
    key, msg = pydantic_problem(err, words=UNKNOWN_KEY)
    if err["type"] == "extra_forbidden" and len(loc) == 1:
        given = " (a keyword override)" if loc[0] in overrides else ""
        msg = f"unknown key{given}; a {source} scenario has {', '.join(k for k in model.model_fields if k != 'source')}"
    return (f"{key}: " if key else "") + msg


def build_city(spec: ScenarioSpec) -> City:
    """Turn a validated spec into a :class:`City`, its events applied to the realised demand."""
    return apply_events(_base_city(spec), spec.events, spec._source or f"scenario {spec.name!r}")


def _base_city(spec: ScenarioSpec) -> City:
    if isinstance(spec, SyntheticScenario):
        params = spec.model_dump(exclude={"source", "description", "name", "events"})
        return grid_city(name=spec.name, **params)
    if isinstance(spec, SumoScenario):
        return _build_sumo_city(spec)
    return load_json_city(
        resolve(spec.data_file),
        name=spec.name,
        tstep=spec.tstep,
        start_hour=spec.start_hour,
        demand_ratio=spec.demand_ratio,
        beta=spec.beta,
        horizon=spec.horizon,
        fleet=spec.fleet,
    )


def _build_sumo_city(spec: SumoScenario) -> City:
    from marl_amod.scenario.sumo.city import build_sumo_city  # loads the network tools only when needed

    return build_sumo_city(spec)


_CACHE: dict[tuple, City] = {}
_CACHE_SIZE = 32


def _identity(relative: str | None) -> tuple:
    """A data file's resolved path, modification time and size: a new file is a new city."""
    if relative is None:
        return ()
    path = resolve(relative).resolve()
    st = path.stat()
    return (str(path), st.st_mtime_ns, st.st_size)


def load_city(name_or_path: str = DEFAULT_SCENARIO, **overrides: Any) -> City:
    """The city for a scenario name (see :func:`available`) or YAML path, or a variant of one
    (``<scenario>~hot...``, ``<scenario>~skew...``, ``<scenario>~ev...``: :mod:`.variants`), built on the scenario with the
    overrides applied.

    Cached on the validated scenario keys and the identity (resolved path, mtime, size) of its data
    file, so pointing ``MARL_AMOD_DATA`` elsewhere or replacing the file gives the new city. The
    cached city's arrays are read-only, so sharing one object between callers is safe. A variant is
    rebuilt from its cached base on each call (a few array operations).
    """
    base, variant = parse_variant(str(name_or_path))
    if variant is not None:
        return variant(load_city(base, **overrides))
    spec = load_spec(str(name_or_path), **overrides)
    data_file = spec.data_file if isinstance(spec, JsonScenario) else getattr(spec, "osm_file", None)
    key = (type(spec).__name__, spec.model_dump_json(), _identity(data_file))
    city = _CACHE.get(key)
    if city is None:
        city = build_city(spec)
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = city
    return city


@dataclass(frozen=True)
class ScenarioInfo:
    """One row of the scenario catalogue, read from the YAML alone (no city is built, so listing
    stays instant and a broken file or missing data spoils only its own row)."""

    name: str
    source: str = "-"  # json | synthetic | sumo meso | sumo micro | sumo macro (+ taxi)
    regions: int | None = None  # None: known only after reading the data file
    fleet: int | None = None
    horizon: int | None = None
    tstep: float | None = None
    needs: tuple[str, ...] = ()  # "data" (MARL_AMOD_DATA), "sumo" (the [sumo] extra)
    description: str = ""
    error: str | None = None  # the scenario file is invalid


def describe(name_or_path: str) -> ScenarioInfo:
    """What a scenario's YAML says about it, without building the city."""
    try:
        spec = load_spec(name_or_path)
    except ConfigError as exc:
        return ScenarioInfo(name=Path(name_or_path).stem, error=str(exc))
    common = {"name": spec.name, "horizon": spec.horizon, "tstep": spec.tstep, "description": spec.description}
    if isinstance(spec, SyntheticScenario):
        n = spec.rows * spec.cols
        return ScenarioInfo(source="synthetic", regions=n, fleet=n * spec.vehicles_per_region, **common)
    if isinstance(spec, SumoScenario):
        source = f"sumo {spec.mode}" + (" taxi" if spec.taxi_device else "")
        needs = ("data", "sumo") if spec.network == "osm" else ("sumo",)
        return ScenarioInfo(source=source, regions=spec.regions, fleet=spec.fleet, needs=needs, **common)
    return ScenarioInfo(source="json", fleet=spec.fleet, needs=("data",), **common)


def catalogue() -> list[ScenarioInfo]:
    """Every bundled scenario, described from its YAML (see :func:`describe`)."""
    return [describe(name) for name in available()]
