"""A2C and SAC end to end on a 3x3 grid, checkpoints, configs and the CLI."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch
import yaml

from marl_amod.checkpoints import load_policy, save_policy
from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.models import build_actor
from marl_amod.scenario import load_city
from marl_amod.system import FleetSystem


@pytest.fixture
def tiny_yaml(tmp_path: Path) -> str:
    """The 3x3, 6-step grid as a scenario file, so configs can name it."""
    path = tmp_path / "tiny.yaml"
    path.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return str(path)


def _common(tmp_path: Path, scenario: str, **kw) -> dict:
    return {"scenario": scenario, "eval_every": 4, "eval_episodes": 2, "final_eval_episodes": 2, "hidden": 8,
            "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "policies" / "p.pt"), **kw}


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_a2c_tiny_run_writes_checkpoint_logs_and_card(tmp_path, tiny_yaml, mode):
    from marl_amod.algos import a2c

    summary = a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, mode=mode, episodes=8, episodes_per_update=2)))
    pt = tmp_path / "policies" / "p.pt"
    assert pt.is_file() and pt.with_suffix(".json").is_file() and pt.with_suffix(".md").is_file()
    card = json.loads(pt.with_suffix(".json").read_text())
    assert card["mode"] == mode and card["algorithm"] == "a2c" and card["episodes_trained"] == 8
    assert card["env_version"] == "amod_v0"  # a card says which env version its score is on
    assert np.isfinite(card["profit_mean"]) and card["profit_mean"] == summary["card"]["profit_mean"]
    log = (tmp_path / "run" / "log.csv").read_text()
    assert "eval/profit" in log and "loss/policy" in log
    assert (tmp_path / "run" / "state.pt").is_file()
    assert any(p.name.startswith("events.out.tfevents") for p in (tmp_path / "run").iterdir())
    # the policy file evaluates through the same path as `marl-amod evaluate --policy x.pt`
    res = evaluate(load_city(tiny_yaml), str(pt), episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"])


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_sac_tiny_run_updates_and_writes_checkpoint(tmp_path, tiny_yaml, mode):
    from marl_amod.algos import sac

    summary = sac.train(sac.Args(**_common(tmp_path, tiny_yaml, mode=mode, episodes=4, batch_size=8, warmup_steps=8)))
    assert summary["card"]["algorithm"] == "sac" and summary["card"]["mode"] == mode
    assert "loss/q" in (tmp_path / "run" / "log.csv").read_text()
    assert (tmp_path / "policies" / "p.pt").is_file()


def test_a2c_resume_continues_from_saved_episode(tmp_path, tiny_yaml):
    from marl_amod.algos import a2c

    a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2)))
    summary = a2c.train(a2c.Args(**_common(tmp_path, tiny_yaml, episodes=8, episodes_per_update=2)), resume=str(tmp_path / "run" / "state.pt"))
    assert summary["card"]["episodes_trained"] == 8
    episodes = [int(line.split(",")[0]) for line in (tmp_path / "run" / "log.csv").read_text().splitlines()[1:]]
    assert episodes == sorted(episodes) and max(episodes) == 8  # resumed at 4, not restarted at 0


@pytest.mark.parametrize("kind", ["gnn", "mlp", "cnn"])
def test_save_load_round_trip_gives_identical_actions(tmp_path, tiny_city, kind):
    torch.manual_seed(0)
    actor = build_actor(kind, tiny_city, 13, 8)
    card = {"scenario": tiny_city.name, "algorithm": "a2c", "mode": "centralised", "actor": kind, "conv": "gcn",
            "hidden": 8, "n_features": 13, "lookahead": 6, "seed": 0}
    path = save_policy(tmp_path / "x.pt", actor, card)
    assert path.stat().st_size < 2_000_000
    system = FleetSystem(tiny_city)
    system.reset(3)
    from marl_amod.checkpoints import ActorPolicy

    fresh, loaded = ActorPolicy(actor, tiny_city), load_policy(path, tiny_city)
    for _ in range(4):
        w = fresh.weights(system)
        np.testing.assert_array_equal(w, loaded.weights(system))
        np.testing.assert_array_equal(fresh.target(system), loaded.target(system))
        system.step(loaded.target(system))


def test_discounted_returns():
    from marl_amod.algos.a2c import discounted_returns

    torch.testing.assert_close(discounted_returns([1.0, 2.0, 4.0], 0.5), torch.tensor([3.0, 4.0, 4.0]))


def test_train_config_typo_is_a_clear_error(tmp_path):
    from marl_amod.training import load_train_config

    bad = tmp_path / "bad.yaml"
    bad.write_text("algo: a2c\nargs: {episodse: 10}\n")
    with pytest.raises(ConfigError, match="episodse"):
        load_train_config(bad)
    bad.write_text("algo: a2c\nargz: {}\n")
    with pytest.raises(ConfigError, match="argz"):
        load_train_config(bad)
    bad.write_text("algo: a2c\nargs: {gamma: fast}\n")
    with pytest.raises(ConfigError, match="gamma"):
        load_train_config(bad)


@pytest.mark.parametrize("loader", ["marl_amod.training:load_train_config", "marl_amod.comparison:load_compare_config"])
def test_malformed_or_missing_config_is_a_config_error_naming_the_file(tmp_path, loader):
    import importlib

    module, name = loader.split(":")
    load = getattr(importlib.import_module(module), name)
    bad = tmp_path / "broken.yaml"
    bad.write_text("algo: a2c\nargs: {episodes: [1, 2\n")
    with pytest.raises(ConfigError, match="malformed YAML in .*broken.yaml"):
        load(bad)
    bad.write_text("- just\n- a list\n")
    with pytest.raises(ConfigError, match="expected a mapping"):
        load(bad)
    with pytest.raises(ConfigError, match="not found"):
        load(tmp_path / "missing.yaml")


def test_compare_config_typo_is_a_clear_error(tmp_path):
    from marl_amod.comparison import load_compare_config

    bad = tmp_path / "c.yaml"
    bad.write_text("scenario: synthetic\nepisodez: 3\n")
    with pytest.raises(ConfigError, match="episodez"):
        load_compare_config(bad)
    bad.write_text("scenario: synthetic\nruns: [{label: x, algo: sac, args: {hiden: 3, policy_out: a.pt}}]\n")
    with pytest.raises(ConfigError, match="hiden"):
        load_compare_config(bad)


def test_bundled_configs_validate():
    import yaml

    from marl_amod.comparison import load_compare_config
    from marl_amod.integrations.rllib import load_rllib_config  # pydantic only: no Ray needed
    from marl_amod.training import load_train_config

    root = Path(__file__).resolve().parent.parent / "configs"
    for path in root.glob("*.yaml"):
        if path.stem.startswith("compare_"):
            load_compare_config(path)
        elif yaml.safe_load(path.read_text()).get("algo") == "ppo":
            load_rllib_config(path)
        else:
            load_train_config(path)


def test_cli_train_and_compare_on_tiny_city(tmp_path, tiny_yaml):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    args = _common(tmp_path, tiny_yaml, episodes=4, episodes_per_update=2)
    cfg = tmp_path / "run.yaml"
    cfg.write_text(yaml.safe_dump({"algo": "a2c", "args": args}))
    res = CliRunner().invoke(app, ["train", "--config", str(cfg)])
    assert res.exit_code == 0, res.output
    assert (tmp_path / "policies" / "p.pt").is_file()
    assert json.loads((tmp_path / "policies" / "p.json").read_text())["config"] == str(cfg)  # card says how to reproduce
    args.pop("scenario")
    cmp_cfg = tmp_path / "compare.yaml"
    cmp_cfg.write_text(yaml.safe_dump({"scenario": tiny_yaml, "episodes": 2, "baselines": ["equal-distribution"],
                                       "output": str(tmp_path / "cmp"), "runs": [{"label": "gnn", "algo": "a2c", "args": args}]}))
    res = CliRunner().invoke(app, ["compare", "--config", str(cmp_cfg)])
    assert res.exit_code == 0, res.output
    table = json.loads((tmp_path / "cmp" / "compare.json").read_text())
    assert [r["label"] for r in table["rows"]] == ["equal-distribution", "gnn"]
    for name in ("compare.md", "learning_curves.png", "profit.png", "served_by_region.png"):
        assert (tmp_path / "cmp" / name).is_file()


def test_decentralised_execution_through_env_equals_centralised_evaluation(tiny_city):
    """Each agent acting on its own PettingZoo observation reproduces the global policy's episode."""
    from marl_amod.checkpoints import ActorPolicy
    from marl_amod.env.observations import split_local
    from marl_amod.env.parallel import AmodParallelEnv
    from marl_amod.models import LocalActor
    from marl_amod.training import WEIGHT_DIVISOR

    torch.manual_seed(0)
    actor = LocalActor(13, 8)
    env = AmodParallelEnv(tiny_city)
    obs, _ = env.reset(seed=5)
    total = 0.0
    while env.agents:
        actions = {}
        for agent in env.agents:  # one agent at a time, its own observation only
            own, _ctx, nbrs, mask = split_local(torch.as_tensor(obs[agent]))
            actions[agent] = np.array([actor.forward_local(own, nbrs, mask).item() / WEIGHT_DIVISOR], dtype=np.float32)
        obs, rewards, _, _, _ = env.step(actions)
        total += rewards["region_0"]
    system = FleetSystem(tiny_city)
    system.reset(5)
    policy = ActorPolicy(actor.eval(), tiny_city)
    central = 0.0
    while not system.done:
        central += system.step(policy.target(system)).reward
    assert total == pytest.approx(central)
