"""The opt-in ``arrivals_now`` node column (vehicles arriving in the current step, idle from the
next): the same column on both env faces, in the training rollouts, on the policy card and back."""

from __future__ import annotations

import json

import numpy as np
import pytest
import torch
import yaml

import marl_amod
from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.algos.rollout import BatchRollout, Rollout, train_seed
from marl_amod.checkpoints import architecture_args, load_policy
from marl_amod.datasets import collect
from marl_amod.env.features import feature_high, feature_names, n_features, node_features
from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city


def _moving_weights(rng: np.random.Generator, shape: tuple[int, ...]) -> np.ndarray:
    return rng.uniform(0.0, 1.0, shape).astype(np.float32)


def test_the_column_is_the_arrivals_of_this_step_after_the_default_columns(small_city) -> None:
    """Appended last, so the default columns are unchanged; it is ``arrivals[t]`` times 0.01, which
    becomes idle at t + 1 (the next step's idle count minus what arrives later cannot tell it)."""
    env = marl_amod.parallel_env(small_city, arrivals_now=True)
    plain = marl_amod.parallel_env(small_city)
    env.reset(seed=3)
    plain.reset(seed=3)
    rng = np.random.default_rng(0)
    seen = 0.0
    while env.agents:
        x, base = env.graph()["x"], plain.graph()["x"]
        sim = env.system.sim
        assert x.shape == (16, n_features(6, True)) == (16, 14) and x.dtype == np.float32
        np.testing.assert_array_equal(x[:, :-1], base)
        np.testing.assert_array_equal(x[:, -1], (sim.arrivals[sim.t] * 0.01).astype(np.float32))
        seen += float(x[:, -1].sum())
        obs = env._observations()
        assert all(env.observation_space(a).contains(o) for a, o in obs.items())
        w = _moving_weights(rng, (16,))
        for e in (env, plain):
            e.step({a: w[i : i + 1] for i, a in enumerate(e.possible_agents)})
    assert seen > 0  # vehicles did arrive mid-step: the column is not all zeros
    assert feature_names(6, True)[-1] == "arrivals_now" and len(feature_names(6, True)) == 14
    assert len(feature_high(small_city, 6, arrivals_now=True)) == 14
    assert n_features(6) == 13 and plain.observation_space("region_0").shape[0] < env.observation_space("region_0").shape[0]


def test_vector_env_and_parallel_env_agree_with_the_column() -> None:
    b, seed = 3, 11
    venv = marl_amod.vector_env("synthetic", num_envs=b, arrivals_now=True)
    envs = [marl_amod.parallel_env("synthetic", arrivals_now=True) for _ in range(b)]
    obs, _ = venv.reset(seed=seed)
    singles = [env.reset(seed=seed + k)[0] for k, env in enumerate(envs)]
    rng = np.random.default_rng(2)
    while True:
        for k, env in enumerate(envs):
            np.testing.assert_array_equal(obs[k], np.stack([singles[k][a] for a in env.possible_agents]))
            np.testing.assert_array_equal(venv.state()[k], env.state())
            np.testing.assert_array_equal(venv.graph()["x"][k], env.graph()["x"])
        w = _moving_weights(rng, (b, venv.num_agents))
        obs, _r, _te, trunc, _ = venv.step(w)
        singles = [env.step({a: w[k, j : j + 1] for j, a in enumerate(env.possible_agents)})[0] for k, env in enumerate(envs)]
        if trunc.all():
            break
    assert obs.shape[-1] == venv.observation_space.shape[0]


@pytest.mark.parametrize("mode", ["centralised", "decentralised"])
def test_training_rollouts_read_the_column_on_both_paths(small_city, mode) -> None:
    """The batched rollout (A2C's num_envs > 1) and the one-episode rollout give the same features."""
    batch, single = BatchRollout(small_city, mode, 6, 2, arrivals_now=True), Rollout(small_city, mode, 6, arrivals_now=True)
    ob_b = batch.reset(seed=5, first_episode=0)
    ob_s = single.reset(train_seed(5, 0))  # episode 0 of the batch
    rng = np.random.default_rng(4)
    for _ in range(4):
        assert ob_b.x.shape == (2, 16, 14)
        torch.testing.assert_close(ob_b.x[0], ob_s.x, rtol=0, atol=0)
        if mode == "decentralised":
            torch.testing.assert_close(ob_b.own[0], ob_s.own, rtol=0, atol=0)
        w = rng.uniform(0.1, 1.0, (2, 16))
        ob_b, _ = batch.step(w)
        ob_s, _ = single.step(w[0])
    np.testing.assert_array_equal(ob_s.x.numpy(), node_features(single.system, 6, arrivals_now=True))


def test_options_are_checked_on_both_faces(tiny_city) -> None:
    for make in (marl_amod.parallel_env, marl_amod.vector_env):
        with pytest.raises(ConfigError, match="arrivals_now"):
            make(tiny_city, arrivals_now="yes")


@pytest.fixture(scope="module")
def tiny_arrivals_dataset(tmp_path_factory) -> tuple[str, str]:
    root = tmp_path_factory.mktemp("arrivals")
    scenario = root / "tiny.yaml"
    scenario.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    city = load_city(str(scenario))
    data = collect(city, make_policy("prop", city), episodes=3, seed=0, arrivals_now=True)
    assert data.meta["arrivals_now"] is True and data.meta["n_features"] == 14
    assert "arrivals_now" not in collect(city, make_policy("prop", city), episodes=1, seed=0).meta  # the default meta as before
    return str(scenario), str(data.save(root / "tiny_prop_arrivals.npz"))


def test_bc_card_records_the_column_and_evaluation_and_warm_starts_rebuild_it(tmp_path, tiny_arrivals_dataset) -> None:
    from marl_amod.algos import a2c

    scenario, dataset = tiny_arrivals_dataset
    args = {"scenario": scenario, "dataset": dataset, "updates": 4, "batch_size": 8, "eval_every": 4, "eval_episodes": 1,
            "final_eval_episodes": 2, "hidden": 8, "conv": "sage", "actor_time": True, "run_dir": str(tmp_path / "run"),
            "policy_out": str(tmp_path / "p.pt")}  # fmt: skip
    with pytest.raises(ConfigError, match="arrivals_now"):  # the data's features, not the default ones
        ALGOS["bc"].train(args_for("bc", args))
    summary = ALGOS["bc"].train(args_for("bc", {**args, "arrivals_now": True}))
    card = json.loads((tmp_path / "p.json").read_text())
    assert card["arrivals_now"] is True and card["n_features"] == 14
    city = load_city(scenario)
    policy = load_policy(str(tmp_path / "p.pt"), city)
    assert policy.arrivals_now
    res = evaluate(str(tmp_path / "p.pt"), city, episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(summary["card"]["profit_mean"])
    # the policy is also a callable on the env's observations: the same weights from the local layout
    env = marl_amod.parallel_env(city, arrivals_now=True)
    obs, _ = env.reset(seed=1)
    acts = policy(obs)
    np.testing.assert_allclose(np.concatenate([acts[a] for a in env.possible_agents]), policy.weights(env.system).astype(np.float32), rtol=1e-6)

    tuned = a2c.train(a2c.Args(scenario=scenario, **architecture_args(card), init_actor=str(tmp_path / "p.pt"), episodes=4, num_envs=2,
                               episodes_per_update=2, critic_time=True, eval_every=4, eval_episodes=1, final_eval_episodes=1,
                               run_dir=str(tmp_path / "a2c"), policy_out=str(tmp_path / "ft.pt")))  # fmt: skip
    assert tuned["card"]["arrivals_now"] is True and tuned["card"]["n_features"] == 14
    assert evaluate(str(tmp_path / "ft.pt"), city, episodes=1, seed=0)["metrics"]["profit"]["mean"] > 0


@pytest.mark.parametrize("algo", ["iql", "cql"])
def test_offline_critics_read_the_column(tmp_path, tiny_arrivals_dataset, algo) -> None:
    """IQL's and CQL's critics take the data's F (14), as the actor does: a critic built for 13
    columns failed on the first batch; the shipped critic's card says 14."""
    scenario, dataset = tiny_arrivals_dataset
    args = {"scenario": scenario, "dataset": dataset, "arrivals_now": True, "updates": 2, "batch_size": 4, "eval_every": 2,
            "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "critic_hidden": 8, "run_dir": str(tmp_path / "run"),
            "policy_out": str(tmp_path / "p.pt")}  # fmt: skip
    if algo == "cql":
        args["bc_steps"] = 1  # one BC step, then one step on the critic's Q
    summary = ALGOS[algo].train(args_for(algo, args))
    assert summary["card"]["arrivals_now"] is True and summary["card"]["n_features"] == 14


def test_sac_critic_reads_the_column(tiny_city) -> None:
    """SAC's twin critics take the rollout's F (14) with arrivals_now, as its actor does."""
    from marl_amod.algos import common as C
    from marl_amod.algos import sac

    args = sac.Args(scenario="synthetic", hidden=8, batch_size=4, arrivals_now=True, policy_out="")
    learner = sac.Learner(args, tiny_city, C.make_graph(tiny_city, args))
    x = torch.as_tensor(Rollout(tiny_city, "centralised", 6, arrivals_now=True).reset(0).x)
    b = {"x": x.expand(4, -1, -1), "next_x": x.expand(4, -1, -1), "action": torch.full((4, 9), 1 / 9), "reward": torch.ones(4),
         "done": torch.zeros(4)}  # fmt: skip
    learner.update(b)  # the critics read (B, N, 14)



def test_meta_runs_refuse_the_column(tmp_path) -> None:
    """Meta-RL builds its own task features: arrivals_now there would be silently dropped."""
    with pytest.raises(ConfigError, match="arrivals_now is not read"):
        args_for("meta", {"arrivals_now": True, "run_dir": str(tmp_path)})


def test_concatenate_refuses_datasets_with_and_without_the_column(tiny_arrivals_dataset) -> None:
    """A DataError naming the key (the message read the key of the part that lacks it: KeyError)."""
    from marl_amod.datasets import OfflineDataset, concatenate
    from marl_amod.errors import DataError

    with_col = OfflineDataset.load(tiny_arrivals_dataset[1])
    city = load_city(tiny_arrivals_dataset[0])
    plain = collect(city, make_policy("prop", city), episodes=1, seed=0)
    for parts in ([with_col, plain], [plain, with_col]):
        with pytest.raises(DataError, match="arrivals_now"):
            concatenate(parts)



def test_dagger_rounds_log_the_column_of_the_bc_config(tmp_path, tiny_arrivals_dataset) -> None:
    """DAgger's rounds are collected with the config's arrivals_now, so they join its dataset."""
    from marl_amod.dagger import dagger
    from marl_amod.datasets import OfflineDataset

    scenario, dataset = tiny_arrivals_dataset
    values = {"scenario": scenario, "dataset": dataset, "arrivals_now": True, "updates": 2, "batch_size": 4, "eval_every": 2,
              "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "run_dir": str(tmp_path / "bc"), "policy_out": str(tmp_path / "clone.pt")}  # fmt: skip
    ALGOS["bc"].train(args_for("bc", values))
    config = tmp_path / "bc.yaml"
    config.write_text(yaml.safe_dump({"algo": "bc", "args": {**values, "policy_out": ""}}))
    dagger(config, start=str(tmp_path / "clone.pt"), expert="prop", rounds=1, episodes=1, run_root=tmp_path / "dagger")
    part = OfflineDataset.load(tmp_path / "dagger" / "round1.npz")
    assert part.meta["arrivals_now"] is True and part.meta["n_features"] == 14


def test_a_warm_start_names_the_column_it_was_trained_with(tmp_path, tiny_arrivals_dataset) -> None:
    """An init_actor trained with the column, in a run without it, is refused by name: the
    features differ (the weights' shapes may even agree: lookahead 5 with actor_time has 14 inputs too)."""
    from marl_amod.algos import a2c
    from marl_amod.algos import common as C
    from marl_amod.errors import DataError

    scenario, dataset = tiny_arrivals_dataset
    ALGOS["bc"].train(args_for("bc", {"scenario": scenario, "dataset": dataset, "arrivals_now": True, "updates": 1, "batch_size": 4,
                                      "eval_every": 1, "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "conv": "sage",
                                      "run_dir": str(tmp_path / "bc"), "policy_out": str(tmp_path / "p.pt")}))  # fmt: skip
    city = load_city(scenario)
    for other in ({}, {"lookahead": 5, "actor_time": True}):  # 13 inputs; 11 + 3 = 14 inputs, as the file's
        args = a2c.Args(scenario=scenario, hidden=8, conv="sage", init_actor=str(tmp_path / "p.pt"), **other)
        with pytest.raises(DataError, match="arrivals_now True"):
            C.warm_start(C.make_actor(args, city), args, city)
    args = a2c.Args(scenario=scenario, hidden=8, conv="sage", arrivals_now=True, init_actor=str(tmp_path / "p.pt"))
    C.warm_start(C.make_actor(args, city), args, city)  # the same features: it loads


def test_an_outside_policy_for_the_column_env_sees_its_observations(small_city) -> None:
    """A callable written for ``parallel_env(arrivals_now=True)`` (an SB3 or TorchRL model) is
    evaluated on the observations it was trained on (the option was refused: no way to give it)."""
    env = marl_amod.parallel_env(small_city, arrivals_now=True)
    dim = env.observation_space("region_0").shape[0]
    seen = []

    def fn(obs):
        seen.append(obs["region_0"].copy())
        return {a: np.ones(1, dtype=np.float32) for a in obs}

    evaluate(make_policy(fn, small_city, arrivals_now=True), small_city, episodes=1, seed=0)
    assert seen and all(o.shape == (dim,) for o in seen)
    assert any(o[n_features(6, True) - 1] > 0 for o in seen)  # the own row's last column: vehicles arriving now


def test_a_policy_with_the_column_refuses_an_env_without_it_by_name(small_city) -> None:
    """The policy as a callable on an env made with other feature options: a ConfigError that says
    which (it was a ValueError about layouts, and an env whose widths happen to fit was read wrongly)."""
    from marl_amod.algos import a2c
    from marl_amod.algos import common as C
    from marl_amod.checkpoints import ActorPolicy

    for arrivals in (True, False):
        actor = C.make_actor(a2c.Args(scenario="synthetic", hidden=8, arrivals_now=arrivals), small_city)
        policy = ActorPolicy(actor, small_city, 6, arrivals_now=arrivals)
        obs, _ = marl_amod.parallel_env(small_city, arrivals_now=not arrivals).reset(seed=0)
        with pytest.raises(ConfigError, match=f"arrivals_now {arrivals}"):
            policy(obs)
        obs, _ = marl_amod.parallel_env(small_city, arrivals_now=arrivals).reset(seed=0)
        assert len(policy(obs)) == 16
