"""Property test over every city: whatever the agents do, the coordinator's flows are feasible, no
vehicle is created or lost, and the local rewards sum to the team reward, every step (issue 13).

A seeded loop per city (synthetic always, every real city when MARL_AMOD_DATA is set) runs whole
episodes for about a second with random and adversarial joint actions, over both action modes,
both reward modes and two request patiences.
"""

from __future__ import annotations

import itertools
import time
import zlib

import numpy as np
import pytest
from conftest import REAL_CITIES, has_data

from marl_amod import parallel_env
from marl_amod.env import actions as act

CITIES = ["synthetic", *(REAL_CITIES if has_data() else [])]
SECONDS_PER_CITY = 1.0


def adversarial_actions(rng: np.random.Generator, n: int) -> np.ndarray:
    """(N,) joint actions: uniform noise or one of the shapes that break naive normalisation."""
    kind = int(rng.integers(8))
    one = np.zeros(n)
    one[rng.integers(n)] = 1.0
    return [
        rng.uniform(0, 1, n),  # what a fresh policy does
        np.zeros(n),  # "stay"
        np.ones(n),
        one,  # everything to one region
        one * 1e-300,  # a sum that is almost zero
        rng.uniform(0, 1e30, n),  # far above the box: clipped
        np.where(rng.random(n) < 0.5, -1e-7, rng.uniform(0, 1, n)),  # tolerated negative noise
        rng.exponential(1.0, n),  # unclipped Gaussian/Gamma policy output
    ][kind]


@pytest.mark.parametrize("name", CITIES)
def test_invariants_hold_under_random_and_adversarial_actions(name):
    rng = np.random.default_rng(zlib.crc32(name.encode()))
    envs = [
        parallel_env(name, action_mode=mode, reward_mode=reward, max_wait=wait)
        for mode, reward, wait in itertools.product(("weight", "logit"), ("local", "team"), (0, 2))
    ]
    fleet = envs[0].city.fleet_size
    deadline = time.perf_counter() + SECONDS_PER_CITY
    steps = 0
    for episode in itertools.count():
        if episode >= len(envs) and time.perf_counter() > deadline:
            break
        env = envs[episode % len(envs)]
        obs, _ = env.reset(seed=int(rng.integers(2**31)))
        sim, system = env.system.sim, env.system
        while env.agents:
            joint = adversarial_actions(rng, len(env.agents))
            actions = {a: np.array([v], dtype=np.float64) for a, v in zip(env.agents, joint, strict=True)}
            idle = sim.idle.copy()
            target = system.targets_from_weights(act.weights(act.joint_action(actions, env.agents), env.action_mode))
            obs, rewards, _, _, _ = env.step(actions)
            out = env.last_outcome
            y, x = out.rebalancing, out.dispatch
            # rebalancing: non-negative, nothing on the diagonal, never more than a region's idle
            # vehicles, and every (feasible by construction) target met
            assert (y >= 0).all() and not np.diag(y).any() and (y.sum(axis=1) <= idle).all()
            assert (idle - y.sum(axis=1) + y.sum(axis=0) >= np.maximum(target, 0)).all()
            # dispatch: non-negative, never more than the open requests or the idle vehicles
            assert (x >= 0).all() and (sim.requests() >= 0).all() and (sim.idle >= 0).all()
            assert sim.vehicles() == fleet  # conservation
            r = np.array([rewards[a] for a in env.possible_agents])
            assert np.isfinite(r).all()
            if env.reward_mode == "local":
                assert r.sum() == pytest.approx(out.reward, rel=1e-9, abs=1e-6)
            else:
                assert np.all(r == out.reward)
            assert all(env.observation_space(a).contains(o) for a, o in obs.items())
            steps += 1
        assert (sim.totals.served <= sim.totals.demand).all()
    assert steps >= len(envs) * (envs[0].city.horizon - 1)
