"""DAgger on a 3x3 grid: relabelled collection, aggregation, rounds that resume, and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml
from typer.testing import CliRunner

from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.cli import app
from marl_amod.dagger import dagger
from marl_amod.datasets import OfflineDataset, collect, concatenate
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city


def test_labeller_logs_the_experts_action_on_the_learners_states(tiny_prop_dataset):
    city = load_city(tiny_prop_dataset[0])
    driven = collect(city, make_policy("equal-distribution", city), episodes=1, seed=3)
    relabelled = collect(city, make_policy("equal-distribution", city), episodes=1, seed=3, labeller=make_policy("prop", city))
    expert = collect(city, make_policy("prop", city), episodes=1, seed=3)
    # the same trajectory as the driven policy's (states and rewards), the expert's actions
    np.testing.assert_array_equal(relabelled.states, driven.states)
    np.testing.assert_array_equal(relabelled.team_rewards, driven.team_rewards)
    assert not np.allclose(relabelled.actions, driven.actions)
    np.testing.assert_array_equal(relabelled.actions[0], expert.actions[0])  # same first state: the expert's own answer
    assert relabelled.meta["policy"] == "prop" and relabelled.meta["rollout_policy"] == "equal-distribution"


def test_concatenate_renumbers_episodes_and_refuses_other_cities(tiny_prop_dataset):
    base = OfflineDataset.load(tiny_prop_dataset[1])
    both = concatenate([base, base])
    assert len(both) == 2 * len(base) and both.meta["episodes"] == 2 * base.meta["episodes"]
    np.testing.assert_array_equal(np.unique(both.episode_ids), np.arange(2 * base.meta["episodes"]))
    other = OfflineDataset(**{**base.__dict__, "meta": {**base.meta, "lookahead": 3}})
    with pytest.raises(DataError, match="lookahead"):
        concatenate([base, other])


@pytest.fixture
def bc_config(tmp_path, tiny_prop_dataset) -> tuple[Path, Path]:
    """A tiny BC config and its clone (the policy round 1 rolls out)."""
    scenario, dataset = tiny_prop_dataset
    values = {"scenario": scenario, "dataset": dataset, "updates": 20, "batch_size": 8, "eval_every": 20, "eval_episodes": 1,
              "final_eval_episodes": 1, "hidden": 8, "run_dir": str(tmp_path / "bc"), "policy_out": str(tmp_path / "clone.pt")}  # fmt: skip
    ALGOS["bc"].train(args_for("bc", values))
    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump({"algo": "bc", "args": {**values, "policy_out": str(tmp_path / "dagger.pt")}}))
    return config, tmp_path / "clone.pt"


def test_dagger_rounds_aggregate_keep_the_best_and_resume(tmp_path, bc_config):
    config, clone = bc_config
    root = tmp_path / "dagger"
    summary = dagger(config, start=str(clone), expert="prop", rounds=2, episodes=2, run_root=root)
    rounds = summary["rounds"]
    base = OfflineDataset.load(yaml.safe_load(config.read_text())["args"]["dataset"])
    per_episode = len(base) // base.meta["episodes"]
    assert [r["transitions"] for r in rounds] == [len(base) + 2 * per_episode, len(base) + 4 * per_episode]  # +2 episodes a round
    assert rounds[0]["rollout_policy"] == str(clone) and rounds[1]["rollout_policy"] == str(root / "round1.pt")
    r2 = OfflineDataset.load(root / "round2.npz")
    assert r2.meta["policy"] == "prop" and r2.meta["seed"] == 2  # round k on collection seed 1 + k - 1
    kept = max(rounds, key=lambda r: r["validation_profit"])
    assert summary["kept"] == kept["round"]
    shipped, source = (torch.load(p, weights_only=True) for p in (tmp_path / "dagger.pt", kept["policy"]))
    assert all(torch.equal(shipped["state_dict"][k], v) for k, v in source["state_dict"].items())
    assert shipped["card"]["algorithm"] == "dagger" and shipped["card"]["dagger"]["kept_round"] == kept["round"]
    assert "Reproduce: `marl-amod dagger --config" in (tmp_path / "dagger.md").read_text()
    city = load_city(yaml.safe_load(config.read_text())["args"]["scenario"])
    profit = lambda p: evaluate(str(p), city, 1, 0)["metrics"]["profit"]["mean"]  # noqa: E731
    assert profit(tmp_path / "dagger.pt") == profit(kept["policy"])  # it loads and plays as the kept round
    assert json.loads((root / "dagger.json").read_text())["kept"] == kept["round"]
    # rerun: nothing is collected or retrained again; one more round only adds round 3
    stamps = {p: p.stat().st_mtime_ns for p in root.glob("round*")}
    again = dagger(config, start=str(clone), expert="prop", rounds=3, episodes=2, run_root=root)
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps
    assert [r["round"] for r in again["rounds"]] == [1, 2, 3] and again["rounds"][:2] == rounds
    # rounds made with another expert, episodes or seed are not reused under the new settings' name
    for changed in ({"expert": "dtv"}, {"episodes": 3}, {"seed": 5}):
        with pytest.raises(ConfigError, match=f"other {next(iter(changed))}"):
            dagger(config, **{"start": str(clone), "expert": "prop", "rounds": 3, "episodes": 2, "run_root": root, **changed})


def test_dagger_refuses_a_config_that_is_not_bc(tmp_path, bc_config):
    config = tmp_path / "a2c.yaml"
    config.write_text(yaml.safe_dump({"algo": "a2c", "args": {"scenario": "synthetic"}}))
    with pytest.raises(ConfigError, match="behaviour cloning"):
        dagger(config, start=str(bc_config[1]))


def test_dagger_checks_its_config_before_collecting(tmp_path, bc_config):
    """A config DAgger cannot retrain fails before round 1's episodes are collected, naming the file."""
    config, clone = bc_config
    args = yaml.safe_load(config.read_text())["args"]
    bad = {
        "misspelt": ({**args, "updats": 5}, "updats"),
        "lookahead": ({**args, "lookahead": 2}, "set lookahead: 6"),
        "own start": ({**args, "policy_out": str(clone)}, "would overwrite"),
    }
    for name, (values, message) in bad.items():
        path = tmp_path / f"{name.replace(' ', '_')}.yaml"
        path.write_text(yaml.safe_dump({"algo": "bc", "args": values}))
        with pytest.raises(ConfigError, match=message):
            dagger(path, start=str(clone), expert="prop", rounds=1, episodes=1, run_root=tmp_path / name)
        assert not (tmp_path / name / "round1.npz").exists()


def test_cli_runs_dagger(tmp_path, bc_config):
    config, clone = bc_config
    args = ["dagger", "--config", str(config), "--start", str(clone), "--expert", "prop", "--rounds", "1", "--episodes", "1",
            "--run-root", str(tmp_path / "d")]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "kept round 1" in result.output and (tmp_path / "dagger.pt").is_file()
