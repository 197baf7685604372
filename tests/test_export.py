"""Export of the centralised view to d3rlpy and Minari (each test skips when its library is absent)."""

from __future__ import annotations

import numpy as np
import pytest
import yaml

from marl_amod.datasets import collect
from marl_amod.errors import ConfigError
from marl_amod.export import centralised_arrays, episodes
from marl_amod.policies import make_policy
from marl_amod.scenario import load_city


@pytest.fixture(scope="module")
def city(tmp_path_factory):
    scenario = tmp_path_factory.mktemp("export") / "tiny.yaml"
    scenario.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    return load_city(str(scenario))


@pytest.fixture(scope="module")
def data(city):
    return collect(city, make_policy("prop", city), episodes=3, seed=0)


def test_centralised_view_is_the_state_the_joint_action_and_the_team_reward(data):
    a = centralised_arrays(data)
    assert a["observations"].shape == (len(data), 9 * 13 + 3) and a["actions"].shape == (len(data), 9)
    assert np.allclose(a["actions"].sum(1), 1.0, atol=1e-5)
    assert np.allclose(a["rewards"], data.team_rewards)
    spans = episodes(data)
    assert len(spans) == 3 and all(a["truncations"][s][-1] and not a["truncations"][s][:-1].any() for s in spans)
    assert not a["terminations"].any()  # the env never terminates; the horizon truncates


def test_d3rlpy_trains_on_the_exported_dataset(data):
    d3rlpy = pytest.importorskip("d3rlpy")
    from marl_amod.export import to_d3rlpy

    ds = to_d3rlpy(data)
    assert ds.size() == 3 and sum(ep.size() for ep in ds.episodes) == len(data)
    bc = d3rlpy.algos.BCConfig(batch_size=8).create(device="cpu:0")
    bc.fit(ds, n_steps=5, n_steps_per_epoch=5, show_progress=False, save_interval=10**9,
           logger_adapter=d3rlpy.logging.NoopAdapterFactory())  # no d3rlpy_logs/ in the working directory
    assert bc.predict(ds.episodes[0].observations[:2]).shape == (2, 9)


def test_minari_holds_the_episodes(data, tmp_path, monkeypatch):
    minari = pytest.importorskip("minari")
    from marl_amod.export import to_minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    refs = {"equal-distribution": {"mean": 1.0}, "mpc-oracle": {"mean": 2.0}}
    ds = to_minari(data, "marl_amod/tiny/prop-v0", card={"reference_scores": refs})
    assert ds.total_episodes == 3 and ds.total_steps == len(data)
    ep = next(ds.iterate_episodes())
    rows = episodes(data)[0]
    assert np.allclose(ep.actions, centralised_arrays(data)["actions"][rows])
    assert ep.observations.shape[0] == rows.stop - rows.start + 1
    # the card's references are Minari's score range (Minari keeps them only with an eval env, so
    # they must be written apart): ED's profit scores 0, MPC-Oracle's 1
    assert np.allclose(minari.get_normalized_score(ds, np.array([1.0, 1.5, 2.0])), [0.0, 0.5, 1.0])


def test_a_missing_library_is_a_config_error_naming_the_extra(data, monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "d3rlpy", None)  # import d3rlpy now raises ImportError
    from marl_amod.export import to_d3rlpy

    with pytest.raises(ConfigError, match=r"marl-amod\[d3rlpy\]"):
        to_d3rlpy(data)


def test_a_policy_on_the_exported_view_plays_through_evaluate(city):
    """What an offline library learns from the export reads env.state() and answers the joint action;
    state_policy turns it into the observations -> actions callable that marl_amod.evaluate scores."""
    import marl_amod
    from marl_amod.export import state_policy

    env = marl_amod.parallel_env(city)
    seen = []
    policy = state_policy(lambda state: seen.append(state) or np.ones(city.n_regions), n_features=13)
    obs, _ = env.reset(seed=2)
    while env.agents:
        actions = policy(obs)
        np.testing.assert_array_equal(seen[-1], env.state())  # the exported observation, exactly
        assert set(actions) == set(env.agents) and all(a.shape == (1,) for a in actions.values())
        obs, *_ = env.step(actions)
    ed = marl_amod.evaluate("equal-distribution", city, episodes=2, seed=0)["metrics"]
    record = marl_amod.evaluate(policy, city, episodes=2, seed=0)
    assert record["metrics"] == ed  # all ones: equal distribution
    # the record's policy name (results tables file rows by it) says what it is, not the inner function's "act"
    assert record["policy"] == "state-policy"
    assert marl_amod.evaluate(policy, city, episodes=1, seed=0, name="bc-d3rlpy")["policy"] == "bc-d3rlpy"


@pytest.mark.parametrize("n_features, hint", [(7, r"lookahead=3\)"), (14, "lookahead=6, arrivals_now=True")])
def test_a_state_policy_on_observations_of_another_look_ahead_is_refused(n_features, hint):
    """The env's observations must hold the dataset's F features: on a city whose neighbour slots
    K = 3 an F = 13 observation also splits as F = 7 (13 + 3 + 3 * 14 = 7 + 3 + 5 * 8), which gave
    a state of the right size for a look-ahead-3 model built from the wrong numbers."""
    import marl_amod
    from marl_amod.export import state_policy

    city = load_city("synthetic", rows=2, cols=3)  # in-degrees 2 and 3: K = 3
    obs, _ = marl_amod.parallel_env(city).reset(seed=0)  # look-ahead 6: F = 13
    policy = state_policy(lambda state: np.ones(city.n_regions), n_features=n_features)
    with pytest.raises(ConfigError, match=f"n_features={n_features}.*{hint}"):
        policy(obs)


def test_a_state_policy_of_another_city_or_no_features_is_refused():
    import marl_amod
    from marl_amod.export import state_policy

    city = load_city("synthetic", rows=2, cols=3)
    obs, _ = marl_amod.parallel_env(city).reset(seed=0)
    with pytest.raises(ConfigError, match="answered 16 weights for this city's 6 regions"):  # learnt on the 16-region city
        state_policy(lambda state: np.ones(16))(obs)
    with pytest.raises(ConfigError, match="n_features must be an integer >= 3"):
        state_policy(lambda state: np.ones(6), n_features=0)


def test_a_bad_minari_id_or_card_is_refused_before_anything_is_written(data, tmp_path, monkeypatch):
    pytest.importorskip("minari")
    from marl_amod.errors import DataError
    from marl_amod.export import to_minari

    monkeypatch.setenv("MINARI_DATASETS_PATH", str(tmp_path))
    with pytest.raises(ConfigError, match="end in a version"):
        to_minari(data, "marl_amod/tiny/prop")
    with pytest.raises(ConfigError, match="card must be the dataset card as a dict"):
        to_minari(data, "marl_amod/tiny/prop-v0", card="card.json")
    with pytest.raises(DataError, match="needs equal-distribution, mpc-oracle"):
        to_minari(data, "marl_amod/tiny/prop-v0", card={"reference_scores": {"equal-distribution": {"mean": 1.0}}})
    assert not any(tmp_path.iterdir())  # nothing left to block the retry
    assert to_minari(data, "marl_amod/tiny/prop-v0").total_episodes == 3
