"""INF, DTV, PROP and the MPC policies: registered by name, feasible integer targets every step."""

from __future__ import annotations

import numpy as np
import pytest

from marl_amod.baselines.behaviour import DynamicTripVehicle, Informed, Proportional
from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.policies import make_policy, policy_names
from marl_amod.system import FleetSystem

NAMES = ["inf", "dtv", "prop", "mpc-oracle", "mpc-forecast"]


def test_policies_are_registered_by_name():
    assert set(NAMES) <= set(policy_names())


@pytest.mark.parametrize("name", NAMES)
def test_policy_targets_are_feasible_integers_every_step(tiny_city, name):
    system = FleetSystem(tiny_city)
    system.reset(7)
    policy = make_policy(name, tiny_city)
    policy.reset(system, np.random.default_rng(0))
    while not system.done:
        target = np.asarray(policy.target(system))
        idle = system.sim.idle
        assert target.shape == idle.shape and target.dtype.kind == "i"
        assert np.all(target >= -1)
        assert np.maximum(target, 0).sum() <= idle.sum()
        system.step(target)
    assert system.sim.vehicles() == tiny_city.fleet_size


def test_dtv_moves_vehicles_toward_this_steps_requests(tiny_city):
    system = FleetSystem(tiny_city)
    system.reset(0)
    sim = system.sim
    sim.idle[:] = 0
    sim.idle[0] = 6
    sim.backlog[:] = 0
    sim.backlog[0, 8, 0] = 2  # two open requests in the far corner
    sim.last_dispatch[:] = 0
    target = DynamicTripVehicle().target(system)
    assert target[8] == 2 and target[0] == 4 and target.sum() == 6


def test_prop_weights_follow_the_forecast_not_the_draw(tiny_city):
    system = FleetSystem(tiny_city)
    system.reset(0)
    w = Proportional().weights(system)
    assert np.allclose(w, tiny_city.demand_rate[1].sum(axis=1))


def test_inf_sends_nothing_beyond_max_reb_and_is_deterministic(tiny_city):
    result = [evaluate(Informed(max_reb=2), tiny_city, episodes=2, seed=0)["per_episode"] for _ in range(2)]
    assert result[0] == result[1]
    with pytest.raises(ConfigError):
        Informed(max_reb=0)
