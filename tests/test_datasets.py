"""Offline datasets (format 2): what the env's agents saw and did, round-tripped, in both views."""

from __future__ import annotations

import json

import numpy as np
import pytest
from typer.testing import CliRunner

from marl_amod import parallel_env
from marl_amod.cli import app
from marl_amod.datasets import (
    ARRAY_KEYS,
    EnvActionPolicy,
    OfflineDataset,
    collect,
    collection_seed,
    merge,
    normalised_score,
    read_card,
    write_card,
)
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import episode_seeds, evaluate
from marl_amod.policies import make_policy


@pytest.fixture
def dataset(tiny_city) -> OfflineDataset:
    return collect(tiny_city, make_policy("prop", tiny_city), episodes=2, seed=3)


def test_dataset_round_trips_through_npz(dataset, tmp_path):
    path = dataset.save(tmp_path / "sub" / "d.npz")
    back = OfflineDataset.load(path)
    for key in (*ARRAY_KEYS, "edge_index", "edge_attr"):
        assert np.array_equal(getattr(back, key), getattr(dataset, key)), key
        assert getattr(back, key).dtype == getattr(dataset, key).dtype
    assert back.meta == dataset.meta and back.meta["format_version"] == 2


def test_dataset_holds_the_envs_observations_actions_and_rewards(tiny_city, dataset):
    steps, n = tiny_city.horizon - 1, tiny_city.n_regions
    env = parallel_env(tiny_city, reward_mode="local")
    obs, _ = env.reset(seed=collection_seed(3, 0))
    assert len(dataset) == 2 * steps and dataset.actions.shape == (2 * steps, n)
    assert np.array_equal(dataset.observations[0], np.stack([obs[a] for a in env.possible_agents]))
    assert np.array_equal(dataset.states[0], env.state())
    # replaying the logged actions through the env gives the logged next observations and rewards
    for t in range(steps):
        nxt, rew, _, truncs, _ = env.step({a: dataset.actions[t, i : i + 1] for i, a in enumerate(env.possible_agents)})
        assert np.array_equal(dataset.next_observations[t], np.stack([nxt[a] for a in env.possible_agents]))
        assert np.allclose(dataset.rewards[t], [rew[a] for a in env.possible_agents])
        assert dataset.truncations[t] == truncs["region_0"]
    assert np.all((dataset.actions >= 0) & (dataset.actions <= 1))
    assert np.allclose(dataset.rewards.sum(axis=1), dataset.team_rewards, rtol=1e-4, atol=1e-2)
    assert not dataset.terminations.any() and dataset.truncations.sum() == 2 and dataset.truncations[steps - 1]
    within = ~dataset.truncations[:-1]
    assert np.array_equal(dataset.next_observations[:-1][within], dataset.observations[1:][within])
    assert np.array_equal(dataset.step_ids[:steps], np.arange(steps)) and set(dataset.episode_ids) == {0, 1}


@pytest.mark.parametrize("name", ["inf", "dtv"])
def test_target_policies_are_logged_as_actions_that_reproduce_their_targets(tiny_city, name):
    """The env floors w / sum(w) * M; the logged weights give the behaviour policy's targets back."""
    data = collect(tiny_city, make_policy(name, tiny_city), episodes=1, seed=0)
    assert data.meta["target_mismatch"] == 0.0
    ours = evaluate(EnvActionPolicy(make_policy(name, tiny_city)), tiny_city, episodes=2, seed=0)
    theirs = evaluate(name, tiny_city, episodes=2, seed=0)
    assert ours["metrics"]["profit"]["mean"] == pytest.approx(theirs["metrics"]["profit"]["mean"])


def test_collection_seeds_are_not_evaluation_seeds(tiny_city, dataset):
    """Episode 0 of the dataset is not episode 0 of `evaluate --seed 3` (nor of seed 0)."""
    from marl_amod.system import FleetSystem

    demand = FleetSystem(tiny_city)
    demand.reset(collection_seed(3, 0))
    logged = demand.sim.demand.copy()
    for s in (0, 3):
        demand.reset(episode_seeds(s, 0)[0])
        assert not np.array_equal(logged, demand.sim.demand)


def test_dataset_rewards_add_up_to_the_episode_profit(tiny_city, dataset):
    """Episode profit = the reset's dispatch (no transition) + the logged team rewards = the env's own total."""
    profits = []
    for ep in range(2):
        env = parallel_env(tiny_city)
        env.reset(seed=collection_seed(3, ep))
        first_dispatch = env.last_outcome.reward
        for t in np.flatnonzero(dataset.episode_ids == ep):
            _, _, _, _, infos = env.step({a: dataset.actions[t, i : i + 1] for i, a in enumerate(env.possible_agents)})
        profits.append(infos["region_0"]["system_profit"])
        assert first_dispatch + dataset.team_rewards[dataset.episode_ids == ep].sum() == pytest.approx(profits[-1], rel=1e-5)
    assert dataset.meta["episode_profit_mean"] == pytest.approx(np.mean(profits), rel=1e-5)


def test_views_give_the_graph_and_the_agents(tiny_city, dataset):
    g = dataset.global_view()
    n, f = tiny_city.n_regions, dataset.n_features
    assert g["x"].shape == (len(dataset), n, f)
    assert np.array_equal(g["x"], dataset.observations[:, :, :f])  # own block of each agent = its graph row
    assert np.allclose(g["action"].sum(axis=1), 1, atol=1e-5) and np.array_equal(g["done"], dataset.truncations)
    agents = dataset.agent_view()
    assert list(agents) == [f"region_{i}" for i in range(n)]
    a = agents["region_2"]
    assert a["observation"].shape == (len(dataset), dataset.observations.shape[2]) and a["action"].shape == (len(dataset), 1)
    assert np.array_equal(a["reward"], dataset.rewards[:, 2]) and np.array_equal(a["truncation"], dataset.truncations)


def test_card_scores_the_behaviour_policy_and_the_references(tiny_city, dataset, tmp_path):
    path = dataset.save(tmp_path / "d.npz")
    card = write_card(path, dataset, tiny_city, make_policy("prop", tiny_city), eval_episodes=2, eval_seed=0)
    assert read_card(path) == json.loads(json.dumps(card))
    refs = card["reference_scores"]
    assert normalised_score(refs["equal-distribution"]["mean"], refs) == 0.0
    assert normalised_score(refs["mpc-oracle"]["mean"], refs) == pytest.approx(100.0)
    prop = evaluate("prop", tiny_city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    assert card["behaviour_score"]["mean"] == pytest.approx(prop)
    assert card["episodes"] == 2 and card["transitions"] == len(dataset) and card["policy"] == "prop"


def test_loading_a_foreign_or_old_file_is_a_data_error(tmp_path, dataset):
    with pytest.raises(DataError):
        OfflineDataset.load(tmp_path / "missing.npz")
    np.savez(tmp_path / "other.npz", x=np.zeros(3))
    with pytest.raises(DataError):
        OfflineDataset.load(tmp_path / "other.npz")
    np.savez(tmp_path / "v1.npz", meta=np.array(json.dumps({"format_version": 1})))
    with pytest.raises(DataError, match="format 1"):
        OfflineDataset.load(tmp_path / "v1.npz")
    # the card beside a dataset, or any file that is no .npz: a DataError, not numpy's advice to unpickle it
    (tmp_path / "data.json").write_text('{"policy": "prop"}')
    with pytest.raises(DataError, match=r"data\.json is not a marl_amod dataset .*card"):
        OfflineDataset.load(tmp_path / "data.json")
    (tmp_path / "cut.npz").write_bytes(b"PK\x03\x04 truncated")
    with pytest.raises(DataError, match=r"cut\.npz is not a marl_amod dataset"):
        OfflineDataset.load(tmp_path / "cut.npz")


def test_cli_collect_writes_a_dataset_and_its_card(tmp_path):
    out = tmp_path / "data.npz"
    args = ["collect", "--policy", "dtv", "--episodes", "1", "--seed", "1", "--output", str(out), "--eval-episodes", "1"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    data = OfflineDataset.load(out)
    assert data.meta["policy"] == "dtv" and data.truncations.sum() == 1
    assert read_card(out)["behaviour_score"]["mean"] > 0
    # collected again over it without a card: the first dataset's card is not left to describe the new one
    again = CliRunner().invoke(app, [*args[:2], "prop", *args[3:-1], "0"])
    assert again.exit_code == 0, again.output
    assert OfflineDataset.load(out).meta["policy"] == "prop" and not out.with_suffix(".json").exists()


def test_a_dataset_named_like_its_card_is_refused_before_collecting(tmp_path, dataset):
    """The card is written beside the dataset as <name>.json: a dataset path ending in .json would be
    overwritten by its own card, so collect refuses it before the run and save() refuses it too."""
    out = tmp_path / "data.json"
    args = ["collect", "--policy", "prop", "--episodes", "1", "--output", str(out), "--eval-episodes", "1"]
    result = CliRunner().invoke(app, args)
    assert isinstance(result.exception, ConfigError) and "card" in str(result.exception) and not out.exists()
    with pytest.raises(ConfigError, match=r"data\.json.*\.npz"):
        dataset.save(out)


def test_cli_collect_passes_policy_options_and_names_the_teacher(tmp_path):
    out = tmp_path / "data.npz"
    args = ["collect", "--policy", "mpc-forecast", "--policy-option", "demand_scale=1.3", "--policy-option", "horizon=4",
            "--episodes", "1", "--output", str(out), "--eval-episodes", "0"]  # fmt: skip
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert OfflineDataset.load(out).meta["policy"] == "mpc-forecast+scale1.3"


def test_noisy_collection_logs_exploratory_actions_around_the_policy(tiny_city):
    plain = collect(tiny_city, make_policy("prop", tiny_city), episodes=1, seed=0)
    noisy = collect(tiny_city, make_policy("prop", tiny_city), episodes=1, seed=0, noise=0.05)
    again = collect(tiny_city, make_policy("prop", tiny_city), episodes=1, seed=0, noise=0.05)
    assert noisy.meta["policy"] == "prop+noise0.05" and noisy.meta["noise"] == 0.05
    assert np.array_equal(noisy.actions, again.actions)  # seeded
    assert not np.allclose(noisy.actions[0], plain.actions[0])
    assert np.array_equal(noisy.observations[0], plain.observations[0])  # same demand, same first state
    assert np.abs(noisy.actions[0] - plain.actions[0]).sum() < 1.0  # around the policy's share, not anywhere


# ------------------------------------------------------------------ pieces of one collection
def _same_arrays(a: OfflineDataset, b: OfflineDataset) -> bool:
    return all(np.array_equal(getattr(a, k), getattr(b, k)) for k in (*ARRAY_KEYS, "edge_index", "edge_attr"))


def test_a_resumed_piece_merges_into_exactly_the_one_long_collection(tiny_city):
    prop = make_policy("prop", tiny_city)
    whole = collect(tiny_city, prop, episodes=3, seed=3)
    head = collect(tiny_city, prop, episodes=1, seed=3)
    tail = collect(tiny_city, prop, episodes=2, seed=3, first_episode=1)
    assert set(tail.episode_ids) == {1, 2} and tail.meta["streams"] == [[3, 1, 2]]
    for parts in ([head, tail], [tail, head]):  # the order given does not matter
        merged = merge(parts)
        assert _same_arrays(merged, whole)
        assert merged.meta["streams"] == [[3, 0, 3]] and merged.meta["seed"] == 3
        assert merged.meta["episodes"] == 3 and merged.meta["transitions"] == len(whole)
        assert merged.meta["episode_profit_mean"] == pytest.approx(whole.meta["episode_profit_mean"])
        assert merged.meta["episode_profit_std"] == pytest.approx(whole.meta["episode_profit_std"])


def test_pieces_with_different_seeds_hold_different_demand(tiny_city):
    prop = make_policy("prop", tiny_city)
    a, b = (collect(tiny_city, prop, episodes=2, seed=s) for s in (4, 5))
    merged = merge([b, a])
    assert merged.meta["streams"] == [[4, 0, 2], [5, 0, 2]] and merged.meta["seed"] == [4, 5]
    assert np.array_equal(merged.episode_ids, np.repeat(np.arange(4), len(a) // 2))
    assert _same_arrays(OfflineDataset(**{k: getattr(merged, k)[: len(a)] for k in ARRAY_KEYS},
                                       edge_index=a.edge_index, edge_attr=a.edge_attr, meta=a.meta), a)  # fmt: skip
    first_states = merged.states[merged.step_ids == 0]
    assert len({row.tobytes() for row in first_states}) == 4  # four different demand streams, none shared


def test_merge_refuses_overlapping_or_foreign_pieces(tiny_city):
    prop = make_policy("prop", tiny_city)
    a = collect(tiny_city, prop, episodes=2, seed=3)
    with pytest.raises(DataError, match=r"a and b both hold episodes 1\.\.1 of seed 3"):
        merge([a, collect(tiny_city, prop, episodes=2, seed=3, first_episode=1)], names=["a", "b"])
    with pytest.raises(DataError, match=r"a and a both hold episodes 0\.\.1 of seed 3"):  # one file given twice
        merge([a, a], names=["a", "a"])
    with pytest.raises(DataError, match="policy"):
        merge([a, collect(tiny_city, make_policy("dtv", tiny_city), episodes=1, seed=4)])
    with pytest.raises(DataError, match="noise"):
        merge([a, collect(tiny_city, prop, episodes=1, seed=4, noise=0.1)])
    other = collect(tiny_city, prop, episodes=1, seed=4)
    other.meta["policy_options"] = {"horizon": 4}  # the name alone does not say it
    with pytest.raises(DataError, match="policy_options"):
        merge([a, other])


def test_cli_merges_pieces_and_writes_one_card(tmp_path):
    run = CliRunner().invoke
    common = ["collect", "--policy", "mpc-forecast", "--policy-option", "horizon=4", "--episodes", "1", "--eval-episodes", "1"]
    pieces = (("a", ["--seed", "1"]), ("b", ["--seed", "1", "--first-episode", "1"]), ("c", ["--seed", "2", "--eval-episodes", "0"]))
    for name, extra in pieces:  # one card is enough: the scores are the policy's, not the data's
        result = run(app, [*common, *extra, "--output", str(tmp_path / f"{name}.npz")])
        assert result.exit_code == 0, result.output
    out = tmp_path / "m.npz"
    result = run(app, ["merge-datasets", *(str(tmp_path / f"{n}.npz") for n in "cba"), "--output", str(out)])
    assert result.exit_code == 0, result.output
    card, piece = read_card(out), read_card(tmp_path / "a.npz")
    data = OfflineDataset.load(out)
    assert card["episodes"] == 3 and card["transitions"] == len(data) == 3 * len(OfflineDataset.load(tmp_path / "a.npz"))
    assert card["streams"] == [[1, 0, 2], [2, 0, 1]] and card["policy_options"] == {"horizon": 4}
    assert card["behaviour_score"] == piece["behaviour_score"] and card["sha256"] != piece["sha256"]
    assert card["dataset"] == "m.npz" and card["policy"] == "mpc-forecast"
    again = run(app, ["merge-datasets", str(tmp_path / "a.npz"), str(out), "--output", str(tmp_path / "x.npz")])
    assert again.exit_code != 0 and "both hold episodes 0..0 of seed 1" in str(again.exception)
    card = read_card(tmp_path / "b.npz")
    card["reference_scores"]["mpc-oracle"]["mean"] += 1.0  # scored on other evaluation streams
    (tmp_path / "b.json").write_text(json.dumps(card))
    again = run(app, ["merge-datasets", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--output", str(tmp_path / "y.npz")])
    assert again.exit_code != 0 and "scored differently (reference_scores)" in str(again.exception)


def test_merge_cards_refuses_a_card_left_from_another_collection_at_a_pieces_path(tiny_city, tmp_path):
    """``collect --eval-episodes 0`` over an earlier piece leaves that piece's card beside the new
    data: its scores are of whatever was collected there before, so the merged card must not take them."""
    from marl_amod.datasets import merge_cards

    prop = make_policy("prop", tiny_city)
    a, b = (collect(tiny_city, prop, episodes=1, seed=s) for s in (1, 2))
    for name, data in (("a", a), ("b", b)):
        data.save(tmp_path / f"{name}.npz")
        write_card(tmp_path / f"{name}.npz", data, tiny_city, prop, eval_episodes=1)
    merged = merge([a, b])
    merged.save(tmp_path / "m.npz")
    assert merge_cards(tmp_path / "m.npz", merged, [tmp_path / "a.npz", tmp_path / "b.npz"])["episodes"] == 2
    dtv = make_policy("dtv", tiny_city)
    collect(tiny_city, dtv, episodes=1, seed=2).save(tmp_path / "b.npz")  # b.json is prop's card still
    with pytest.raises(DataError, match=r"b\.json is not the card of .*b\.npz"):
        merge_cards(tmp_path / "m.npz", merged, [tmp_path / "a.npz", tmp_path / "b.npz"])


def test_merging_cardless_pieces_over_an_earlier_merge_leaves_no_stale_card(tiny_city, tmp_path):
    prop = make_policy("prop", tiny_city)
    for name, seed in (("a", 1), ("b", 2), ("c", 3), ("d", 4)):
        data = collect(tiny_city, prop, episodes=1, seed=seed)
        data.save(tmp_path / f"{name}.npz")
        if name in "ab":
            write_card(tmp_path / f"{name}.npz", data, tiny_city, prop, eval_episodes=1)
    out = tmp_path / "m.npz"
    run = CliRunner().invoke
    result = run(app, ["merge-datasets", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--output", str(out)])
    assert result.exit_code == 0, result.output
    assert read_card(out)["streams"] == [[1, 0, 1], [2, 0, 1]]
    result = run(app, ["merge-datasets", str(tmp_path / "c.npz"), str(tmp_path / "d.npz"), "--output", str(out)])
    assert result.exit_code == 0, result.output
    assert OfflineDataset.load(out).meta["streams"] == [[3, 0, 1], [4, 0, 1]]
    assert not out.with_suffix(".json").exists()  # the a+b card described the file this merge replaced


def test_merge_refuses_a_concatenation_of_collections(tiny_city):
    """A DAgger aggregate (``concatenate``) mixes collections and may revisit a stream; merged as a
    piece, the result kept its first parts' record only (or blamed the piece for overlapping itself)."""
    from marl_amod.datasets import concatenate

    prop = make_policy("prop", tiny_city)
    a, b, c = (collect(tiny_city, prop, episodes=1, seed=s) for s in (1, 2, 3))
    for parts in ([concatenate([a, b]), c], [concatenate([a, a])]):
        with pytest.raises(DataError, match="concatenation"):
            merge(parts, names=[f"p{i}" for i in range(len(parts))])


def test_merge_says_which_piece_does_not_record_what_the_other_does(tiny_city):
    """A piece collected before the policy options were logged (or through the Python API) cannot
    be told to be the same collection: the error says so and what to do, not ``{} != None``."""
    prop = make_policy("prop", tiny_city)
    a, b = (collect(tiny_city, prop, episodes=1, seed=s) for s in (1, 2))
    b.meta["policy_options"] = {}  # as marl-amod collect logs it
    with pytest.raises(DataError, match=r"a does not record policy_options .*collect it again"):
        merge([a, b], names=["a", "b"])
    dagger = collect(tiny_city, prop, episodes=1, seed=3, labeller=make_policy("prop", tiny_city))
    with pytest.raises(DataError, match="not one collection: rollout_policy"):  # a DAgger piece is another collection
        merge([a, dagger])


# ------------------------------------------------------------------ mixtures of behaviours
def test_mix_joins_behaviours_on_shared_streams_and_refuses_one_behaviour_twice(tiny_city, tmp_path):
    from marl_amod.datasets import concatenate, mix

    prop, dtv = make_policy("prop", tiny_city), make_policy("dtv", tiny_city)
    plain, noisy = collect(tiny_city, prop, episodes=2, seed=3), collect(tiny_city, prop, episodes=2, seed=3, noise=0.1)
    other = collect(tiny_city, dtv, episodes=1, seed=4)
    mixed = mix([plain, noisy, other])
    assert len(mixed) == len(plain) + len(noisy) + len(other) and mixed.meta["episodes"] == 5
    assert mixed.meta["policy"] == "prop & prop+noise0.1 & dtv" and "noise" not in mixed.meta
    assert [p["noise"] for p in mixed.meta["parts"]] == [0.0, 0.1, 0.0]
    assert np.array_equal(mixed.episode_ids, np.repeat(np.arange(5), len(other)))
    assert np.array_equal(mixed.actions[: len(plain)], plain.actions)
    starts = mixed.states[mixed.step_ids == 0]
    assert np.array_equal(starts[0], starts[2]) and not np.array_equal(plain.actions, noisy.actions)  # same demand, other acts
    with pytest.raises(DataError, match=r"a and b both hold prop's episodes 1\.\.1 of seed 3: they would weigh twice"):
        mix([plain, collect(tiny_city, prop, episodes=2, seed=3, first_episode=1)], names=["a", "b"])
    with pytest.raises(DataError, match="at least two"):
        mix([plain])
    aggregate = concatenate([plain, plain])  # a DAgger aggregate may revisit its streams: that is its own record, not a twin
    assert mix([aggregate, other]).meta["episodes"] == 5
    plain.save(tmp_path / "p.npz")
    wider = OfflineDataset.load(tmp_path / "p.npz")
    wider.meta["lookahead"] = 3  # logged with other features: refused as by concatenate
    with pytest.raises(DataError, match="lookahead"):
        mix([noisy, wider])


def test_cli_mixes_behaviours_and_cards_each_one(tmp_path):
    run = CliRunner().invoke
    common = ["collect", "--policy", "prop", "--episodes", "1"]
    parts = (("a", ["--seed", "1", "--eval-episodes", "1"]), ("b", ["--seed", "1", "--noise", "0.1", "--eval-episodes", "1"]),
             ("c", ["--seed", "2", "--policy", "dtv", "--eval-episodes", "0"]), ("d", ["--seed", "3", "--eval-episodes", "0"]))  # fmt: skip
    for name, extra in parts:
        result = run(app, [*common, *extra, "--output", str(tmp_path / f"{name}.npz")])
        assert result.exit_code == 0, result.output
    out = tmp_path / "m.npz"
    result = run(app, ["mix-datasets", *(str(tmp_path / f"{n}.npz") for n in "abc"), "--output", str(out)])
    assert result.exit_code == 0, result.output
    assert "3 episodes (1 of prop, 1 of prop+noise0.1, 1 of dtv)" in " ".join(result.output.split())
    card, a, b = read_card(out), read_card(tmp_path / "a.npz"), read_card(tmp_path / "b.npz")
    assert "behaviour_score" not in card and card["reference_scores"] == a["reference_scores"]
    assert [s["behaviour"] for s in card["behaviour_scores"]] == ["prop", "prop+noise0.1", "dtv"]
    assert [s["score"] for s in card["behaviour_scores"]] == [a["behaviour_score"], b["behaviour_score"], None]
    assert card["policy"] == "prop & prop+noise0.1 & dtv" and card["episodes"] == 3 == OfflineDataset.load(out).meta["episodes"]
    nested = run(app, ["mix-datasets", str(out), str(tmp_path / "b.npz"), "--output", str(tmp_path / "n.npz")])
    assert nested.exit_code != 0 and "both hold prop+noise0.1's episodes 0..0 of seed 1" in str(nested.exception)
    result = run(app, ["mix-datasets", str(out), str(tmp_path / "d.npz"), "--output", str(tmp_path / "n.npz")])
    assert result.exit_code == 0, result.output  # a mixture is a part like any other; its card keeps its parts' scores
    assert read_card(tmp_path / "n.npz")["behaviour_scores"][0]["score"] == card["behaviour_scores"]
    again = run(app, ["mix-datasets", str(tmp_path / "a.npz"), str(tmp_path / "a.npz"), "--output", str(tmp_path / "x.npz")])
    assert again.exit_code != 0 and "are the same data" in str(again.exception)
    b["reference_scores"]["mpc-oracle"]["mean"] += 1.0  # scored on other evaluation streams
    (tmp_path / "b.json").write_text(json.dumps(b))
    again = run(app, ["mix-datasets", str(tmp_path / "a.npz"), str(tmp_path / "b.npz"), "--output", str(tmp_path / "y.npz")])
    assert again.exit_code != 0 and "scored differently (reference_scores)" in str(again.exception)
