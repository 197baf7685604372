"""Q-guided action selection (marl_amod.selection): the opt-in policy option of IQL and CQL files."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.checkpoints import ActorPolicy, load_actor, load_critic, load_policy, read_card, write_policy
from marl_amod.env.features import node_features
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import TwinQ
from marl_amod.scenario import load_city
from marl_amod.selection import QSelector, Selection
from marl_amod.system import FleetSystem

SELECT = {"candidates": 16, "concentration": 20.0, "seed": 3}


@pytest.fixture(scope="module")
def trained(tiny_prop_dataset, tmp_path_factory):
    """(city, IQL policy file with selection, CQL policy file without): tiny runs of a few updates."""
    scenario, dataset = tiny_prop_dataset
    root = tmp_path_factory.mktemp("selection")
    common = {"scenario": scenario, "dataset": dataset, "updates": 6, "batch_size": 8, "eval_every": 6, "eval_episodes": 1,
              "final_eval_episodes": 2, "hidden": 8, "critic_hidden": 8}  # fmt: skip
    iql = ALGOS["iql"].train(args_for("iql", {**common, "selection": SELECT, "run_dir": str(root / "iql"), "policy_out": str(root / "iql.pt")}))
    ALGOS["cql"].train(args_for("cql", {**common, "bc_steps": 2, "n_actions": 2, "run_dir": str(root / "cql"), "policy_out": str(root / "cql.pt")}))
    return load_city(scenario), root / "iql.pt", root / "cql.pt", iql["card"]


def _states(city, n: int = 6) -> list[np.ndarray]:
    """Node features of a few reachable states (a fleet rolled forward under its own dispatch)."""
    system, out = FleetSystem(city), []
    system.reset(0)
    while len(out) < n and not system.done:
        out.append(node_features(system, 6))
        system.step(system.targets_from_weights(np.full(city.n_regions, 1.0 / city.n_regions)))
    return out


def test_no_candidates_is_the_deterministic_policy(trained):
    """candidates 0 (the mean only) plays exactly today's action, from the file and from a selector."""
    city, _, cql, _ = trained
    plain, chosen = load_policy(cql, city), load_policy(cql, city, selection={"candidates": 0, "concentration": 5.0})
    import marl_amod  # the top-level load_policy takes the same options

    assert isinstance(marl_amod.load_policy(cql, city, selection=SELECT).selector, QSelector) and plain.selector is None
    critic, _ = load_critic(cql)
    only_mean = QSelector(critic, city, Selection(candidates=0, concentration=5.0))
    for x in _states(city):
        mean = plain._mean(x, np.zeros(3, np.float32))
        assert np.array_equal(chosen._mean(x, np.zeros(3, np.float32)), mean)
        assert np.array_equal(only_mean(x, mean), mean)


def test_the_selected_action_has_the_highest_q_among_the_candidates(trained):
    """The played action is the candidate the critic scores highest (the mean first among them),
    and it is not always the mean: the critic does choose."""
    city, _, cql, _ = trained
    policy = load_policy(cql, city, selection=SELECT)
    sel, moved = policy.selector, 0
    for x in _states(city):
        mean = load_policy(cql, city)._mean(x, np.zeros(3, np.float32))
        cands = sel.candidates(x, mean)
        assert cands.shape == (SELECT["candidates"] + 1, city.n_regions) and np.array_equal(cands[0], mean)
        assert np.allclose(cands.sum(1), 1.0)
        played = policy._mean(x, np.zeros(3, np.float32))
        scores = sel.scores(x, cands)
        assert np.array_equal(played, cands[int(np.argmax(scores))])
        assert sel.scores(x, played[None])[0] == pytest.approx(scores.max(), abs=1e-6)
        moved += not np.array_equal(played, mean)
    assert moved > 0


def test_selection_is_a_function_of_the_observation_and_its_seed(trained):
    """The same features and seed give the same candidates (any episode order); another seed other ones."""
    city, _, cql, _ = trained
    critic, _ = load_critic(cql)
    x = _states(city, 2)[1]
    mean = np.full(city.n_regions, 1.0 / city.n_regions)
    a, b = (QSelector(critic, city, Selection(**SELECT)).candidates(x, mean) for _ in range(2))
    other = QSelector(critic, city, Selection(**{**SELECT, "seed": 4})).candidates(x, mean)
    assert np.array_equal(a, b) and not np.array_equal(a[1:], other[1:])
    r1, r2 = (evaluate(load_policy(cql, city, selection=SELECT), city, episodes=2, seed=5)["metrics"]["profit"]["mean"] for _ in range(2))
    assert r1 == r2


def test_a_run_with_selection_ships_its_critic_and_evaluates_to_its_card(trained):
    """Round trip: the card records the selection and the critic, the file carries the critic's weights,
    and evaluating the file (which plays the card's selection) gives the run's own final score."""
    city, iql, _, card = trained
    assert card["selection"] == {**SELECT, "reduce": "min"} and card["critic"] == {"n_features": 13, "hidden": 8, "conv": "gcn"}
    assert read_card(iql)["selection"] == card["selection"]
    policy = load_policy(iql, city)
    assert policy.selector is not None and policy.selector.selection == Selection(**SELECT)
    res = evaluate(str(iql), city, episodes=2, seed=0)
    assert res["metrics"]["profit"]["mean"] == pytest.approx(card["profit_mean"])
    off = evaluate(load_policy(iql, city, selection={"candidates": 0, "concentration": 1.0}), city, episodes=2, seed=0)
    assert off["metrics"]["profit"]["mean"] != pytest.approx(card["profit_mean"])  # the selection is what was scored
    # written again from its parts, the file gives the same critic and the same actions
    actor, card2 = load_actor(iql, city)
    critic, _ = load_critic(iql)
    copy = write_policy(iql.parent / "copy.pt", actor.state_dict(), card2, critic.state_dict())
    again, _ = load_critic(copy)
    assert all(torch.equal(v, again.state_dict()[k]) for k, v in critic.state_dict().items())
    x = _states(city, 3)[2]
    assert np.array_equal(load_policy(copy, city)._mean(x, np.zeros(3, np.float32)), policy._mean(x, np.zeros(3, np.float32)))


def test_selection_without_critic_weights_or_with_bad_settings_is_refused(trained, tmp_path):
    """A card that asks for selection but a file without a critic (a BC policy, an older IQL file) is a
    DataError naming the missing weights; impossible settings are a ConfigError."""
    city, iql, cql, _ = trained
    actor, card = load_actor(iql, city)
    bare = write_policy(tmp_path / "bare.pt", actor.state_dict(), card)  # the card keeps selection, no critic
    with pytest.raises(DataError, match="carries no critic weights"):
        load_policy(bare, city)
    with pytest.raises(DataError, match="carries no critic weights"):
        evaluate(str(bare), city, episodes=1, seed=0)
    assert isinstance(load_policy(bare, city, selection={"candidates": 0, "concentration": 1.0}), ActorPolicy)  # off needs no critic
    with pytest.raises(ConfigError, match="candidates"):
        load_policy(cql, city, selection={"candidates": -1, "concentration": 1.0})
    with pytest.raises(ConfigError, match="concentration"):
        load_policy(cql, city, selection={"candidates": 4})
    critic = TwinQ(13, 4, "gcn")  # weights of another shape than the card's critic (hidden 8)
    with pytest.raises(DataError, match="do not fit"):
        load_critic(write_policy(tmp_path / "odd.pt", actor.state_dict(), card, critic.state_dict()))


def test_selection_plays_the_same_on_the_simulator_and_through_the_envs_observations(trained):
    """Seeded by what the policy observes, the selected action is the same whether the policy reads
    the fleet or the agents' PettingZoo observations."""
    from marl_amod.env.parallel import AmodParallelEnv

    city, iql, _, _ = trained
    policy = load_policy(iql, city)
    env = AmodParallelEnv(city)
    obs, _ = env.reset(seed=5)
    steps = 0
    while env.agents:
        actions = policy(obs)
        via_env = np.array([actions[a][0] for a in policy.agents], dtype=np.float32)
        assert np.array_equal(via_env, policy.weights(env.system).astype(np.float32))
        obs, *_ = env.step(actions)
        steps += 1
    assert steps >= 2  # every step of an episode compared
