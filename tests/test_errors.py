"""The one-line form of pydantic's errors (errors.pydantic_problem/s), pinned at every place that uses it."""

from __future__ import annotations

from pathlib import Path

import pytest
from pydantic import BaseModel, ConfigDict, ValidationError, model_validator

from marl_amod.checkpoints import _card_of, _selection
from marl_amod.config import problems
from marl_amod.errors import UNKNOWN_KEY, ConfigError, DataError, pydantic_problem, pydantic_problems
from marl_amod.scenario import grid_city, load_city
from marl_amod.scenario.variants import event_task


class _M(BaseModel):
    model_config = ConfigDict(extra="forbid")
    a: int
    b: int = 0

    @model_validator(mode="after")
    def _whole(self) -> _M:
        if self.b < 0:
            raise ValueError("b must be >= 0")
        return self


def _errors(**values) -> ValidationError:
    with pytest.raises(ValidationError) as info:
        _M(**values)
    return info.value


def test_the_helper_names_the_key_and_says_the_message_in_the_librarys_words():
    exc = _errors(a="x", c=1)
    assert pydantic_problems(exc) == "a: Input should be a valid integer, unable to parse string as an integer; c: Extra inputs are not permitted"
    assert pydantic_problems(exc, UNKNOWN_KEY).endswith("; c: unknown key")
    assert pydantic_problem(exc.errors()[1], ("args",), UNKNOWN_KEY) == ("args.c", "unknown key")
    assert pydantic_problems(_errors(a=1, b=-1)) == "b must be >= 0"  # the whole model: no key, no "Value error, "
    assert pydantic_problems(_errors(), {"missing": "missing"}) == "a: missing"


def test_every_caller_keeps_its_message():
    assert str(problems("x.yaml", _errors(a=1, b=-1))) == "x.yaml: config: b must be >= 0"
    assert str(problems("x.yaml", _errors(a=1, c=2), "args")) == "x.yaml: args.c: unknown key"
    with pytest.raises(ConfigError) as info:
        _selection({"candidates": 1, "concentration": 1.0, "candidatez": 2})
    assert str(info.value) == "selection: candidatez: Extra inputs are not permitted"
    with pytest.raises(ConfigError) as info:
        _selection({"candidates": 1})
    assert str(info.value) == "selection: concentration: Field required"
    with pytest.raises(DataError) as info:
        _card_of(Path("p.pt"), {"scenario": "s", "algorithm": "a", "mode": "m", "conv": "gcn", "hidden": "h", "n_features": 3,
                                "lookahead": 1, "seed": 0})  # fmt: skip
    assert str(info.value) == "p.pt: its card is incomplete (actor: missing; hidden: Input should be a valid integer, unable to parse string as an integer)"
    with pytest.raises(ConfigError) as info:
        event_task(grid_city(rows=2, cols=2), [0], 2.0, 3, 3)
    assert str(info.value) == "event task of grid2x2, its surge: event 'surge': end (3) must be after start (3)"
    with pytest.raises(ConfigError) as info:
        load_city("synthetic", fleet=3)
    assert "invalid scenario" in str(info.value) and ": fleet: unknown key (a keyword override); a synthetic scenario has " in str(info.value)
