"""Fitted Q evaluation: the logged behaviour's estimate is its logged return; a policy file is scored from the dataset alone."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from marl_amod import fqe
from marl_amod.datasets import OfflineDataset
from marl_amod.scenario import load_city


def test_fqe_of_the_logged_behaviour_is_its_logged_return(tiny_prop_dataset):
    """PROP is deterministic, so its own next actions are the logged ones: Q^PROP at the first
    states must come out as the logged episodes' mean return (4 episodes of 5 decisions, fitted
    to the last few dollars), and each first state's value as its own episode's return (the demand
    differs by episode, and the first states differ with it)."""
    scenario, path = tiny_prop_dataset
    data = OfflineDataset.load(path)
    returns = fqe.logged_returns(data)
    got = fqe.estimate(None, path, scenario, fqe.FQESettings(updates=3000, batch_size=32, hidden=32, lr=3e-3))
    assert len(got.per_start) == len(returns) == 4
    assert got.profit == pytest.approx(returns.mean(), rel=0.03)
    assert np.abs(got.per_start - returns).max() < 0.08 * returns.mean()


def test_a_policy_file_is_scored_from_the_dataset_deterministically_by_seed(tmp_path, tiny_prop_dataset):
    """A trained policy's estimate needs no env episode, repeats for a seed, and differs from the
    logged behaviour's where the policy plays otherwise."""
    from marl_amod.algos.registry import ALGOS, args_for

    scenario, path = tiny_prop_dataset
    ALGOS["bc"].train(args_for("bc", {"scenario": scenario, "dataset": path, "updates": 3, "batch_size": 8, "eval_every": 3,
                                      "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "run_dir": str(tmp_path / "run"),
                                      "policy_out": str(tmp_path / "bc.pt")}))  # fmt: skip
    settings = fqe.FQESettings(updates=50, batch_size=16, hidden=16)
    city = load_city(scenario)
    one, two = (fqe.estimate(tmp_path / "bc.pt", path, city, settings) for _ in range(2))
    assert np.isfinite(one.profit) and one.profit == two.profit
    logged = fqe.estimate(None, path, city, settings)
    assert logged.profit != one.profit
    next_action, start = fqe.policy_actions(tmp_path / "bc.pt", OfflineDataset.load(path), path, city)
    np.testing.assert_allclose(next_action.sum(-1).numpy(), 1.0, rtol=1e-5)
    assert start.shape == (4, city.n_regions)


def test_a_dataset_of_another_city_or_other_features_is_refused_before_fitting(tmp_path, tiny_prop_dataset):
    from marl_amod.algos.registry import ALGOS, args_for
    from marl_amod.errors import ConfigError, DataError

    scenario, path = tiny_prop_dataset
    with pytest.raises(DataError, match="collected on tiny .9 regions., this run is on synthetic .16"):
        fqe.estimate(None, path, "synthetic")
    ALGOS["bc"].train(args_for("bc", {"scenario": scenario, "dataset": path, "updates": 2, "batch_size": 8, "eval_every": 2,
                                      "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "run_dir": str(tmp_path / "run"),
                                      "policy_out": str(tmp_path / "bc.pt")}))  # fmt: skip
    data = OfflineDataset.load(path)
    other = OfflineDataset(**{**data.__dict__, "meta": {**data.meta, "lookahead": 2}})  # as if collected with --lookahead 2
    with pytest.raises(ConfigError, match="the policy reads lookahead 6: collect the data with --lookahead 6"):
        fqe.estimate(tmp_path / "bc.pt", path, scenario, loaded=other)


def test_the_fqe_command_prints_the_estimates_and_writes_them(tmp_path, tiny_prop_dataset):
    import json

    from typer.testing import CliRunner

    from marl_amod.cli import app

    scenario, path = tiny_prop_dataset
    out = tmp_path / "fqe.json"
    result = CliRunner().invoke(app, ["fqe", "--dataset", path, "--scenario", scenario, "--updates", "20", "--output", str(out)])
    assert result.exit_code == 0, result.output
    assert "logged behaviour" in result.output and "FQE estimate" in result.output
    assert "have not converged" in result.output  # 20 updates: the behaviour's estimate is far from its return
    got = json.loads(out.read_text())["policies"]["logged behaviour"]
    assert got["episodes"] == 4 and got["logged_return"] == pytest.approx(fqe.logged_returns(OfflineDataset.load(path)).mean())
    bad = CliRunner().invoke(app, ["fqe", "--dataset", str(tmp_path / "none.npz"), "--scenario", scenario])
    assert bad.exit_code != 0 and "no dataset" in str(bad.exception)
    typo = CliRunner().invoke(app, ["fqe", "--dataset", path, "--scenario", scenario, "--policy", str(tmp_path / "gone.pt")])
    assert typo.exit_code != 0 and "gone.pt" in str(typo.exception) and "logged behaviour" not in typo.output  # before any fit
    card = str(Path(path).with_suffix(".json"))
    before = Path(card).read_bytes()
    own = CliRunner().invoke(app, ["fqe", "--dataset", path, "--scenario", scenario, "--updates", "2", "--output", card])
    assert own.exit_code != 0 and "dataset's own card" in str(own.exception) and Path(card).read_bytes() == before
