"""The policy index: every checkpoint from its card, scores normalised only on the card's own episodes."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from marl_amod import policy_catalogue as pc
from marl_amod.checkpoints import save_policy
from marl_amod.cli import app
from marl_amod.ensemble import write_ensemble
from marl_amod.errors import ConfigError
from marl_amod.models import build_actor

ROOT = Path(__file__).resolve().parent.parent
runner = CliRunner()


def test_the_committed_index_is_the_one_the_cards_make():
    """policies/README.md lists every shipped checkpoint as its card says; a policy added, retrained or
    removed without regenerating the index fails here."""
    expected = pc.markdown(ROOT / "policies", ROOT / "docs" / "results").replace(str(ROOT) + "/", "") + "\n"
    committed = (ROOT / "policies" / "README.md").read_text()
    assert committed == expected, "policies/README.md is stale: run `marl-amod policies --markdown policies/README.md`"
    for pt in (ROOT / "policies").glob("*.pt"):
        assert f"`{pt.stem}`" in committed


def _save(folder: Path, name: str, city, **card) -> Path:
    torch.manual_seed(0)
    fields = {"scenario": city.name, "algorithm": "a2c", "mode": "centralised", "actor": "gnn", "conv": "gcn", "hidden": 8,
              "n_features": 13, "lookahead": 6, "seed": 0, "eval_episodes": 10, "eval_seed": 0, "profit_mean": 150.0,
              "profit_std": 5.0, "training_wall_s": 120.0, "episodes_trained": 1000, "config": "configs/a2c/x.yaml", **card}  # fmt: skip
    return save_policy(folder / f"{name}.pt", build_actor("gnn", city, 13, 8), fields)


def _results(folder: Path, scenario: str, episodes: int = 10, seed: int = 0) -> Path:
    rows = [{"policy": p, "metrics": {"profit": {"mean": m, "std": 1.0}}} for p, m in (("equal-distribution", 100.0), ("mpc-oracle", 200.0))]
    folder.mkdir(exist_ok=True)
    (folder / f"{scenario}.json").write_text(json.dumps({"scenario": scenario, "episodes": episodes, "seed": seed, "results": rows}))
    return folder


def test_scores_are_normalised_only_against_anchors_of_the_same_episodes(tmp_path, tiny_city):
    folder = tmp_path / "policies"
    folder.mkdir()
    _save(folder, "same", tiny_city)
    _save(folder, "other_seed", tiny_city, eval_seed=3)
    _save(folder, "fewer", tiny_city, eval_episodes=2)
    _save(folder, "validation", tiny_city, eval_streams="validation")
    anchors = pc.read_anchors(_results(tmp_path / "results", tiny_city.name))
    scores = {e.name: pc.score(e, anchors) for e in pc.read_entries(folder)}
    assert scores == {"fewer": None, "other_seed": None, "same": pytest.approx(50.0), "validation": None}
    assert pc.read_anchors(tmp_path / "nowhere") == {}


def test_the_index_groups_by_training_place_and_lists_ensembles_and_seeds(tmp_path, tiny_city):
    folder = tmp_path / "policies"
    (folder / "seeds").mkdir(parents=True)
    a = _save(folder, "a", tiny_city, profit_mean=175.0)
    b = _save(folder / "seeds", "b", tiny_city)
    write_ensemble(folder / "pair.yaml", [a, b])
    text = pc.markdown(folder, _results(tmp_path / "results", tiny_city.name))
    assert text.startswith("# Trained policies (1 checkpoints, 1 ensembles)")
    assert f"## {tiny_city.name}" in text and "| `a` | a2c, centralised | GNN, gcn, 8 units | 1,000 episodes in 2.0 min |" in text
    assert "| 75 |" in text  # (175 - 100) / (200 - 100)
    assert "| `pair.yaml` | `a.pt`, `seeds/b.pt` |" in text
    assert "## Training seeds (seeds/)" in text and "| `b` |" in text


def test_the_command_filters_and_names_what_it_could_list(tmp_path, tiny_city):
    folder = tmp_path / "policies"
    folder.mkdir()
    _save(folder, "a2c_one", tiny_city)
    _save(folder, "sac_one", tiny_city, algorithm="sac")
    out = runner.invoke(app, ["policies", str(folder), "--algorithm", "sac", "--results", str(tmp_path)])
    assert out.exit_code == 0, out.output
    assert "sac_one" in out.output and "a2c_one" not in out.output and "1 of 2" in out.output and "no scores" in out.output
    out = runner.invoke(app, ["policies", str(folder), "--algorithm", "ppo"])
    assert isinstance(out.exception, ConfigError) and "trained with 'ppo'; there are: a2c, sac" in str(out.exception)
    out = runner.invoke(app, ["policies", str(folder), "--scenario", "atlantis"])
    assert isinstance(out.exception, ConfigError) and f"trained in 'atlantis'; there are: {tiny_city.name}" in str(out.exception)
    index = tmp_path / "index.md"
    assert runner.invoke(app, ["policies", str(folder), "--markdown", str(index)]).exit_code == 0
    assert "`sac_one`" in index.read_text()
    with pytest.raises(ConfigError, match="policy folder .* not found"):
        pc.read_entries(tmp_path / "missing")
    with pytest.raises(ConfigError, match="is a file; give the policy folder that holds it"):
        pc.read_entries(folder / "a2c_one.pt")
    (folder / "broken.pt").write_bytes(b"not a checkpoint")  # one damaged file: the listing goes on without it
    out = runner.invoke(app, ["policies", str(folder), "--results", str(tmp_path)])
    assert out.exit_code == 0, out.output
    assert "left out" in out.output and "broken.pt" in out.output and "a2c_one" in out.output and "sac_one" in out.output
    index = runner.invoke(app, ["policies", str(folder), "--markdown", str(tmp_path / "index2.md")])  # the index leaves nothing out
    assert index.exit_code != 0 and "broken.pt" in str(index.exception)


def test_training_is_described_in_the_units_each_trainer_counts():
    assert pc.trained_on({"iterations": 247, "env_steps": 75088, "training_wall_s": 611.3}) == "247 iterations (75,088 env steps) in 10.2 min"
    assert pc.trained_on({"episodes_trained": 682688, "training_wall_s": 1560.0}) == "682,688 episodes in 26.0 min"
