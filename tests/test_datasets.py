"""Offline datasets: the documented .npz round-trips and reads as per-agent transitions."""

from __future__ import annotations

import numpy as np
import pytest
from typer.testing import CliRunner

from marl_amod.cli import app
from marl_amod.datasets import ARRAY_KEYS, OfflineDataset, agent_transitions, collect
from marl_amod.errors import DataError
from marl_amod.policies import make_policy


@pytest.fixture
def dataset(tiny_city) -> OfflineDataset:
    return collect(tiny_city, make_policy("prop", tiny_city), episodes=2, seed=3)


def test_dataset_round_trips_through_npz(dataset, tmp_path):
    path = dataset.save(tmp_path / "sub" / "d.npz")
    back = OfflineDataset.load(path)
    for key in (*ARRAY_KEYS, "edge_index"):
        assert np.array_equal(getattr(back, key), getattr(dataset, key)), key
        assert getattr(back, key).dtype == getattr(dataset, key).dtype
    assert back.feature_names == dataset.feature_names and back.meta == dataset.meta


def test_dataset_contents_are_consistent(tiny_city, dataset):
    steps = tiny_city.horizon - 1
    n = tiny_city.n_regions
    assert len(dataset) == 2 * steps
    assert dataset.observation.shape == (2 * steps, n, len(dataset.feature_names))
    assert dataset.done.sum() == 2 and dataset.done[steps - 1] and dataset.done[-1]
    assert np.allclose(dataset.action.sum(axis=1), 1, atol=1e-5) and np.all(dataset.action >= 0)
    assert np.allclose(dataset.region_reward.sum(axis=1), dataset.reward, rtol=1e-4, atol=1e-2)
    within = ~dataset.done[:-1]
    assert np.array_equal(dataset.next_observation[:-1][within], dataset.observation[1:][within])


def test_dataset_rewards_match_evaluation(tiny_city, dataset):
    from marl_amod.evaluation import evaluate

    profits = evaluate("prop", tiny_city, episodes=2, seed=3)["per_episode"]
    # episode profit = first dispatch (not a transition) + transition rewards; transitions are the larger part
    for ep, m in enumerate(profits):
        assert dataset.reward[dataset.episode == ep].sum() <= m["profit"] + 1e-3


def test_agent_view_has_one_transition_stream_per_region(tiny_city, dataset):
    agents = agent_transitions(dataset)
    assert list(agents) == [f"region_{i}" for i in range(tiny_city.n_regions)]
    a = agents["region_2"]
    assert a["observation"].shape == (len(dataset), dataset.observation.shape[2])
    assert a["action"].shape == (len(dataset), 1)
    assert np.array_equal(a["reward"], dataset.region_reward[:, 2])


def test_loading_a_foreign_file_is_a_data_error(tmp_path):
    with pytest.raises(DataError):
        OfflineDataset.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(DataError):
        OfflineDataset.load(tmp_path / "other.npz")


def test_cli_collect_writes_a_dataset(tmp_path):
    out = tmp_path / "data.npz"
    result = CliRunner().invoke(app, ["collect", "--policy", "dtv", "--episodes", "1", "--seed", "1", "--output", str(out)])
    assert result.exit_code == 0, result.output
    data = OfflineDataset.load(out)
    assert data.meta["policy"] == "dtv" and data.done.sum() == 1
