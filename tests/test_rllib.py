"""RLlib backend: config checks, the scaled-Gamma head, and one CI-sized PPO run end to end.

The run starts Ray on loopback with its temp and results folders inside pytest's tmp dirs,
trains two small PPO iterations through ``marl-amod train --backend rllib``, then restores the
shared module from the RLlib checkpoint, checks that the converted native policy acts exactly like
it, and evaluates the converted policy through ``marl-amod evaluate``.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

from marl_amod.errors import ConfigError

pytest.importorskip("ray.rllib")

from typer.testing import CliRunner  # noqa: E402

from marl_amod.algos.rollout import WEIGHT_DIVISOR  # noqa: E402
from marl_amod.cli import app  # noqa: E402
from marl_amod.integrations import rllib as rl  # noqa: E402


def test_require_ray_names_the_extra_when_ray_is_missing(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "ray", None)  # makes `import ray` raise ImportError
    with pytest.raises(ConfigError, match=r'pip install "marl-amod\[rllib\]"'):
        rl.require_ray()


def test_rllib_config_rejects_unknown_keys_and_native_configs(tmp_path: Path) -> None:
    typo = tmp_path / "typo.yaml"
    typo.write_text(yaml.safe_dump({"algo": "ppo", "args": {"scenario": "synthetic", "learning_rate": 0.1}}))
    with pytest.raises(ConfigError, match="learning_rate"):
        rl.load_rllib_config(typo)
    with pytest.raises(ConfigError, match="without --backend rllib"):
        rl.load_rllib_config(Path(__file__).parents[1] / "configs" / "a2c" / "synthetic.yaml")
    assert rl.load_rllib_config(Path(__file__).parents[1] / "configs" / "ppo_rllib" / "synthetic.yaml").scenario == "synthetic"


def test_train_cli_keeps_rllib_options_to_the_rllib_backend() -> None:
    native = str(Path(__file__).parents[1] / "configs" / "a2c" / "synthetic.yaml")
    out = CliRunner().invoke(app, ["train", "--config", native, "--num-env-runners", "2"])
    assert isinstance(out.exception, ConfigError) and "--backend rllib" in str(out.exception)
    out = CliRunner().invoke(app, ["train", "--config", native, "--backend", "spark"])
    assert isinstance(out.exception, ConfigError) and "native or rllib" in str(out.exception)
    ppo = str(Path(__file__).parents[1] / "configs" / "ppo_rllib" / "synthetic.yaml")
    out = CliRunner().invoke(app, ["train", "--config", ppo])  # the native backend names the one that trains it
    assert isinstance(out.exception, ConfigError) and "add --backend rllib" in str(out.exception)


def test_scaled_gamma_is_the_density_of_the_action_the_env_receives() -> None:
    import torch

    from marl_amod.integrations.rllib_module import ScaledGamma

    torch.manual_seed(0)
    alpha = torch.tensor([[0.5], [3.0], [40.0]])
    dist = ScaledGamma.from_logits(alpha)
    a = dist.sample(sample_shape=(2000,))  # (2000, 3, 1)
    assert a.shape == (2000, 3, 1) and float(a.min()) >= 0.0 and float(a.max()) < 1.0
    g = torch.distributions.Gamma(alpha, torch.ones_like(alpha))
    expected = (g.log_prob(a[0] * WEIGHT_DIVISOR) + math.log(WEIGHT_DIVISOR)).sum(-1)
    torch.testing.assert_close(dist.logp(a[0]), expected)
    torch.testing.assert_close(a.mean(0), alpha / WEIGHT_DIVISOR, rtol=0.1, atol=1e-4)
    torch.testing.assert_close(dist.to_deterministic().sample(), alpha / WEIGHT_DIVISOR)


def test_rllib_env_appends_the_global_state_for_the_central_critic() -> None:
    env = rl.RllibAmodEnv("synthetic", reward_scale=0.001, central_critic=True)
    obs, _ = env.reset(seed=3)
    o = obs["region_0"]
    assert o.shape == env.observation_space("region_0").shape == (env.local_dim + env.env.state_space.shape[0],)
    np.testing.assert_array_equal(o[env.local_dim :], env.state())
    _, rew, *_ = env.step({a: np.array([0.001], np.float32) for a in env.possible_agents})
    assert len(set(rew.values())) == 1  # the team reward, scaled


@pytest.mark.parametrize("central_critic", [True, False])
def test_shared_module_acts_from_the_local_part_and_values_what_it_is_given(central_critic: bool) -> None:
    import torch
    from ray.rllib.core.columns import Columns

    from marl_amod.integrations.rllib_module import AmodGNNModule

    env = rl.RllibAmodEnv("synthetic", central_critic=central_critic)
    obs, _ = env.reset(seed=5)
    batch = torch.as_tensor(np.stack([obs[a] for a in env.possible_agents]))  # (N, D[+S])
    model = {"local_dim": env.local_dim, "n_features": 13, "hidden": 32, "critic_hidden": 16}
    spaces = {"observation_space": env.observation_space("region_0"), "action_space": env.action_space("region_0")}
    module = AmodGNNModule(**spaces, model_config=model)
    out = module.forward_train({Columns.OBS: batch})
    alpha = out[Columns.ACTION_DIST_INPUTS]
    assert alpha.shape == (len(env.possible_agents), 1) and bool((alpha > 0).all())
    assert module.compute_values({Columns.OBS: batch}).shape == (len(env.possible_agents),)
    if central_critic:  # the actor ignores the appended state: changing it leaves the actions alone
        shifted = batch.clone()
        shifted[:, env.local_dim :] += 1.0
        torch.testing.assert_close(module.forward_train({Columns.OBS: shifted})[Columns.ACTION_DIST_INPUTS], alpha)
    actor_only = AmodGNNModule(**spaces, model_config=model, inference_only=True)
    assert not hasattr(actor_only, "critic")  # env runners build the module without the critic


def test_rllib_ppo_trains_saves_restores_converts_and_evaluates(
    tmp_path: Path, tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch, capfd: pytest.CaptureFixture[str]
) -> None:
    import ray
    import torch
    from ray.rllib.core.columns import Columns
    from ray.rllib.core.rl_module.rl_module import RLModule

    from marl_amod.checkpoints import load_policy
    from marl_amod.integrations.rllib_module import ScaledGamma
    from marl_amod.scenario import load_city

    home = tmp_path / "home"  # Ray would write ~/.ray/auth_token and RLlib ~/ray_results
    home.mkdir()
    monkeypatch.setenv("HOME", str(home))
    ray_tmp = tmp_path_factory.mktemp("ray")  # short: Ray's socket paths must stay under 107 bytes
    policy = tmp_path / "ppo.pt"
    config = tmp_path / "ppo.yaml"
    args = {
        "scenario": "synthetic", "iterations": 2, "train_batch_env_steps": 76, "minibatch_size": 76, "num_epochs": 1,
        "eval_every": 0, "eval_episodes": 1, "final_eval_episodes": 1, "run_dir": str(tmp_path / "run"),
        "policy_out": str(policy), "ray_temp_dir": str(ray_tmp),
    }
    config.write_text(yaml.safe_dump({"algo": "ppo", "args": args}))
    runner = CliRunner()
    out = runner.invoke(app, ["train", "--backend", "rllib", "--config", str(config), "--num-env-runners", "1"])
    assert out.exit_code == 0, out.output
    assert "iter    2" in out.output and not ray.is_initialized()
    assert "max_restarts" not in capfd.readouterr().err  # Ray's core_worker error line on env runners that may restart
    assert not list(home.iterdir()), "Ray or RLlib wrote into the home directory"
    card = json.loads(policy.with_suffix(".json").read_text())
    assert card["actor"] == "local" and card["algorithm"] == "rllib-ppo" and card["iterations"] == 2
    assert card["config"] == str(config) and card["env_version"] == "v0" and card["args"]["num_epochs"] == 1  # the one card type

    # restore the shared module from the RLlib checkpoint (no Ray needed) and convert it
    checkpoint = tmp_path / "run" / "checkpoint"
    module = RLModule.from_checkpoint(rl.checkpoint_module_path(checkpoint))
    converted = rl.actor_from_checkpoint(checkpoint)
    saved = torch.load(policy, weights_only=True)["state_dict"]
    for k, v in converted.state_dict().items():
        torch.testing.assert_close(v, saved[k])

    # same deterministic action: RLlib module (inference) vs the native policy on the same state
    env = rl.RllibAmodEnv("synthetic", central_critic=True)
    obs, _ = env.reset(seed=11)
    batch = torch.as_tensor(np.stack([obs[a] for a in env.possible_agents]))
    with torch.no_grad():
        inputs = module.forward_inference({Columns.OBS: batch})[Columns.ACTION_DIST_INPUTS]
    rllib_action = ScaledGamma.from_logits(inputs).to_deterministic().sample().squeeze(-1).numpy()
    assert rllib_action.max() < 1.0  # inside the env's Box(0, 1): nothing is clipped
    native = load_policy(policy, load_city("synthetic")).weights(env.env.system)
    np.testing.assert_allclose(rllib_action / rllib_action.sum(), native, rtol=1e-5, atol=1e-7)

    result = tmp_path / "eval.json"
    out = runner.invoke(app, ["evaluate", "--scenario", "synthetic", "--policy", str(policy), "--episodes", "1", "--output", str(result)])
    assert out.exit_code == 0, out.output
    assert json.loads(result.read_text())["metrics"]["profit"]["mean"] > 0
