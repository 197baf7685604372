"""Scenario variants by name: a scenario with one change to its demand, rebuilt from the name alone.

Four forms, appended to any scenario (a bundled name or a YAML path)::

    <scenario>~hot<region>x<multiplier>[@<start>-<end>]        a hotspot, all day or over a window (:func:`hotspot`)
    <scenario>~sink<region>x<multiplier>                       a sink of the trips (:func:`sink`)
    <scenario>~skew<gamma>                                     a more (or less) skewed demand (:func:`skew`)
    <scenario>~ev<r>+<r>x<m>@<start>-<end>[dr<r>+<r>x<m>]      a special event (:func:`event_task`)

``porto~hot1x2.5`` is Porto with the requests out of region 1 x2.5 against the rest, in the draw
and the forecast (another city, which the features show), and ``porto~hot1x2.5@15-20`` the same over
control steps [15, 20) only; ``porto~ev3+7x4@5-12dr0+1x0.5`` is Porto
whose requests out of regions 3 and 7 are x4 over control steps [5, 12) while those out of 0 and 1
are x0.5, in the draw only (a shock the forecast does not know, as a scenario's ``events``);
``porto~sink4x3`` is Porto with every origin's requests *to* region 4 x3 against its other
destinations, in the draw and the forecast (the fleet drains into region 4);
``porto~skew1.6`` is Porto with every region's requests out x (its share / the average share) ^ 0.6,
in the draw and the forecast (big regions bigger, small ones smaller; gamma 1 is the city itself).

Why names: the meta study's tasks, their demonstrations, DAgger rounds and policy cards keep only a
name, and :func:`~marl_amod.scenario.registry.load_city` (hence the envs and every CLI command)
resolves it: the base scenario with its keyword overrides first, then the variant. Variants stack,
left to right (``porto~hot1x3~ev2x4@0-6`` is the event on the hotspot variant). The numbers in a
name are exact (:func:`hotspot_name`, :func:`sink_name`, :func:`skew_name`, :func:`event_name`), so the name rebuilds the city bit for bit.
"""

from __future__ import annotations

import re
from collections.abc import Callable
from dataclasses import replace
from functools import partial

import numpy as np
from pydantic import ValidationError

from marl_amod.errors import ConfigError, pydantic_problems
from marl_amod.scenario.events import DemandEvent, apply_events
from marl_amod.scenario.types import City

HOTSPOT = "~hot"  # "<scenario>~hot<region>x<multiplier>[@<start>-<end>]": the scenario with that hotspot
SINK = "~sink"  # "<scenario>~sink<region>x<multiplier>": the scenario with the trips into that region x the multiplier
SKEW = "~skew"  # "<scenario>~skew<gamma>": the scenario with its origin shares raised to that power
EVENT = "~ev"  # "<scenario>~ev<r>+<r>x<m>@<start>-<end>[dr<r>+<r>x<m>]": the scenario with that event
FORMS = (
    f"<scenario>{HOTSPOT}<region>x<multiplier>[@<start>-<end>] (a hotspot, e.g. porto{HOTSPOT}1x2.5 or porto{HOTSPOT}1x2.5@15-20), "
    f"<scenario>{SINK}<region>x<multiplier> (a sink, e.g. porto{SINK}4x3), "
    f"<scenario>{SKEW}<gamma> (a demand shape, e.g. porto{SKEW}1.6) or "
    f"<scenario>{EVENT}<r>+<r>x<m>@<start>-<end>[dr<r>+<r>x<m>] (an event, e.g. porto{EVENT}3+7x4@5-12dr0+1x0.5)"
)

_NUMBER = r"\d+(?:\.\d+)?"  # what _number writes: no sign, no exponent
_REGIONS = r"\d+(?:\+\d+)*"
_HOTSPOT_RE = re.compile(rf"(?P<region>\d+)x(?P<m>{_NUMBER})")
_WINDOWED_RE = re.compile(_HOTSPOT_RE.pattern + r"(?:@(?P<s>\d+)-(?P<e>\d+))?")  # a hotspot, over a window of steps or not
_SKEW_RE = re.compile(rf"(?P<g>{_NUMBER})")
_EVENT_RE = re.compile(rf"(?P<up>{_REGIONS})x(?P<m>{_NUMBER})@(?P<s>\d+)-(?P<e>\d+)(?:dr(?P<down>{_REGIONS})x(?P<dm>{_NUMBER}))?")


# --------------------------------------------------------------------------------------------
# The four variants
# --------------------------------------------------------------------------------------------
def hotspot(city: City, region: int, multiplier: float, start: int | None = None, end: int | None = None) -> City:
    """``city`` with the requests out of ``region`` x ``multiplier`` against the rest, every step's
    total kept (the same fleet against the same demand, only more of it in one place), in the draw
    *and* the forecast: another city (the features show it), not a shock. Why: the held-out cities'
    busiest region draws 4.6 (San Francisco) and 5.1 (Brooklyn) times a region's average share of
    the requests, every training city's at most 4.2, and MPC-Forecast sends it 0.29-0.31 of the
    idle fleet against at most 0.14 in a training city; the meta policy, never shown that, sends
    0.15-0.25 (docs/meta/log.md, "Where the held-out gap comes from").

    With ``start`` and ``end`` only control steps [start, end) change (end capped at the tables'
    steps): a hotspot that rises during the day, as San Francisco's busiest region's share does at
    step 15, where the meta policy stops sending it vehicles that MPC-Forecast sends
    (docs/meta/log.md, "Which steps hold the held-out gap")."""
    if not 0 <= region < city.n_regions or not np.isfinite(multiplier) or multiplier <= 0:
        raise ConfigError(f"hotspot of {city.name}: region {region} (0..{city.n_regions - 1}) and multiplier {multiplier} (> 0)")
    if (start is None) != (end is None):
        raise ConfigError(f"hotspot of {city.name}: a window needs both start and end, got start {start}, end {end}")
    if start is not None and (not 0 <= start < end or start >= city.horizon):
        raise ConfigError(f"hotspot of {city.name}: window [{start}, {end}) must satisfy 0 <= start < end and start < the horizon {city.horizon}")
    factor = np.ones((city.n_steps, city.n_regions))
    factor[slice(start, end), region] = multiplier  # all day without a window
    window = {} if start is None else {"start": start, "end": end}
    return _reweighted(city, factor, hotspot_name(city.name, region, multiplier, start, end),
                       {"hotspot": {"region": region, "multiplier": multiplier, **window}})  # fmt: skip


def skew(city: City, gamma: float) -> City:
    """``city`` with every region's requests out x (s_r / mean(s)) ^ (gamma - 1), s_r the region's
    share of the day's requests out (the forecast's over the episode, as
    :func:`~marl_amod.algos.meta.place_table` reports it), every step's total kept, in the draw
    *and* the forecast: gamma > 1 makes big regions bigger and small ones smaller (the shares go
    roughly as s_r ^ gamma), gamma 1 is the city itself. Why: the held-out cities differ from the
    training cities in the shape of their demand, not one region: the median Brooklyn region draws
    0.10 of the average share (San Francisco 0.29, the training cities' median 0.74), the busiest
    5.1x it (4.6; the training cities at most 4.2); a hotspot raises one region only
    (docs/meta/log.md, "Demand-shape variants")."""
    if not np.isfinite(gamma) or gamma <= 0:
        raise ConfigError(f"skew of {city.name}: gamma {gamma} (a finite number > 0; 1 is the city itself)")
    out = np.asarray(city.forecast_rate)[: city.horizon].sum(axis=(0, 2))  # (N,) expected requests out over the episode
    share = out / max(float(out.mean()), 1e-12)
    factor = np.where(share > 0, share, 1.0) ** (gamma - 1.0)  # a region without requests stays without them
    return _reweighted(city, factor, skew_name(city.name, gamma), {"skew": {"gamma": gamma}})


def sink(city: City, region: int, multiplier: float) -> City:
    """``city`` with every origin's requests *to* ``region`` x ``multiplier`` against its other
    destinations, each origin's requests of every step kept (the same requests, other
    destinations), in the draw *and* the forecast. Fares and trip times stay those of each origin
    and destination. Why: in Brooklyn the trips in and out of a region differ by half of all trips
    (half the L1 distance between the regions' shares of requests out and in: 0.49, region 6 draws
    38% of the arrivals and 20% of the departures), in every training city by at most 0.26 (Porto),
    so no training city shows the fleet draining into one region and MPC-F's moves back against
    that drain; a sink raises it (docs/meta/log.md, "Where the held-out gap is now")."""
    if not 0 <= region < city.n_regions or not np.isfinite(multiplier) or multiplier <= 0:
        raise ConfigError(f"sink of {city.name}: region {region} (0..{city.n_regions - 1}) and multiplier {multiplier} (> 0)")
    factor = np.ones(city.n_regions)
    factor[region] = multiplier
    return _reweighted(city, factor, sink_name(city.name, region, multiplier), {"sink": {"region": region, "multiplier": multiplier}}, DESTINATIONS)


def in_out_imbalance(city: City) -> float:
    """Half the L1 distance between the regions' shares of the episode's expected requests out and
    in: the share of all trips that must come back by rebalancing for the fleet to keep its shape
    (0: every region receives what it sends). Brooklyn 0.49, the meta study's training cities 0.09-0.26."""
    rate = np.asarray(city.forecast_rate)[: city.horizon]
    out, into = rate.sum(axis=(0, 2)), rate.sum(axis=(0, 1))
    return float(np.abs(out - into).sum() / 2 / max(float(out.sum()), 1e-12))


ORIGINS = 1  # the axis of the rates (S, N, N) that :func:`_reweighted` weighs: requests out of each region,
DESTINATIONS = 2  # or requests into each region


def _reweighted(city: City, factor: np.ndarray, name: str, meta: dict, axis: int = ORIGINS) -> City:
    """``city`` with the requests out of (``ORIGINS``) or into (``DESTINATIONS``) each region x
    ``factor`` (N,), or (S, N) for a factor that changes with the step, in the draw and the forecast,
    named ``name``, ``meta`` added to its meta. Kept: every step's total (origins), or every step's
    requests out of each origin (destinations: the same requests, other destinations)."""
    shape, kept = [1, 1, 1], ((1, 2) if axis == ORIGINS else (2,))
    shape[axis] = city.n_regions
    if factor.ndim == 2:  # (S, N): the step on the first axis
        shape[0] = city.n_steps
    weight = factor.reshape(shape)

    def raised(rate: np.ndarray) -> np.ndarray:
        new = np.asarray(rate) * weight  # (S, N, N): origins on axis 1, destinations on axis 2
        total, now = np.asarray(rate).sum(axis=kept, keepdims=True), new.sum(axis=kept, keepdims=True)
        return new * np.where(now > 0, total / np.maximum(now, 1e-12), 1.0)

    return replace(city, name=name, demand_rate=raised(city.demand_rate), forecast_rate=raised(city.forecast_rate), meta={**city.meta, **meta})


def event_task(city: City, surge: list[int], multiplier: float, start: int, end: int, drop: list[int] = (), drop_multiplier: float = 1.0) -> City:
    """``city`` with one special event (:func:`~marl_amod.scenario.events.apply_events`): requests
    out of ``surge`` x ``multiplier`` over steps [start, end), and out of ``drop`` x
    ``drop_multiplier`` over the same window; the draw carries it, the forecast (what the features
    read) does not. Why: the Brooklyn event moves demand from its busiest regions to two small
    ones (their share x7 in the window), and the policies send the surge *fewer* vehicles inside
    the window than outside; a task whose every episode repeats one event lets the meta study's
    imitation show the memory a shock it can carry from one episode to the next."""
    events = []
    for what, regions, m in [("surge", surge, multiplier)] + ([("drop", drop, drop_multiplier)] if len(drop) else []):
        try:
            events.append(DemandEvent(name=what, regions=list(regions), start=start, end=end, multiplier=m))
        except ValidationError as err:  # one line naming the task, not pydantic's report
            raise ConfigError(f"event task of {city.name}, its {what}: {pydantic_problems(err)}") from None
    shocked = apply_events(city, events, f"event task of {city.name}")
    return replace(shocked, name=event_name(city.name, list(surge), multiplier, start, end, list(drop), drop_multiplier))


# --------------------------------------------------------------------------------------------
# Names: written exactly, parsed back
# --------------------------------------------------------------------------------------------
def hotspot_name(city: str, region: int, multiplier: float, start: int | None = None, end: int | None = None) -> str:
    """``<city>~hot<region>x<multiplier>`` and, over a window, ``@<start>-<end>``: the multiplier
    exactly (the name is what rebuilds the city) and short (3, not 3.0)."""
    window = "" if start is None else f"@{start}-{end}"
    return f"{city}{HOTSPOT}{region}x{_number(multiplier)}{window}"


def sink_name(city: str, region: int, multiplier: float) -> str:
    """``<city>~sink<region>x<multiplier>``, the multiplier exactly and short: the name :func:`parse` rebuilds :func:`sink` from."""
    return f"{city}{SINK}{region}x{_number(multiplier)}"


def skew_name(city: str, gamma: float) -> str:
    """``<city>~skew<gamma>``, gamma exactly and short (2, not 2.0): the name :func:`parse` rebuilds :func:`skew` from."""
    return f"{city}{SKEW}{_number(gamma)}"


def event_name(city: str, surge: list[int], multiplier: float, start: int, end: int, drop: list[int] = (), drop_multiplier: float = 1.0) -> str:
    """``<city>~ev<r>+<r>x<m>@<start>-<end>`` and, with ``drop``, ``dr<r>+<r>x<m>``: the name
    :func:`parse` rebuilds :func:`event_task` from."""
    name = f"{city}{EVENT}{'+'.join(map(str, surge))}x{_number(multiplier)}@{start}-{end}"
    return name + (f"dr{'+'.join(map(str, drop))}x{_number(drop_multiplier)}" if drop else "")


def _number(x: float) -> str:
    """A multiplier in a name: exact and short (3, not 3.0)."""
    return np.format_float_positional(float(x) + 0.0, trim="-")  # + 0.0: -0.0 would be named -0, which no name parses


def split(name: str) -> tuple[str, str | None]:
    """``(base, variant)`` of ``<base>~<variant>`` (the last ``~``: variants stack), or ``(name, None)``
    for a plain scenario; a ``.yaml`` path is always plain (a variant comes after its suffix)."""
    base, sep, variant = name.rpartition("~")
    if not sep or not base or name.endswith((".yaml", ".yml")):
        return name, None
    return base, sep + variant


def base_city(name: str) -> str:
    """The scenario a name is a variant of (itself for a plain scenario)."""
    while (parts := split(name))[1] is not None:
        name = parts[0]
    return name


def parse(name: str) -> tuple[str, Callable[[City], City] | None]:
    """``(base, change)``: the scenario a name's last variant applies to and the variant as a
    function of that city (None for a plain scenario). Checked before any city is built, so a
    malformed name is a one-line ConfigError naming the four forms, data or not."""
    base, variant = split(name)
    if variant is None:
        return name, None
    if variant.startswith(HOTSPOT) and (m := _WINDOWED_RE.fullmatch(variant.removeprefix(HOTSPOT))):
        window = {"start": int(m["s"]), "end": int(m["e"])} if m["s"] else {}
        return base, partial(hotspot, region=int(m["region"]), multiplier=float(m["m"]), **window)
    if variant.startswith(SINK) and (m := _HOTSPOT_RE.fullmatch(variant.removeprefix(SINK))):
        return base, partial(sink, region=int(m["region"]), multiplier=float(m["m"]))
    if variant.startswith(SKEW) and (m := _SKEW_RE.fullmatch(variant.removeprefix(SKEW))):
        return base, partial(skew, gamma=float(m["g"]))
    if variant.startswith(EVENT) and (m := _EVENT_RE.fullmatch(variant.removeprefix(EVENT))):
        regions = lambda text: [int(r) for r in text.split("+")]  # noqa: E731
        drop = {"drop": regions(m["down"]), "drop_multiplier": float(m["dm"])} if m["down"] else {}
        return base, partial(event_task, surge=regions(m["up"]), multiplier=float(m["m"]), start=int(m["s"]), end=int(m["e"]), **drop)
    raise ConfigError(f"scenario {name!r}: {variant!r} is no variant; a variant is named {FORMS}")
