"""The env against PettingZoo's AEC, state and render tests and the trainers it must plug into (the
parallel API and seed tests run over every scenario in tests/test_scenarios_all.py)."""

from __future__ import annotations

import pickle
import tempfile
from pathlib import Path

import numpy as np
import pytest
from pettingzoo.test import api_test, max_cycles_test, render_test, state_test

import marl_amod
from marl_amod.env.parallel import AmodParallelEnv
from marl_amod.errors import ConfigError
from tests.conftest import needs_data

SCENARIOS = [
    pytest.param({"scenario": "synthetic", "horizon": 8}, id="synthetic"),
    pytest.param({"scenario": "nyc_brooklyn", "horizon": 6}, id="nyc_brooklyn", marks=needs_data),
]


@pytest.mark.parametrize("kwargs", SCENARIOS)
def test_aec_api_conformance(kwargs: dict) -> None:
    api_test(marl_amod.env(**kwargs), num_cycles=20)


@pytest.mark.parametrize("kwargs", SCENARIOS)
def test_state_conformance(kwargs: dict) -> None:
    """state() matches state_space in both the AEC and the parallel API, every step."""
    state_test(marl_amod.env(**kwargs), marl_amod.parallel_env(**kwargs), num_cycles=20)


@pytest.mark.parametrize("kwargs", SCENARIOS)
def test_render_conformance(kwargs: dict) -> None:
    render_test(lambda render_mode=None: marl_amod.env(render_mode=render_mode, **kwargs))


def test_rgb_array_frames_show_the_state(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city, render_mode="rgb_array")
    env.reset(seed=0)
    first = env.render()
    env.step({a: np.array([1.0 if a == "region_0" else 0.0], dtype=np.float32) for a in env.agents})
    assert env.last_outcome.rebalancing.sum() > 0  # everything was asked into region 0: arrows to draw
    second = env.render()
    assert first.dtype == np.uint8 and first.ndim == 3 and first.shape[2] == 3
    assert first.shape == second.shape and not np.array_equal(first, second)
    assert first.std() > 10  # not a blank canvas


def test_env_metadata_and_spaces_are_shared(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city)
    assert env.metadata["name"] == "amod_v0" and env.metadata["is_parallelizable"] is True
    assert env.possible_agents == [f"region_{i}" for i in range(tiny_city.n_regions)]
    spaces = {id(env.observation_space(a)) for a in env.possible_agents}
    assert len(spaces) == 1 and env.observation_space("region_0") is env.observation_space("region_0")
    assert env.action_space("region_1") is env.action_space("region_2")
    box = env.action_space("region_0")
    assert box.shape == (1,) and box.dtype == np.float32 and box.low[0] == 0.0 and box.high[0] == 1.0
    f = 13
    assert env.observation_space("region_0").shape == (f + 3 + env.max_degree * (f + 1),)
    assert env.render_mode is None
    beyond = f"region_{tiny_city.n_regions}"  # one past the last region: a typo, not an agent
    for space in (env.observation_space, env.action_space):
        with pytest.raises(KeyError, match=beyond):
            space(beyond)


def test_max_cycles_conformance() -> None:
    from marl_amod import amod_v0

    max_cycles_test(amod_v0)


def test_versioned_module_and_registry() -> None:
    from marl_amod import amod_v0
    from marl_amod.env import ENV_VERSION

    assert ENV_VERSION == "amod_v0" == amod_v0.ENV_VERSION
    assert isinstance(amod_v0.parallel_env(horizon=4), AmodParallelEnv)
    assert amod_v0.env is amod_v0.raw_env


def test_pettingzoo_registry_makes_the_env() -> None:
    """PettingZoo 1.27+ has a registry; the lower-bound CI venv (1.24.3) does not."""
    import pettingzoo

    from marl_amod import amod_v0

    if not hasattr(pettingzoo, "make"):
        pytest.skip(f"pettingzoo {pettingzoo.__version__} has no registry (1.27+)")
    made = pettingzoo.make("parallel", amod_v0.ENV_ID, horizon=4)
    assert made.unwrapped.metadata["name"] == "amod_v0" and made.unwrapped.city.horizon == 4


def test_import_marl_amod_loads_neither_torch_nor_the_env() -> None:
    import subprocess
    import sys

    code = "import sys, marl_amod; print('torch' in sys.modules, 'marl_amod.env.parallel' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out == ["False", "False"]


def test_env_pickles_mid_episode_and_continues_identically(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city, render_mode="rgb_array")
    env.reset(seed=3)
    env.render()
    act = {a: np.array([0.5 + 0.05 * i], dtype=np.float32) for i, a in enumerate(env.agents)}
    env.step(act)
    clone = pickle.loads(pickle.dumps(env))
    o1, r1, *_ = env.step(act)
    o2, r2, *_ = clone.step(act)
    assert r1 == r2
    assert all(np.array_equal(o1[a], o2[a]) for a in o1)


def _sb3_vec_env(n_envs: int = 2):
    pytest.importorskip("stable_baselines3")
    from marl_amod.integrations.sb3 import sb3_vec_env

    return sb3_vec_env(marl_amod.parallel_env(horizon=6), copies=n_envs)


def test_supersuit_sb3_ppo_trains_one_shared_policy() -> None:
    pytest.importorskip("stable_baselines3")
    import torch
    from stable_baselines3 import PPO

    torch.set_num_threads(1)
    vec = _sb3_vec_env()
    n_agents = 16
    assert vec.num_envs == 2 * n_agents  # every region of every copy is one row of one shared policy
    model = PPO("MlpPolicy", vec, n_steps=8, batch_size=64, n_epochs=1, seed=0, verbose=0)
    before = [p.detach().clone() for p in model.policy.parameters()]
    model.learn(total_timesteps=3 * 8 * vec.num_envs)
    assert model.num_timesteps >= 3 * 8 * vec.num_envs
    # SB3 makes a log folder per learn() even at verbose=0; the suite's go to its own tmp folder, not /tmp/SB3-*
    assert Path(model.logger.get_dir()).parent != Path(tempfile.gettempdir())
    changed = any(not torch.equal(a, b) for a, b in zip(before, model.policy.parameters(), strict=True))
    assert changed
    obs = vec.reset()
    action, _ = model.predict(obs, deterministic=True)
    assert action.shape == (vec.num_envs, 1)
    vec.close()


def test_supersuit_seed_forwarding_makes_resets_reproducible() -> None:
    vec = _sb3_vec_env()
    vec.seed(7)
    a = vec.reset()
    vec.seed(7)
    b = vec.reset()
    c = vec.reset()  # unseeded: a new episode
    vec.seed(8)
    d = vec.reset()
    assert np.array_equal(a, b)
    assert not np.array_equal(a, d)
    assert a.shape == c.shape
    vec.close()


def test_copies_of_a_seeded_env_draw_their_own_unseeded_episodes() -> None:
    """SuperSuit pickles the env into each copy: after a seeded reset (e.g. checking the env first),
    the copies' unseeded episodes must differ, or every copy replays one demand stream."""
    pytest.importorskip("stable_baselines3")
    from marl_amod.integrations.sb3 import sb3_vec_env

    env = marl_amod.parallel_env(horizon=6)
    env.reset(seed=0)
    vec = sb3_vec_env(env, copies=2)
    obs = vec.reset()  # no seed: each copy's own stream
    n = len(env.possible_agents)
    for _ in range(3):  # past step 0: the idle fleets then differ by the requests served
        obs, *_ = vec.step(np.full((2 * n, 1), 0.5, np.float32))
    assert not np.array_equal(obs[:n], obs[n:])
    vec.close()
    for bad in (0, -1, 1.5, True):  # a count, as everywhere else
        with pytest.raises(ConfigError, match="copies must be"):
            sb3_vec_env(marl_amod.parallel_env(horizon=6), copies=bad)


def test_torchrl_pettingzoo_wrapper_rollout() -> None:
    pytest.importorskip("torchrl")
    import torch
    from torchrl.envs.libs.pettingzoo import PettingZooWrapper

    torch.set_num_threads(1)
    env = PettingZooWrapper(marl_amod.parallel_env(horizon=5), return_state=True)
    assert list(env.group_map) == ["region"] and len(env.group_map["region"]) == 16
    td = env.rollout(10, break_when_any_done=True)
    obs = td["region", "observation"]
    assert obs.shape[0] == 4 and obs.shape[1] == 16  # horizon - 1 steps, 16 agents
    assert td["state"].shape[-1] == 16 * 13 + 3
    assert bool(td["next", "done"][-1].all())


def test_marl_amod_env_builds_the_aec_env_even_after_submodules_are_imported() -> None:
    from pettingzoo import AECEnv

    import marl_amod.env.features  # noqa: F401  binds the subpackage to marl_amod.env

    aec = marl_amod.env(horizon=3)
    assert isinstance(aec, AECEnv) and aec.possible_agents[0] == "region_0"


def test_record_episode_writes_an_animated_gif(tiny_city, tmp_path) -> None:
    import imageio.v2 as imageio

    from marl_amod.env.render import record_episode

    env = marl_amod.parallel_env(tiny_city, render_mode="rgb_array")
    path = tmp_path / "episode.gif"
    frames = record_episode(env, seed=0, path=path)
    assert len(frames) == tiny_city.horizon  # reset frame + one per step
    back = imageio.mimread(path)
    assert len(back) == len(frames) and back[0].shape[:2] == frames[0].shape[:2]
    with pytest.raises(ValueError, match="not the AEC env"):  # it plays all agents at once
        record_episode(marl_amod.env(tiny_city, render_mode="rgb_array"), seed=0)


def test_options_the_envs_cannot_use_are_clear_errors(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city)
    with pytest.raises(ConfigError, match="takes a dict or None, got str"):
        env.reset(seed=0, options="fast")
    env.reset(seed=0, options={"from_a_wrapper": 1})  # a wrapper's keys pass (the env reads none)
    venv = marl_amod.vector_env(tiny_city, num_envs=2)
    with pytest.raises(ConfigError, match="takes a dict or None"):
        venv.reset(seed=0, options=[1])
    with pytest.raises(ConfigError, match="num_envs must be an integer >= 1, got True"):
        marl_amod.vector_env(tiny_city, num_envs=True)
    with pytest.raises(ConfigError, match="the vector env does not render"):
        marl_amod.vector_env(tiny_city, render_mode="rgb_array")
    with pytest.raises(ConfigError, match="lookahead must be a positive number of steps, got True"):
        marl_amod.evaluate(lambda obs: {a: [1.0] for a in obs}, tiny_city, episodes=1, lookahead=True)


def test_human_mode_renders_on_reset_and_step_without_a_display(tiny_city) -> None:
    env = marl_amod.parallel_env(tiny_city, render_mode="human")
    env.reset(seed=0)
    assert env.render() is None and env._viewer is not None
    env.step({a: np.array([0.5], dtype=np.float32) for a in env.agents})
    pickle.dumps(env)  # the window does not travel
    env.close()
    assert env._viewer is None
