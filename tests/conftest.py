"""Shared fixtures: small cities, and real-city data when MARL_AMOD_DATA points at it."""

from __future__ import annotations

import os
from pathlib import Path

import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

from marl_amod.data import ENV_VAR  # noqa: E402
from marl_amod.scenario import City, grid_city  # noqa: E402

REAL_CITIES = [
    "chicago", "nyc_brooklyn", "nyc_man_middle", "nyc_man_north", "nyc_man_south", "porto", "rome",
    "san_francisco", "shenzhen_baoan", "shenzhen_downtown_east", "shenzhen_downtown_west", "shenzhen_north",
    "washington_dc",
]


def has_data() -> bool:
    value = os.environ.get(ENV_VAR)
    return bool(value) and (Path(value) / "macro").is_dir()


needs_data = pytest.mark.skipif(not has_data(), reason=f"set {ENV_VAR} to the data folder to run real-city tests")


def pytest_collection_modifyitems(config, items):
    """Tests marked ``slow`` (a whole city in SUMO, several starts) run with MARL_AMOD_SLOW=1."""
    if os.environ.get("MARL_AMOD_SLOW") == "1":
        return
    skip = pytest.mark.skip(reason="slow: set MARL_AMOD_SLOW=1 to run")
    for item in items:
        if "slow" in item.keywords:
            item.add_marker(skip)


@pytest.fixture(scope="session", autouse=True)
def _private_network_cache(tmp_path_factory):
    """SUMO networks built by tests go to a folder the test session owns, never the user's cache."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("MARL_AMOD_CACHE", str(tmp_path_factory.mktemp("sumo_cache")))
        yield


@pytest.fixture(scope="session", autouse=True)
def _private_sb3_logs(tmp_path_factory):
    """SB3 makes a log folder per ``learn()`` (``/tmp/SB3-<time>`` unless SB3_LOGDIR is set), even at
    verbose=0: the suite's, the docs' blocks' and the examples' (subprocesses inherit it) go to a
    folder the test session owns, so runs leave nothing behind."""
    with pytest.MonkeyPatch.context() as mp:
        mp.setenv("SB3_LOGDIR", str(tmp_path_factory.mktemp("sb3_logs")))
        yield


@pytest.fixture
def tiny_city() -> City:
    """A 3x3 grid with a 6-step horizon: fast enough for per-step property tests."""
    return grid_city(3, 3, seed=1, horizon=6, vehicles_per_region=5, requests_per_region=3.0)


@pytest.fixture
def small_city() -> City:
    """The default synthetic city (4x4, 20 steps)."""
    return grid_city(4, 4, seed=0)


@pytest.fixture(scope="session")
def tiny_prop_dataset(tmp_path_factory) -> tuple[str, str]:
    """(scenario yaml, dataset path): a 3x3 grid and 4 episodes of PROP with its card, shared by
    the offline-learning and fine-tuning tests."""
    import yaml

    from marl_amod.datasets import collect, write_card
    from marl_amod.policies import make_policy
    from marl_amod.scenario import load_city

    root = tmp_path_factory.mktemp("offline")
    scenario = root / "tiny.yaml"
    scenario.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    city = load_city(str(scenario))
    data = collect(city, make_policy("prop", city), episodes=4, seed=0)
    path = data.save(root / "tiny_prop.npz")
    write_card(path, data, city, make_policy("prop", city), eval_episodes=1, eval_seed=0)
    return str(scenario), str(path)


def ctrl_c_after(monkeypatch: pytest.MonkeyPatch, episode: int) -> None:
    """Training runs (those that close their episodes through ``EpisodeBook``) raise KeyboardInterrupt,
    as a Ctrl-C would, right after logging ``episode``, until ``monkeypatch.undo()``."""
    from marl_amod.algos import common

    real = common.EpisodeBook.close

    def close(self, ep, *a, **k):
        stop = real(self, ep, *a, **k)
        if ep == episode:
            raise KeyboardInterrupt
        return stop

    monkeypatch.setattr(common.EpisodeBook, "close", close)
