"""Policy ensembles: the members' mean, what each member is told it did, the file, and transfer's row."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from marl_amod.algos import meta
from marl_amod.baselines import EqualDistribution, Proportional
from marl_amod.ensemble import NOTES, PolicyEnsemble, write_ensemble
from marl_amod.errors import ConfigError, OutputError
from marl_amod.evaluation import evaluate
from marl_amod.policies import make_policy
from marl_amod.scenario import grid_city, load_city
from marl_amod.system import FleetSystem
from marl_amod.transfer import run_strategy


def _meta_file(tmp_path, name: str, seed: int) -> str:
    """A small meta-policy file for the synthetic city (an untrained model of ``seed``, its card by ``finish``)."""
    args = meta.Args(scenario="synthetic", hidden=8, trial_episodes=2, final_eval_episodes=1, seed=seed,
                     run_dir=str(tmp_path / name), policy_out=str(tmp_path / f"{name}.pt"))  # fmt: skip
    torch.manual_seed(seed)
    return meta.finish(args, meta.make_model(args), 0.0, 0, None)["policy"]


@pytest.fixture(scope="module")
def members(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("members")
    return [_meta_file(tmp, f"m{seed}", seed) for seed in (0, 1)]


def _write(path, text: str) -> str:
    path.write_text(text)
    return str(path)


def test_an_ensemble_acts_as_the_mean_of_its_members_shares():
    city = grid_city(rows=3, cols=3, horizon=6)
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(0))
    ens = PolicyEnsemble([EqualDistribution(), Proportional()])
    ens.reset(system, np.random.default_rng(0))
    shares = [w / w.sum() for w in (EqualDistribution().weights(system), Proportional().weights(system))]
    np.testing.assert_allclose(ens.weights(system), (shares[0] + shares[1]) / 2, rtol=1e-12)
    with pytest.raises(ConfigError, match="two or more"):
        PolicyEnsemble([EqualDistribution()])


def test_each_meta_member_reads_the_ensembles_action_as_its_previous_one(members):
    city = load_city("synthetic")
    system = FleetSystem(city)
    system.reset(np.random.SeedSequence(0))
    ens, alone = (PolicyEnsemble([meta.load_policy(m, city, 1) for m in members]) for _ in range(2))
    for policy in (ens, alone):
        policy.reset(system, np.random.default_rng(0))
    own = [m.weights(system) for m in alone.members]  # each member on its own, on the same state
    assert not np.allclose(own[0], own[1])  # else this test could not tell the mean from either
    mean = ens.weights(system)
    np.testing.assert_allclose(mean, (own[0] + own[1]) / 2, rtol=1e-6)
    for m in ens.members:  # told the mean, not its own action
        torch.testing.assert_close(m.agent.prev_action, torch.as_tensor(mean * city.n_regions, dtype=torch.float32)[None])


def test_an_ensemble_of_one_policy_twice_plays_as_that_policy(tmp_path, members):
    """Two copies of one member: the mean is the member's own action, so every step and profit matches."""
    city = load_city("synthetic")
    twice = _write(tmp_path / "twice.yaml", f"members: [{members[0]}, {members[0]}]\n")
    alone = evaluate(meta.load_policy(members[0], city, 1), city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    both = evaluate(meta.load_policy(twice, city, 1), city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    assert both == pytest.approx(alone, rel=1e-9)
    other = evaluate(meta.load_policy(members[1], city, 1), city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    pair = _write(tmp_path / "pair.yaml", f"members: [{members[0]}, {members[1]}]\n")
    mixed = evaluate(make_policy(pair, city), city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    assert mixed not in (alone, other)  # both members count


def test_an_ensemble_file_loads_wherever_a_checkpoint_does_and_says_what_is_wrong(tmp_path, members):
    (tmp_path / "sub").mkdir()
    for i, m in enumerate(members):  # member paths are relative to the file
        (tmp_path / "sub" / f"m{i}.pt").write_bytes(open(m, "rb").read())
        (tmp_path / "sub" / f"m{i}.json").write_text(open(str(m).removesuffix(".pt") + ".json").read())
    good = _write(tmp_path / "sub" / "ens.yaml", "members: [m0.pt, m1.pt]\n")
    policy = make_policy(good, load_city("synthetic"))
    assert isinstance(policy, PolicyEnsemble) and policy.name == "ens" and len(policy.members) == 2
    assert np.isfinite(evaluate(good, "synthetic", episodes=1)["metrics"]["profit"]["mean"])
    for text, match in [("members: [m0.pt]\n", "at least 2"), ("members: [m0.pt, gone.pt]\n", "gone.pt not found"),
                        ("members: [m0.pt, ens.yaml]\n", "do not nest"), ("members: [m0.pt, m1.pt]\nweights: [1, 2]\n", "weights")]:  # fmt: skip
        with pytest.raises(ConfigError, match=match):
            make_policy(_write(tmp_path / "sub" / "bad.yaml", text), load_city("synthetic"))
    with pytest.raises(ConfigError, match="not found"):
        make_policy(str(tmp_path / "none.yaml"))


def test_the_meta_rl_row_of_an_ensemble_counts_every_members_adaptation_episodes(tmp_path, members):
    pair = _write(tmp_path / "pair.yaml", f"members: [{members[0]}, {members[1]}]\n")
    one = run_strategy("meta-rl", "synthetic", episodes=1, policy=members[0], adapt_episodes=2)["transfer"]
    two = run_strategy("meta-rl", "synthetic", episodes=1, policy=pair, adapt_episodes=2)["transfer"]
    assert (one["target_episodes"], two["target_episodes"]) == (2, 4)
    assert two["source_city"] == f"2 seeds x ({one['source_city']})" and two["source"] == pair


def test_the_ensemble_command_writes_a_file_that_loads_and_a_card_of_its_members(tmp_path, members):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    out = tmp_path / "made" / "pair.yaml"
    out.parent.mkdir()
    result = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(out)])
    assert result.exit_code == 0, result.output
    loaded = make_policy(str(out), load_city("synthetic"))
    assert [m.name for m in loaded.members] == ["m0", "m1"]  # relative paths that reach the members
    card = out.with_suffix(".md").read_text()
    assert all(f"| {m} | meta | {seed} |" in card for m, seed in zip(members, (0, 1), strict=True))
    assert "marl-amod evaluate --scenario synthetic --policy" in card
    notes = f"\n{NOTES}\nScore: written by hand, kept.\n"
    out.with_suffix(".md").write_text(card + notes)
    again = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(out)])
    assert again.exit_code == 0, again.output
    assert out.with_suffix(".md").read_text() == card + notes  # the generated part again, the notes kept
    bad = CliRunner().invoke(app, ["ensemble", str(members[0]), str(tmp_path / "none.pt"), "--out", str(tmp_path / "x.yaml")])
    assert bad.exit_code != 0 and not (tmp_path / "x.yaml").exists()
    cards = [str(m).removesuffix(".pt") + ".json" for m in members]
    for given, message in ((cards, "not a checkpoint"), ([str(members[0])] * 2, "given twice")):
        refused = CliRunner().invoke(app, ["ensemble", *given, "--out", str(tmp_path / "y.yaml")])
        assert isinstance(refused.exception, ConfigError) and message in str(refused.exception)
        assert not (tmp_path / "y.yaml").exists()  # refused before anything is written
    fresh = tmp_path / "new" / "deeper" / "pair.yaml"  # a folder that does not exist yet is made, as for every output
    made = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(fresh)])
    assert made.exit_code == 0, made.output
    assert [m.name for m in make_policy(str(fresh), load_city("synthetic")).members] == ["m0", "m1"]
    (tmp_path / "blocked").write_text("a file where the folder would go")
    blocked = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(tmp_path / "blocked" / "pair.yaml")])
    assert isinstance(blocked.exception, OutputError) and "is a file, not a folder" in str(blocked.exception)


def test_an_ensemble_of_actor_policies_acts_on_the_envs_observations_as_its_members_mean(tmp_path):
    import marl_amod

    members = ["a2c_gnn_synthetic.pt", "bc_gnn_synthetic_mpc_forecast.pt"]
    path = _write(tmp_path / "actors.yaml", "members: [" + ", ".join(str(Path("policies", m).resolve()) for m in members) + "]\n")
    env = marl_amod.parallel_env("synthetic")
    obs, _ = env.reset(seed=0)
    ens, alone = marl_amod.load_policy(path, "synthetic"), [marl_amod.load_policy(f"policies/{m}", "synthetic") for m in members]
    own = [np.concatenate([a(obs)[agent] for agent in env.agents]).astype(np.float64) for a in alone]
    assert not np.allclose(own[0] / own[0].sum(), own[1] / own[1].sum())
    got = np.concatenate([ens(obs)[agent] for agent in env.agents])
    np.testing.assert_allclose(got, (own[0] / own[0].sum() + own[1] / own[1].sum()) / 2, rtol=1e-6)
    env.step(ens(obs))  # the env takes them as any policy's actions


def test_an_ensemble_with_a_meta_member_says_it_cannot_act_on_observations(members):
    ens = PolicyEnsemble([meta.load_policy(m, load_city("synthetic"), 1) for m in members])
    with pytest.raises(ConfigError, match="reads the simulator"):
        ens({})


def test_the_meta_rl_row_says_seeds_only_for_members_of_one_recipe():
    from marl_amod.transfer import meta_used

    def card(seed, **args):
        hot = ["porto~hot1x2"] * 10 * args.get("hotspot_variants", 1)
        demos = {"cities": ["porto"] * 10, "episodes_per_city": 64, "hotspot_variants": hot, "episodes_per_variant": 32}
        return {"algorithm": "meta-bc", "args": {"seed": seed, "run_dir": f"r{seed}", "lr": 1e-3, **args}, "demonstrations": demos}

    assert meta_used([card(0)])["source_city"] == "10 training cities + 10 hotspot variants"
    assert meta_used([card(0), card(1)]) == {"source_city": "2 seeds x (10 training cities + 10 hotspot variants)", "source_episodes": None,
                                              "demonstrations": 2 * 960}  # fmt: skip
    assert meta_used([card(0), card(0, lr=1e-4)])["source_city"].startswith("2 members x (")
    assert meta_used([card(0), card(0, hotspot_variants=0)])["source_city"] == "2 members: 10 training cities + 10 hotspot variants; 10 training cities"
    older = card(1)
    del older["args"]["lr"]  # a card written before an argument existed is not another recipe for it
    assert meta_used([card(0), older])["source_city"].startswith("2 seeds x (")


def _stay_prior_file(tmp_path, name: str, level: float) -> str:
    """A stay-prior meta-policy whose actor outputs carry a common ``level`` (the actor's last bias)."""
    args = meta.Args(scenario="synthetic", hidden=8, trial_episodes=2, final_eval_episodes=1, stay_prior=True,
                     run_dir=str(tmp_path / name), policy_out=str(tmp_path / f"{name}.pt"))  # fmt: skip
    torch.manual_seed(0)
    model = meta.make_model(args)
    with torch.no_grad():
        model.actor[-1].bias += level
    return meta.finish(args, model, 0.0, 0, None)["policy"]


def test_adaptation_by_the_mean_or_the_priors_concentration_does_not_read_the_actors_level(tmp_path):
    """Two stay-prior policies that differ only in their actor's common level (-3 and +3: the same
    Dirichlet means, concentrations e^6 apart) adapt to different memories when they sample, and to
    the same one by the mean or with the prior's concentration."""
    city = load_city("synthetic")
    low, high = _stay_prior_file(tmp_path, "low", -3.0), _stay_prior_file(tmp_path, "high", 3.0)
    memory = {mode: [meta.load_policy(p, city, 2, seed=0, adaptation=mode).adapted for p in (low, high)]
              for mode in ("sampled", "mean", "prior-concentration")}  # fmt: skip
    assert not torch.allclose(*memory["sampled"], atol=1e-4)
    torch.testing.assert_close(*memory["mean"], rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(*memory["prior-concentration"], rtol=1e-4, atol=1e-5)
    assert not torch.allclose(memory["mean"][0], memory["prior-concentration"][0], atol=1e-4)


def test_an_ensemble_file_says_how_its_meta_members_adapt(tmp_path, members):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    city = load_city("synthetic")
    out = tmp_path / "pair.yaml"
    result = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(out), "--adaptation", "mean"])
    assert result.exit_code == 0, result.output
    assert "adaptation: mean" in out.read_text() and "--adaptation mean" in out.with_suffix(".md").read_text()
    by_file = [m.adapted for m in make_policy(str(out), city).members]
    by_call = [meta.load_policy(m, city, seed=0, adaptation="mean").adapted for m in members]
    for a, b in zip(by_file, by_call, strict=True):
        torch.testing.assert_close(a, b)
    sampled = meta.load_policy(members[0], city, seed=0).adapted
    assert not torch.allclose(by_file[0], sampled, atol=1e-4)
    bad = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(tmp_path / "b.yaml"), "--adaptation", "greedy"])
    assert bad.exit_code != 0 and "adaptation" in str(bad.exception) and not (tmp_path / "b.yaml").exists()
    actor = str(Path("policies", "a2c_gnn_synthetic.pt").resolve())
    with pytest.raises(ConfigError, match="not meta-policies"):
        write_ensemble(tmp_path / "c.yaml", [members[0], actor], "mean")


def test_meta_members_adapted_together_play_k_episodes_in_all_on_the_ensembles_path(tmp_path, members):
    """Together: one copy twice adapts as that copy alone (playing its mean, the mean of two equal
    actions is the action); two members each end up told the same executed action, their memories
    differ from those adapted alone, the same seed repeats them, and the row counts K episodes, not 2K."""
    city = load_city("synthetic")
    model, card = meta.load_meta(members[0])
    twice = meta.adapt_together([(model, card["lookahead"])] * 2, city, 2, seed=0, adaptations=["mean", "mean"])
    alone = meta.load_policy(members[0], city, 2, seed=0, adaptation="mean").adapted
    for policy in twice:
        torch.testing.assert_close(policy.adapted, alone, rtol=1e-5, atol=1e-6)

    pair = _write(tmp_path / "together.yaml", f"members: [{members[0]}, {members[1]}]\ntogether: true\n")
    together, again = (meta.load_policy(pair, city, 2, seed=0) for _ in range(2))
    assert isinstance(together, PolicyEnsemble) and [m.name for m in together.members] == ["m0", "m1"]
    torch.testing.assert_close(together.members[0].agent.prev_action, together.members[1].agent.prev_action)  # both told the mean
    for t, a in zip(together.members, again.members, strict=True):
        torch.testing.assert_close(t.adapted, a.adapted)  # reproducible by seed
    by_mean = meta.load_policy(pair, city, 2, seed=0, adaptation="mean")  # deterministic play: alone, each would drive its own path
    for t, m in zip(by_mean.members, members, strict=True):
        assert not torch.allclose(t.adapted, meta.load_policy(m, city, 2, seed=0, adaptation="mean").adapted, atol=1e-4)
    other = meta.load_policy(pair, city, 2, seed=1)
    assert not torch.allclose(other.members[0].adapted, together.members[0].adapted, atol=1e-4)
    assert np.isfinite(evaluate(make_policy(pair, city), city, episodes=1)["metrics"]["profit"]["mean"])  # via checkpoints too
    row = run_strategy("meta-rl", "synthetic", episodes=1, policy=pair, adapt_episodes=2)["transfer"]
    assert row["target_episodes"] == 2


def test_the_ensemble_command_writes_together_and_refuses_it_for_other_policies(tmp_path, members):
    from typer.testing import CliRunner

    from marl_amod.cli import app

    out = tmp_path / "pair.yaml"
    result = CliRunner().invoke(app, ["ensemble", str(members[0]), str(members[1]), "--out", str(out), "--together"])
    assert result.exit_code == 0, result.output
    assert "together: true" in out.read_text() and "--together" in out.with_suffix(".md").read_text()
    assert "adapt together" in out.with_suffix(".md").read_text()
    actor = str(Path("policies", "a2c_gnn_synthetic.pt").resolve())
    with pytest.raises(ConfigError, match="together is how meta-policies adapt"):
        write_ensemble(tmp_path / "c.yaml", [members[0], actor], together=True)
    with pytest.raises(ConfigError, match="together"):  # a file that says it for a non-bool
        make_policy(_write(tmp_path / "bad.yaml", f"members: [{members[0]}, {members[1]}]\ntogether: sometimes\n"), load_city("synthetic"))
