"""Disturbances declared in a scenario: demand shocks that the usual forecast does not know about.

A scenario YAML may list ``events``; each one multiplies the expected requests out of and/or into
a set of regions over a window of control steps::

    events:
      - name: concert
        regions: [3, 7]        # region indices of the city
        start: 8               # first affected control step
        end: 14                # first step after the event (exclusive)
        multiplier: 4.0        # x requests in the window
        direction: out         # out of the regions (default), into them, or both

The city built from such a scenario keeps two demand tables: ``demand_rate`` (what the simulator
draws, event included) and ``forecast_rate`` (the usual expected demand, event excluded). Policies
that plan on expectations (MPC-Forecast, the behaviour heuristics, the RL observations) read the
forecast; MPC-Oracle reads the realised draw. Fares and trip times of a pair are unchanged, so only
pairs that have demand in the data can grow (the data has no fare for the others).
"""

from __future__ import annotations

import dataclasses
from typing import Any, Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator

from marl_amod.errors import ConfigError
from marl_amod.scenario.types import City


class DemandEvent(BaseModel):
    """A demand shock: ``multiplier`` x the expected requests of the regions' trips in [start, end)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)
    name: str = "event"
    regions: list[int] = Field(min_length=1, description="affected region indices")
    start: int = Field(ge=0, description="first affected control step")
    end: int = Field(ge=1, description="first control step after the event (exclusive)")
    multiplier: float = Field(ge=0, le=1000, description="factor on the affected expected requests")
    direction: Literal["out", "in", "both"] = Field("out", description="trips leaving, entering, or touching the regions")

    @model_validator(mode="before")
    @classmethod
    def _no_bools_or_strings(cls, raw: Any) -> Any:
        """``multiplier: true`` would pass pydantic's lax coercion as 1.0; a number is a number."""
        if isinstance(raw, dict):
            for key in ("start", "end", "multiplier"):
                if isinstance(raw.get(key), (bool, np.bool_, str)):
                    raise ValueError(f"{key} must be a number, got {raw[key]!r}")
            regions = raw.get("regions")
            if isinstance(regions, list) and any(isinstance(r, (bool, np.bool_, str, float)) for r in regions):
                raise ValueError(f"regions must be integer region indices, got {regions!r}")
        return raw

    @model_validator(mode="after")
    def _window_and_regions(self) -> DemandEvent:
        if self.end <= self.start:
            raise ValueError(f"event {self.name!r}: end ({self.end}) must be after start ({self.start})")
        if min(self.regions) < 0 or len(set(self.regions)) != len(self.regions):
            raise ValueError(f"event {self.name!r}: regions must be distinct indices >= 0, got {self.regions}")
        return self

    def factor(self, n_steps: int, n_regions: int) -> np.ndarray:
        """(S, N, N) multiplicative factor of this event on the demand table (1 outside it)."""
        inside = np.zeros(n_regions, dtype=bool)
        inside[self.regions] = True
        if self.direction == "out":
            pairs = np.broadcast_to(inside[:, None], (n_regions, n_regions))
        elif self.direction == "in":
            pairs = np.broadcast_to(inside[None, :], (n_regions, n_regions))
        else:
            pairs = inside[:, None] | inside[None, :]
        f = np.ones((n_steps, n_regions, n_regions))
        f[self.start : min(self.end, n_steps)] = np.where(pairs, self.multiplier, 1.0)
        return f


def apply_events(city: City, events: list[DemandEvent] | tuple[DemandEvent, ...], where: str = "") -> City:
    """``city`` whose realised demand carries the events and whose forecast does not.

    Raises ConfigError naming ``where`` (the scenario file) and the event's key when a region or
    the window lies outside the city.
    """
    if not events:
        return city
    n, s = city.n_regions, city.n_steps
    factor = np.ones((s, n, n))
    for k, ev in enumerate(events):
        key = f"{where}: events.{k}" if where else f"events.{k}"
        bad = [r for r in ev.regions if r >= n]
        if bad:
            raise ConfigError(f"{key}.regions: region {bad[0]} is out of range; {city.name} has regions 0..{n - 1}")
        if ev.start >= city.horizon:
            raise ConfigError(f"{key}.start: step {ev.start} is past the episode's last control step {city.horizon - 1}")
        factor *= ev.factor(s, n)
    return dataclasses.replace(
        city,
        demand_rate=np.asarray(city.demand_rate) * factor,
        forecast_rate=np.asarray(city.forecast_rate).copy(),
        meta={**city.meta, "events": [*city.meta.get("events", []), *(ev.model_dump() for ev in events)]},  # a variant's on the YAML's
    )
