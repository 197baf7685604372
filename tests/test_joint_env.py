"""The single-agent view (marl_amod.integrations.joint): gymnasium's checker, and the same episodes as the ParallelEnv."""

from __future__ import annotations

import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

import marl_amod
from marl_amod.errors import ActionError
from marl_amod.integrations.joint import JointEnv, joint_env


def test_joint_env_passes_gymnasium_env_checker(tiny_city) -> None:
    env = joint_env(tiny_city)
    check_env(env, skip_render_check=True)
    assert env.observation_space.shape == (tiny_city.n_regions, env.parallel.observation_space("region_0").shape[0])
    assert env.action_space.shape == (tiny_city.n_regions,)


@pytest.mark.parametrize("reward_mode", ["team", "local"])
def test_joint_episode_equals_the_parallel_env_episode(tiny_city, reward_mode: str) -> None:
    """Same seed and actions: the same observations, and the team reward whatever the reward mode."""
    joint, parallel = joint_env(tiny_city, reward_mode=reward_mode), marl_amod.parallel_env(tiny_city)
    obs, info = joint.reset(seed=4)
    pobs, _ = parallel.reset(seed=4)
    rng = np.random.default_rng(0)
    steps, truncated = 0, False
    while not truncated:
        assert np.array_equal(obs, np.stack([pobs[a] for a in parallel.possible_agents]))
        action = rng.random(tiny_city.n_regions, dtype=np.float32)
        obs, reward, terminated, truncated, info = joint.step(action)
        pobs, prew, _, ptrunc, pinfo = parallel.step({a: action[i : i + 1] for i, a in enumerate(parallel.possible_agents)})
        assert reward == pytest.approx(prew["region_0"])  # parallel is team mode: every region gets the team reward
        assert not terminated and truncated == all(ptrunc.values())
        steps += 1
    assert steps == parallel.max_cycles
    assert info["served"].shape == (tiny_city.n_regions,)
    assert info["served"].tolist() == [pinfo[a]["served"] for a in parallel.possible_agents]
    assert info["system_profit"] == pinfo["region_0"]["system_profit"]


def test_joint_env_keeps_the_action_rules(tiny_city) -> None:
    """Finite values outside [0, 1] are clipped (Gaussian policies), NaN and wrong sizes are errors."""
    env = JointEnv(marl_amod.parallel_env(tiny_city))
    env.reset(seed=0)
    clipped = JointEnv(marl_amod.parallel_env(tiny_city))
    clipped.reset(seed=0)
    n = tiny_city.n_regions
    wide = np.linspace(-1.0, 2.0, n)
    assert env.step(wide)[1] == clipped.step(np.clip(wide, 0.0, 1.0))[1]
    with pytest.raises(ActionError, match="not finite"):
        env.step(np.full(n, np.nan))
    with pytest.raises(ActionError):
        env.step(np.ones(n + 1))
    for wrong in (np.full(n, "0.5"), np.full(n, 0.5 + 1j), np.ones(n, dtype=bool)):  # refused as the ParallelEnv does
        with pytest.raises(ActionError, match="real numbers"):
            env.step(wrong)


def test_joint_actions_are_read_as_given_and_only_in_the_envs_shapes(tiny_city) -> None:
    """No float32 cast before the checks: a huge finite value is clipped (not made inf), a tiny one is a
    weight (not rounded to 0); a (4, 4) array for 16 regions is not a joint action."""
    n = tiny_city.n_regions
    for values in (np.full(n, 1e39), np.full(n, 1e-46)):  # both: equal weights everywhere
        joint, parallel = joint_env(tiny_city), marl_amod.parallel_env(tiny_city)
        joint.reset(seed=1), parallel.reset(seed=1)
        got = joint.step(values)[1]
        assert got == parallel.step({a: values[i : i + 1] for i, a in enumerate(parallel.possible_agents)})[1]["region_0"]
    env = joint_env(tiny_city)
    env.reset(seed=0)
    for shape in ((1, n), (n, 1, 1)):
        with pytest.raises(ActionError, match=f"shape \\({n},\\) or \\({n}, 1\\)"):
            env.step(np.full(shape, 0.5))
    assert env.metadata["render_fps"] == marl_amod.parallel_env(tiny_city).metadata["render_fps"]


def test_an_action_that_requires_grad_says_to_detach_it(tiny_city) -> None:
    torch = pytest.importorskip("torch")
    env = marl_amod.parallel_env(tiny_city)
    env.reset(seed=0)
    with pytest.raises(ActionError, match="action of region_0: a tensor that requires grad; pass action.detach"):
        env.step({a: torch.tensor([0.5], requires_grad=True) for a in env.agents})
    joint = joint_env(tiny_city)
    joint.reset(seed=0)
    with pytest.raises(ActionError, match="requires grad"):
        joint.step(torch.rand(tiny_city.n_regions, requires_grad=True))
