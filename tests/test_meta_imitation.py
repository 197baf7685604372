"""MPC-Forecast demonstrations and the imitation warm start of the meta-RL policy."""

from __future__ import annotations

from dataclasses import replace
from types import SimpleNamespace

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from pydantic import ValidationError

from marl_amod.algos import common as C
from marl_amod.algos import meta
from marl_amod.algos import meta_imitation as mi
from marl_amod.algos import offline as O
from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.baselines.mpc import MPCForecast
from marl_amod.errors import ConfigError, DataError
from marl_amod.evaluation import evaluate
from marl_amod.models import recurrent
from marl_amod.models.recurrent import RecurrentGNN
from marl_amod.scenario import load_city
from tests.conftest import needs_data


def tiny_args(tasks: list[str], tmp_path, name: str = "run", **overrides) -> mi.Args:
    """A meta-bc run small enough for a test: the synthetic tasks, 2 demonstrations a task, one update
    validated at once; its folder and policy file named ``name`` under ``tmp_path``; ``overrides`` on top."""
    return mi.Args(**{"scenario": "synthetic", "cities": tasks, "val_cities": tasks[:1], "hidden": 8, "trial_episodes": 2, "num_envs": 2,
                      "cities_per_update": 2, "demos": str(tmp_path / "demos"), "demo_episodes": 2, "updates": 1, "eval_every": 1,
                      "eval_episodes": 1, "final_eval_episodes": 1, "run_dir": str(tmp_path / name), "policy_out": str(tmp_path / f"{name}.pt")}
                   | overrides)  # fmt: skip


def _city_yaml(tmp_path, name, **keys):
    text = f"name: {name}\nsource: synthetic\nhorizon: 6\n" + "".join(f"{k}: {v}\n" for k, v in keys.items())
    (tmp_path / f"{name}.yaml").write_text(text)
    return str(tmp_path / f"{name}.yaml")


@pytest.fixture
def tasks(tmp_path):
    return [_city_yaml(tmp_path, "small", rows=2, cols=3, vehicles_per_region=5),
            _city_yaml(tmp_path, "large", rows=3, cols=3, vehicles_per_region=40, requests_per_region=20)]  # fmt: skip


def test_demonstrations_are_mpc_forecasts_episodes_in_the_policys_units(tasks, tmp_path):
    """The logged shares ask the coordinator for MPC-F's targets (to a vehicle per region), its
    replayed episode earns the logged rewards, and those are the per-city units the agent feeds back."""
    city = load_city(tasks[1])
    demos = mi.collect_city(city, episodes=2, seed=3, lookahead=6)
    e, t, n = demos["share"].shape
    assert (e, n) == (2, city.n_regions) and demos["x"].shape == (e, t, n, meta.n_task_features(6))
    np.testing.assert_allclose(demos["share"].sum(-1), 1.0, rtol=1e-5)
    np.testing.assert_allclose(demos["region_reward"].sum(-1), demos["reward"] * n, rtol=1e-4)
    from marl_amod.system import FleetSystem

    system, mpc = FleetSystem(city), MPCForecast()
    system.reset(mi.demo_seed(3, 1))
    mpc.reset(system, np.random.default_rng(0))
    rewards = []
    for share in demos["share"][1]:
        want = np.where((w := mpc.target(system)) < 0, system.sim.idle, w)
        asked = system.targets_from_weights(share.astype(np.float64))  # the share asks for MPC-F's targets (float32 floors)
        assert np.abs(asked - want).max() <= 1 and asked.sum() >= want.sum() - n
        rewards.append(system.step(want).reward / meta.CityScale.of(city).reward)
    np.testing.assert_allclose(rewards, demos["reward"][1], rtol=1e-4)


def test_collection_is_split_by_city_resumes_and_refuses_held_out_cities(tasks, tmp_path):
    folder = tmp_path / "demos"
    walls = mi.collect_demos(folder, tasks, episodes=1, seed=0, lookahead=6)
    assert set(walls) == {"small", "large"} and all(w > 0 for w in walls.values())
    stamp = (folder / "small.npz").stat().st_mtime_ns
    assert mi.collect_demos(folder, tasks, episodes=1, seed=0, lookahead=6) == walls  # nothing collected again
    assert (folder / "small.npz").stat().st_mtime_ns == stamp
    with pytest.raises(DataError, match="held-out"):
        mi.collect_demos(folder, ["nyc_brooklyn"], episodes=1, seed=0, lookahead=6)
    with pytest.raises(DataError, match="lookahead"):
        mi.load_demos(folder, load_city(tasks[0]), lookahead=3)
    for episodes, lookahead in [(2, 6), (1, 3)]:  # a stale file is refused, not reused
        with pytest.raises(DataError, match="holds 1 episodes at lookahead 6; this run asks for"):
            mi.collect_demos(folder, tasks, episodes=episodes, seed=0, lookahead=lookahead)
    assert mi.collect_demos(folder, tasks, episodes=1, seed=1, lookahead=6) == walls  # another seed's run reuses them (bc_dagger_place.yaml)
    assert (folder / "small.npz").stat().st_mtime_ns == stamp


def test_imitation_fits_mpc_forecasts_distribution(tasks, tmp_path):
    """Twenty teacher-forced steps bring the Dirichlet mean to MPC-F's shares: the
    cross-entropy falls towards the shares' own entropy (its minimum)."""
    mi.collect_demos(tmp_path / "d", tasks[1:], episodes=4, seed=0, lookahead=6)
    city = load_city(tasks[1])
    demos, graph = mi.load_demos(tmp_path / "d", city, 6), meta.city_graph(city)
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6), hidden=16)
    opt = torch.optim.Adam(model.parameters(), lr=3e-2)
    trials = np.array([[0, 1, 2, 3], [1, 2, 3, 0]])  # (K = 2 episodes, B = 4 trials)
    floor = float(-(demos.share * torch.log(demos.share.clamp_min(1e-12))).sum(-1).mean())
    first = None
    for _ in range(20):
        ce, vl = mi.imitation_losses(model, demos, trials, graph, gamma=0.97)
        first = ce.item() if first is None else first
        opt.zero_grad(), (ce + vl).backward(), opt.step()
    assert ce.item() - floor < 0.5 * (first - floor)


def test_imitation_ships_a_meta_policy_that_warm_starts_rl2(tasks, tmp_path, monkeypatch):
    args = tiny_args(tasks, tmp_path, "bc", updates=4, eval_every=2, eval_episodes=2)
    card = ALGOS["meta-bc"].train(args)["card"]
    assert card["algorithm"] == "meta-bc" and card["demonstrations"]["episodes_per_city"] == 2 and card["updates"] == 4
    assert card["demonstrations"]["seeds"] == [0]
    seed1 = ALGOS["meta-bc"].train(args.model_copy(update={"seed": 1, "run_dir": str(tmp_path / "bc1"), "policy_out": ""}))["card"]
    assert seed1["demonstrations"]["seeds"] == [0]  # a seed-1 run reused the seed-0 files: its card says so
    assert np.isfinite(evaluate(str(tmp_path / "bc.pt"), "synthetic", episodes=1)["metrics"]["profit"]["mean"])
    # RL² from that start, with the imitation term: 1 update of 2 cities x 2 trials x 2 episodes
    rl = meta.Args(scenario="synthetic", cities=tasks, val_cities=tasks[:1], hidden=8, episodes=8, trial_episodes=2, num_envs=2,
                   cities_per_update=2, init_actor=str(tmp_path / "bc.pt"), bc_coef=1.0, demos=str(tmp_path / "demos"),
                   eval_every=8, eval_episodes=2, final_eval_episodes=1, run_dir=str(tmp_path / "rl"), policy_out=str(tmp_path / "rl.pt"))  # fmt: skip
    card = ALGOS["meta"].train(rl)["card"]
    assert card["episodes_trained"] == 8 and card["warm_start"]["demonstrations"]["episodes_per_city"] == 2
    assert np.isfinite(card["warm_start"]["validation"])  # the start's validation, which RL² had to beat to replace it
    # the transfer table names the demonstrations the meta-policy's training used
    from marl_amod.transfer import run_strategy, study_markdown

    rec = run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "rl.pt"), adapt_episodes=1)
    assert rec["transfer"]["demonstrations"] == 4
    rec["normalised_score"] = 0.0
    assert "2 training cities (8) + 4 MPC-F demos" in study_markdown({"targets": {"synthetic": {"meta-rl": rec}}})
    log = (tmp_path / "rl" / "log.csv").read_text()
    assert "eval/scaled_return" in log
    with pytest.raises(DataError, match="hidden 8"):
        meta.train(rl.model_copy(update={"hidden": 4}))
    # the imitation term fits the loss the start was fitted with (an l1 member pulled towards the cross-entropy's optimum would drift)
    fits, real = [], mi.imitation_losses
    monkeypatch.setattr(mi, "imitation_losses", lambda *a: fits.append(a[5]) or real(*a))
    meta.train(rl.model_copy(update={"imitation": "l1", "shortfall_weight": 2.0, "run_dir": str(tmp_path / "rl_l1"), "policy_out": ""}))
    assert fits and all(f.imitation == "l1" and f.shortfall == 2.0 for f in fits)
    with pytest.raises(ValidationError, match="only l1 prices"):
        meta.Args(imitation="ce", shortfall_weight=2.0)


def test_dagger_episodes_are_the_learners_labelled_by_mpc_forecast(tasks):
    """With a learner the recurrent policy drives (its played shares are not MPC-F's) and MPC-F
    labels every state it reached: the label is what MPC-F asks there, the played share what the
    coordinator was given."""
    city = load_city(tasks[1])
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    got = mi.collect_city(city, episodes=2, seed=5, lookahead=6, learner=model, trial_episodes=2, seed_of=mi.dagger_seed)
    assert got["action"].shape == got["share"].shape and np.abs(got["action"] - got["share"]).sum(-1).mean() > 0.05
    from marl_amod.system import FleetSystem

    system, mpc = FleetSystem(city), MPCForecast()
    system.reset(mi.dagger_seed(5, 0))
    mpc.reset(system, np.random.default_rng(0))
    for x, share, played in zip(got["x"][0], got["share"][0], got["action"][0], strict=True):
        np.testing.assert_allclose(x, meta.task_features(system, meta.CityScale.of(city), 6), rtol=1e-5)  # the learner's states
        want = np.where((w := mpc.target(system)) < 0, system.sim.idle, w)
        np.testing.assert_allclose(share, want / want.sum(), rtol=1e-5)
        system.step(system.targets_from_weights(played.astype(np.float64)))
    demos = mi.collect_city(city, episodes=1, seed=5, lookahead=6)  # without a learner MPC-F plays its label
    np.testing.assert_array_equal(demos["action"], demos["share"])


def test_dagger_rounds_join_the_demonstrations_and_resume_from_disk(tasks, tmp_path):
    args = tiny_args(tasks, tmp_path, "bc", updates=4, eval_every=2, eval_episodes=2, dagger_rounds=2, dagger_every=2,
                     dagger_episodes=2, lr=0.01, lr_final=0.001)
    assert mi.lr_at(args, 0) == 0.01 and mi.lr_at(args, 2) == pytest.approx(0.01 * 0.1**0.5) and mi.lr_at(args, 9) == pytest.approx(0.001)
    said: list[tuple[int, str]] = []  # what the bar hears between updates: each task's collection, before it starts
    card = ALGOS["meta-bc"].train(args.model_copy(update={"updates": 2}), progress=lambda ep, total, stats: said.append((ep, stats.get("status", ""))))["card"]
    statuses = [text for _, text in said if text]
    assert statuses == [f"collecting MPC-Forecast demonstrations: {t} ({i}/2)" for i, t in enumerate(tasks, 1)] + [
        f"DAgger round 1: collecting its own episodes: {t} ({i}/2)" for i, t in enumerate(tasks, 1)]
    assert [ep for ep, text in said if text.startswith("DAgger")] == [args.dagger_first] * 2  # the round comes before that update
    rounds = tmp_path / "bc" / "dagger"
    assert card["dagger"]["rounds"] == 1 and sorted(p.name for p in rounds.iterdir()) == ["round1"]
    stamp = (rounds / "round1" / "small.npz").stat().st_mtime_ns
    card = ALGOS["meta-bc"].train(args, resume=str(tmp_path / "bc" / "state.pt"))["card"]  # round 1 read back, round 2 collected
    assert card["dagger"]["rounds"] == 2 and (rounds / "round2" / "large.npz").is_file() and card["updates"] == 4
    assert (rounds / "round1" / "small.npz").stat().st_mtime_ns == stamp
    # the step decays over the 4 updates of the resumed run, not over the first run's 2: update 3 (0-based) took lr_at(3)
    assert torch.load(tmp_path / "bc" / "state.pt", weights_only=False)["opt"]["param_groups"][0]["lr"] == pytest.approx(0.01 * 0.1**0.75)
    # continuing a shipped imitation, extended to the city-structure features: validated first, named on the card
    more = args.model_copy(update={"init_actor": str(tmp_path / "bc.pt"), "run_dir": str(tmp_path / "bc2"), "updates": 1, "dagger_rounds": 1,
                                   "city_features": True, "policy_out": str(tmp_path / "bc2.pt")})  # fmt: skip
    card = ALGOS["meta-bc"].train(more)["card"]
    assert card["warm_start"]["policy"] == str(tmp_path / "bc.pt") and card["warm_start"]["dagger"]["rounds"] == 2
    assert card["n_features"] == meta.n_task_features(6, structure=True)
    from marl_amod.transfer import run_strategy, study_markdown

    rec = run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "bc2.pt"), adapt_episodes=0)
    assert rec["transfer"]["target_episodes"] == 0 and np.isfinite(rec["metrics"]["profit"]["mean"])
    rec["normalised_score"] = 0.0  # (its 1 round + the start's 2) x 2 episodes x 2 cities
    assert "| 2 training cities + 4 MPC-F demos + 12 DAgger |" in study_markdown({"targets": {"synthetic": {"meta-rl": rec}}})
    # and once more, with the place features, a fleet readout and the first run's DAgger rounds joined
    last = more.model_copy(update={"init_actor": str(tmp_path / "bc2.pt"), "run_dir": str(tmp_path / "bc3"), "dagger_rounds": 0,
                                   "place_features": True, "readout": "mean-max", "more_demos": [str(rounds / f"round{k}") for k in (1, 2)],
                                   "policy_out": str(tmp_path / "bc3.pt")})  # fmt: skip
    cities = {name: load_city(name) for name in tasks}
    assert all(demos.episodes == 2 + 2 * 2 and demos.x.shape[-1] == meta.n_task_features(6, True, True) for demos, _ in mi.load_all(last, cities).values())
    card = ALGOS["meta-bc"].train(last)["card"]
    assert card["n_features"] == meta.n_task_features(6, True, True) and card["args"]["readout"] == "mean-max"
    model, _ = meta.load_meta(tmp_path / "bc3.pt")
    assert model.readout is not None
    assert np.isfinite(run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "bc3.pt"), adapt_episodes=1)["metrics"]["profit"]["mean"])


def test_meta_bc_training_is_reproducible_by_seed(tasks, tmp_path):
    """The same config and seed give the same policy to the bit, DAgger trials (sampled adaptation, shocks,
    whole trials) and validation included, whatever torch's and numpy's global streams held before: the recipe's seeds
    are compared with each other, so a seed must mean one run (docs/meta/log.md, "What the DAgger trials hold")."""
    common = {"updates": 3, "eval_every": 2, "num_envs": 4, "stay_prior": True, "dagger_rounds": 1, "dagger_first": 1, "dagger_episodes": 4,
              "dagger_whole_trials": True, "dagger_shock_prob": 0.5, "demos": str(tmp_path / "demos"), "seed": 3}  # fmt: skip
    runs = []
    for name, outside in (("a", 0), ("b", 99)):
        torch.manual_seed(outside), np.random.seed(outside)  # the run seeds both itself
        ALGOS["meta-bc"].train(tiny_args(tasks, tmp_path, name, **common))
        runs.append(torch.load(tmp_path / f"{name}.pt", weights_only=False)["state_dict"])
    assert runs[0].keys() == runs[1].keys() and all(torch.equal(runs[0][k], runs[1][k]) for k in runs[0])
    for task in ("small", "large"):
        a, b = (np.load(tmp_path / n / "dagger" / "round1" / f"{task}.npz") for n in ("a", "b"))
        np.testing.assert_array_equal(a["action"], b["action"])
    other = tiny_args(tasks, tmp_path, "c", **{**common, "seed": 4})
    ALGOS["meta-bc"].train(other)
    assert not all(torch.equal(runs[0][k], v) for k, v in torch.load(tmp_path / "c.pt", weights_only=False)["state_dict"].items())


def test_whole_dagger_trials_are_drawn_in_their_order_and_in_daggers_share():
    """With ``dagger_from`` a trial that draws a DAgger episode first is that episode's whole trial
    in the order played; the others draw demonstrations only, so DAgger's share of the trials is its
    share of the pool. Without DAgger episodes (before round 1) the draw is the plain one, rng for rng."""
    args = args_for("meta-bc", {"trial_episodes": 4, "num_envs": 16})
    pool, first, draws = SimpleNamespace(episodes=32), 20, 2000  # 20 demonstrations, then 3 DAgger trials of 4
    rng = np.random.default_rng(0)
    got = np.concatenate([mi.draw_trials(pool, args, rng, first) for _ in range(draws)], axis=1)
    whole = got[0] >= first
    assert got.shape == (4, 16 * draws) and (got[:, ~whole] < first).all()
    starts = got[0, whole]
    assert ((starts - first) % 4 == 0).all() and (got[:, whole] == starts + np.arange(4)[:, None]).all()
    assert set(starts) == {20, 24, 28} and abs(whole.mean() - 12 / 32) < 0.01
    for dagger_from in (None, 32):
        a, b = np.random.default_rng(1), np.random.default_rng(1)
        np.testing.assert_array_equal(mi.draw_trials(pool, args, a, dagger_from), b.integers(32, size=(4, 16)))


@pytest.mark.parametrize("values", [{"dagger_whole_trials": True}, {"dagger_whole_trials": True, "dagger_rounds": 2, "dagger_episodes": 6}])
def test_whole_dagger_trials_without_rounds_of_whole_trials_are_refused(values):
    with pytest.raises(ConfigError, match="dagger_whole_trials"):
        args_for("meta-bc", {"trial_episodes": 4, **values})
    assert args_for("meta-bc", {**values, "trial_episodes": 4, "dagger_rounds": 2, "dagger_episodes": 8}).dagger_whole_trials


def test_a_run_with_whole_dagger_trials_and_shocks_per_task_says_so_on_its_card_and_resumes_only_with_them(tasks, tmp_path, monkeypatch):
    args = tiny_args(tasks, tmp_path, "bc", num_envs=4, updates=2, eval_every=2, dagger_rounds=1, dagger_first=0,
                     dagger_episodes=4, dagger_whole_trials=True, dagger_shock_prob=0.5, dagger_shock_per_task=True)
    seen = []
    real = mi.draw_trials
    monkeypatch.setattr(mi, "draw_trials", lambda demos, a, rng, dagger_from=None: seen.append(dagger_from) or real(demos, a, rng, dagger_from))
    card = ALGOS["meta-bc"].train(args)["card"]
    assert card["dagger"]["whole_trials"] is True and card["dagger"]["shock_per_task"] is True
    assert seen == [2] * 4  # each task's 2 demonstrations, then its round's 2 trials
    for key in ("dagger_whole_trials", "dagger_shock_per_task"):
        with pytest.raises(DataError, match=key):
            ALGOS["meta-bc"].train(args.model_copy(update={"updates": 3, key: False}), resume=str(tmp_path / "bc" / "state.pt"))


def test_shock_draws_are_one_for_every_task_unless_per_task():
    """Without ``per_task`` every task of a round draws the same shocked trials and shocks (the runs
    before the option, to the bit); with it each task its own, and the same again for the same task."""
    def first(task: str, per_task: bool) -> np.ndarray:
        return mi.shock_draws(mi.dagger_seed, 3, task, per_task).random(8)

    np.testing.assert_array_equal(first("porto", False), np.random.default_rng(mi.dagger_seed(3, 10**6)).random(8))
    np.testing.assert_array_equal(first("porto", False), first("rome~hot1x2", False))
    np.testing.assert_array_equal(first("porto", True), first("porto", True))
    assert not np.allclose(first("porto", True), first("rome~hot1x2", True)) and not np.allclose(first("porto", True), first("porto", False))
    with pytest.raises(ConfigError, match="dagger_shock_per_task"):
        args_for("meta-bc", {"dagger_shock_per_task": True, "dagger_rounds": 2})
    assert args_for("meta-bc", {"dagger_shock_per_task": True, "dagger_rounds": 2, "dagger_shock_prob": 0.3}).dagger_shock_per_task


def test_stop_after_cuts_the_run_not_its_schedule(tasks, tmp_path):
    """A run stopped by ``stop_after`` took the first updates of the full schedule: resumed without
    it, it ends on the same weights as the run that was never stopped."""
    args = tiny_args(tasks, tmp_path, "whole", updates=4, eval_every=2, lr=0.01, lr_final=0.001)
    ALGOS["meta-bc"].train(args)
    cut = args.model_copy(update={"stop_after": 3, "run_dir": str(tmp_path / "cut"), "policy_out": str(tmp_path / "cut.pt")})
    assert ALGOS["meta-bc"].train(cut)["card"]["updates"] == 3
    state = torch.load(tmp_path / "cut" / "state.pt", weights_only=False)
    assert state["episode"] == 3 and state["opt"]["param_groups"][0]["lr"] == pytest.approx(mi.lr_at(args, 2))  # the 4-update decay
    ALGOS["meta-bc"].train(cut.model_copy(update={"stop_after": None}), resume=str(tmp_path / "cut" / "state.pt"))
    whole, resumed = (torch.load(tmp_path / d / "state.pt", weights_only=False)["model"] for d in ("whole", "cut"))
    for key in whole:
        torch.testing.assert_close(resumed[key], whole[key])


def test_a_demand_prior_policy_loads_with_its_prior_and_refuses_to_warm_start_another(tasks, tmp_path):
    args = tiny_args(tasks, tmp_path, stay_prior=True, demand_prior=0.25)
    ALGOS["meta-bc"].train(args)
    model, card = meta.load_meta(tmp_path / "run.pt")
    assert model.demand_prior == 0.25 and model.demand_columns == meta.demand_columns(card["lookahead"])
    with pytest.raises(DataError, match="demand_prior"):
        meta.load_meta(tmp_path / "run.pt", like=meta.make_model(args.model_copy(update={"demand_prior": 0.0})))
    with pytest.raises(ConfigError, match="stay_prior"):  # with the config, before any demonstration is collected
        args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "demand_prior": 0.25})



def test_an_end_cut_policy_trains_on_cut_demonstrations_loads_with_its_cut_and_refuses_to_warm_start_another(tasks, tmp_path):
    args = tiny_args(tasks, tmp_path, stay_prior=True, end_cut=True)
    ALGOS["meta-bc"].train(args)
    model, card = meta.load_meta(tmp_path / "run.pt")
    assert model.end_cut and card["args"]["end_cut"]
    city, lookahead = load_city(tasks[0]), card["lookahead"]
    cut, raw = mi.load_run_demos(args.demos, city, args).x, mi.load_demos(args.demos, city, lookahead).x  # (E, T, N, F)
    steps = np.arange(cut.shape[1])[:, None] + np.arange(1, lookahead + 1)  # (T, lookahead): the steps each value column reads
    past = torch.from_numpy(steps > city.horizon - 1)
    value = slice(1 + lookahead, 1 + 2 * lookahead)
    assert past.any() and (~past).any()
    assert (cut[..., value].transpose(2, 3)[:, past] == 0).all()  # what MPC-F plans without
    assert (raw[..., value].transpose(2, 3)[:, past] != 0).any()  # the file keeps what the env showed
    torch.testing.assert_close(cut[..., value].transpose(2, 3)[:, ~past], raw[..., value].transpose(2, 3)[:, ~past])
    with pytest.raises(DataError, match="end_cut"):
        meta.load_meta(tmp_path / "run.pt", like=meta.make_model(args.model_copy(update={"end_cut": False})))


def test_a_centred_policy_loads_centred_and_refuses_to_warm_start_another(tasks, tmp_path):
    args = tiny_args(tasks, tmp_path, stay_prior=True, centred_actor=True)
    ALGOS["meta-bc"].train(args)
    model, card = meta.load_meta(tmp_path / "run.pt")
    assert model.centred and card["args"]["centred_actor"]
    with pytest.raises(DataError, match="centred_actor"):
        meta.load_meta(tmp_path / "run.pt", like=meta.make_model(args.model_copy(update={"centred_actor": False})))
    with pytest.raises(ConfigError, match="stay_prior"):  # with the config, before any demonstration is collected
        args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "centred_actor": True})

@pytest.mark.parametrize(("first", "every", "rounds", "starts"), [(0, 3, 2, [0, 3]), (0, 500, 5, [0, 500, 1000, 1500, 2000]),
                                                                 (4, 3, 3, [4, 7, 10]), (5, 10, 1, [5])])
def test_dagger_rounds_start_at_the_offset_and_a_resume_reads_back_the_ones_begun(first, every, rounds, starts):
    args = mi.Args(dagger_rounds=rounds, dagger_every=every, dagger_first=first)
    steps = range(2 * max(starts) + 2)
    assert [s for s in steps if mi.round_due(args, s)] == starts
    assert [mi.round_due(args, s) for s in starts] == list(range(1, rounds + 1))
    for s in steps:  # a run resumed at update s reads back exactly the rounds collected before s
        assert mi.started_rounds(args, s) == sum(1 for r in range(s) if mi.round_due(args, r))


@pytest.mark.parametrize(("first", "updates", "refused"), [(599, 600, False), (600, 600, True), (900, 600, True)])
def test_a_dagger_schedule_whose_first_round_never_comes_is_refused(first, updates, refused):
    values = {"dagger_rounds": 2, "dagger_first": first, "updates": updates}
    if refused:
        with pytest.raises(ConfigError, match="no DAgger round"):
            args_for("meta-bc", values)
    else:
        assert args_for("meta-bc", values).dagger_first == first
    assert args_for("meta-bc", {**values, "dagger_rounds": 0}).dagger_rounds == 0  # no rounds asked: nothing to refuse


def test_the_cities_batch_form_is_chosen_by_one_reading_and_the_shipped_recipes_keep_theirs():
    """Padding is the default and packing opt-in; ``pad_cities: false`` (one city after another) is refused beside packing instead of
    ignored; and the meta-bc configs in ``configs/meta`` keep the batching they trained with (the root
    ``bc.yaml`` pins it), so the shipped members retrain to the bit: only a config that asks for packing packs."""
    import glob

    from marl_amod.config import load_config
    from marl_amod.data import read_yaml

    assert args_for("meta-bc", {}).cities_batch == "padded" and args_for("meta-bc", {"pad_cities": False}).cities_batch == "apart"
    assert args_for("meta-bc", {"pack_cities": True}).cities_batch == "packed"
    with pytest.raises(ConfigError, match="pad_cities: true to pack, or pack_cities: false"):
        args_for("meta-bc", {"pad_cities": False, "pack_cities": True})
    algos = {k: v.args for k, v in ALGOS.items()}
    recipes = {f: args for f in sorted(glob.glob("configs/meta/*.yaml")) for algo, args in [load_config(f, algos)] if algo == "meta-bc"}
    asked = {f for f in recipes if "pack_cities" in (read_yaml(f).get("args") or {})}
    assert len(recipes) > 50 and {f for f, args in recipes.items() if args.pack_cities} == asked - {"configs/meta/bc.yaml"}
    assert not recipes["configs/meta/bc_dagger_l1_whole_rep4.yaml"].pack_cities and not recipes["configs/meta/bc_dagger_l1_whole_rep5.yaml"].pack_cities


def test_hotspot_share_sets_how_often_variants_are_drawn():
    """``hotspot_share`` gives the variants that share of the draws (uniform within cities and
    within variants); without it every task is drawn as often, with the draws of the runs before
    the option (the same generator calls); a share without variants is refused."""
    names, draws = ["a", "b", "a~hot0x2", "a~hot1x3", "b~hot0x2", "b~hot1x3"], 6000
    rng = np.random.default_rng(0)
    got = [mi.draw_task(names, 2, 0.25, rng) for _ in range(draws)]
    counts = {n: got.count(n) / draws for n in names}
    assert abs(sum(counts[n] for n in names[2:]) - 0.25) < 0.02
    assert all(abs(counts[n] - 0.375) < 0.03 for n in names[:2]) and all(abs(counts[n] - 0.0625) < 0.015 for n in names[2:])
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    assert [mi.draw_task(names, 2, None, a) for _ in range(50)] == [names[int(b.integers(len(names)))] for _ in range(50)]
    with pytest.raises(ConfigError, match="no variants"):
        args_for("meta-bc", {"hotspot_share": 0.4})
    assert args_for("meta-bc", {"hotspot_share": 0.4, "hotspot_variants": 2}).hotspot_share == 0.4
    # a city named twice is one task (the draws are over distinct tasks), and the share's split of
    # the tasks into cities and variants would count it twice: a variant drawn as a city
    with pytest.raises(ConfigError, match="twice"):
        args_for("meta-bc", {"cities": ["porto", "rome", "porto"], "hotspot_share": 0.4, "hotspot_variants": 1})


def test_hotspot_variants_are_tasks_with_demonstrations_and_dagger_rounds_of_their_own(tasks, tmp_path, monkeypatch):
    """One variant per city: its own MPC-F demonstrations (``hotspot_episodes``), drawn like a city,
    driven in the DAgger rounds (here the first at update 1, not before the first update), named on
    the card and counted by the transfer table."""
    args = tiny_args(tasks, tmp_path, "bc", updates=2, eval_every=2, eval_episodes=2, dagger_rounds=1, dagger_first=1,
                     dagger_episodes=2, hotspot_variants=1, hotspot_episodes=4, hotspot_share=0.5)
    plain, variants = mi.tasks(args)
    assert plain == tasks and [meta.base_city(v) for v in variants] == tasks and all(meta.HOTSPOT in v for v in variants)
    shares, draw = [], mi.draw_task
    monkeypatch.setattr(mi, "draw_task", lambda names, plain, share, rng: shares.append((len(names) - plain, share)) or draw(names, plain, share, rng))
    card = ALGOS["meta-bc"].train(args.model_copy(update={"updates": 1}))["card"]  # stopped before its round, then resumed
    assert shares == [(len(variants), 0.5)] * args.cities_per_update  # the update drew with the run's share and its variants
    assert card["demonstrations"]["hotspot_variants"] == variants and card["dagger"]["rounds"] == 0
    assert card["demonstrations"]["variants_share_of_draws"] == 0.5
    assert not (tmp_path / "bc" / "dagger").exists()  # round 1 waits for update 1
    for name in variants:
        city = meta.task_city(name)
        demos = mi.load_demos(tmp_path / "demos", city, 6)
        assert demos.episodes == 4 and city.name.startswith(("small~hot", "large~hot"))
    for share in (0.25, None):  # its first update drew half its tasks from the variants: the card would name another share
        with pytest.raises(DataError, match="hotspot_share"):
            ALGOS["meta-bc"].train(args.model_copy(update={"hotspot_share": share}), resume=str(tmp_path / "bc" / "state.pt"))
    card = ALGOS["meta-bc"].train(args, resume=str(tmp_path / "bc" / "state.pt"))["card"]
    assert card["dagger"]["rounds"] == 1
    assert sorted(p.stem for p in (tmp_path / "bc" / "dagger" / "round1").glob("*.npz")) == sorted(meta.task_city(n).name for n in [*tasks, *variants])
    from marl_amod.transfer import run_strategy

    rec = run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "bc.pt"), adapt_episodes=0)
    assert rec["transfer"]["demonstrations"] == 2 * 2 + 2 * 4 and rec["transfer"]["dagger_episodes"] == 1 * 2 * 4
    assert rec["transfer"]["source_city"] == "2 training cities + 2 hotspot variants"
    with pytest.raises(DataError, match="held-out"):
        mi.collect_demos(tmp_path / "demos", ["nyc_brooklyn~hot5x2"], episodes=1, seed=0, lookahead=6)


def test_event_tasks_are_drawn_in_their_share_and_refused_without_one():
    """``event_share`` of the draws go to the event tasks (uniform among them), the rest as
    :func:`draw_task` draws them; without event tasks the draws are draw_task's own (the runs
    before the option); event tasks without a share, or a share without them, are refused."""
    names, draws = ["a", "b", "a~hot0x2", "b~hot0x2", "a~ev1+2x4@0-6", "b~ev2+3x5@1-7"], 8000
    args = args_for("meta-bc", {"hotspot_variants": 1, "hotspot_share": 0.4, "event_tasks": 1, "event_share": 0.25})
    rng = np.random.default_rng(0)
    got = [mi.draw_run_task(args, names, 2, names[4:], rng) for _ in range(draws)]
    counts = {n: got.count(n) / draws for n in names}
    assert all(abs(counts[n] - 0.125) < 0.015 for n in names[4:])
    assert all(abs(counts[n] - 0.75 * 0.3) < 0.025 for n in names[:2]) and all(abs(counts[n] - 0.75 * 0.2) < 0.02 for n in names[2:4])
    plain = args.model_copy(update={"event_tasks": 0, "event_share": None})
    a, b = np.random.default_rng(1), np.random.default_rng(1)
    assert [mi.draw_run_task(plain, names[:4], 2, [], a) for _ in range(50)] == [mi.draw_task(names[:4], 2, 0.4, b) for _ in range(50)]
    for values in ({"event_tasks": 1}, {"event_share": 0.2}):
        with pytest.raises(ConfigError, match="event_share"):
            args_for("meta-bc", values)


def test_a_bad_event_setting_fails_before_any_demonstration_is_collected(tasks, tmp_path, monkeypatch):
    """The event tasks are named (and their settings checked), and every task and validation city
    built, before the cities' demonstrations are collected, as the hotspot variants are: not after
    minutes of collection."""
    collected: list[list[str]] = []
    monkeypatch.setattr(mi, "collect_demos", lambda folder, names, *a, **k: collected.append(list(names)) or {})
    args = mi.Args(scenario="synthetic", cities=tasks, val_cities=tasks[:1], demos=str(tmp_path / "demos"), event_tasks=1,
                   event_share=0.5, event_multipliers=(1.0, 2.0), run_dir=str(tmp_path / "bc"))  # fmt: skip
    with pytest.raises(ConfigError, match="event_multipliers"):
        mi.train(args)
    with pytest.raises(ConfigError, match="no_such_city"):  # a validation city's name too
        mi.train(args.model_copy(update={"event_tasks": 0, "event_share": None, "val_cities": ["no_such_city"]}))
    assert collected == []


def test_event_tasks_are_demonstrated_and_labelled_by_mpc_told_the_event(tasks, tmp_path, monkeypatch):
    """One event task per city: its own demonstrations (``event_episodes``) and DAgger episodes,
    every one labelled by MPC told the event (and the cities' by MPC-Forecast), named on the card,
    counted by the transfer table; a resume with another share is refused."""
    args = tiny_args(tasks, tmp_path, "bc", updates=2, eval_every=2, eval_episodes=2, dagger_rounds=1, dagger_first=1,
                     dagger_episodes=2, event_tasks=1, event_episodes=4, event_share=0.5)
    events = mi.event_names(args)
    assert [meta.base_city(e) for e in events] == tasks and all(meta.EVENT in e for e in events)
    experts, expert_for = [], mi.expert_for
    monkeypatch.setattr(mi, "expert_for", lambda city: experts.append((city.name, type(e := expert_for(city)))) or e)
    card = ALGOS["meta-bc"].train(args.model_copy(update={"updates": 1}))["card"]
    told = {name for name, kind in experts if kind is mi.MPCToldTheShock}
    assert told == {meta.task_city(e).name for e in events} and all(kind is MPCForecast for name, kind in experts if name not in told)
    assert card["demonstrations"]["event_tasks"] == events and card["demonstrations"]["event_share_of_draws"] == 0.5
    for name in events:
        city = meta.task_city(name)
        assert mi.load_demos(tmp_path / "demos", city, 6).episodes == 4 and city.meta["events"]
    with pytest.raises(DataError, match="event_share"):
        ALGOS["meta-bc"].train(args.model_copy(update={"event_share": 0.25}), resume=str(tmp_path / "bc" / "state.pt"))
    experts.clear()
    card = ALGOS["meta-bc"].train(args, resume=str(tmp_path / "bc" / "state.pt"))["card"]
    assert card["dagger"]["rounds"] == 1 and {name for name, kind in experts if kind is mi.MPCToldTheShock} == told
    from marl_amod.transfer import run_strategy

    rec = run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "bc.pt"), adapt_episodes=0)
    assert rec["transfer"]["demonstrations"] == 2 * 2 + 2 * 4 and rec["transfer"]["dagger_episodes"] == 1 * 2 * 4
    assert rec["transfer"]["source_city"].endswith(" + 2 event tasks")
    with pytest.raises(DataError, match="held-out"):
        mi.collect_demos(tmp_path / "demos", ["nyc_brooklyn~ev8+10x6@6-14"], episodes=1, seed=0, lookahead=6)


def test_without_event_tasks_a_runs_draws_are_draw_tasks_own(tasks, tmp_path, monkeypatch):
    """The shipped configs (no event tasks) rerun with the draws they had: inside train every draw
    is draw_task's over the cities and variants, from the same generator state, leaving it where
    draw_task leaves it, and every demonstration is labelled by MPC-Forecast."""
    args = tiny_args(tasks, tmp_path, "bc", updates=3, eval_every=3, eval_episodes=2, hotspot_variants=1, hotspot_episodes=2,
                     hotspot_share=0.4)
    draws, real, experts, expert_for = [], mi.draw_run_task, [], mi.expert_for

    def spy(a: mi.Args, names: list[str], plain: int, events: list[str], rng: np.random.Generator) -> str:
        twin = np.random.default_rng()
        twin.bit_generator.state = rng.bit_generator.state
        got = real(a, names, plain, events, rng)
        draws.append((events, names, got == mi.draw_task(names, plain, 0.4, twin), rng.bit_generator.state == twin.bit_generator.state))
        return got

    monkeypatch.setattr(mi, "draw_run_task", spy)
    monkeypatch.setattr(mi, "expert_for", lambda city: experts.append(type(e := expert_for(city))) or e)
    ALGOS["meta-bc"].train(args)
    plain, variants = mi.tasks(args)
    assert len(draws) == 3 * 2 and all(ev == [] and names == [*plain, *variants] and same and state for ev, names, same, state in draws)
    assert experts and set(experts) == {MPCForecast}


@pytest.mark.parametrize("labels", ["told", "forecast"])
def test_shocked_dagger_trials_are_labelled_by_the_chosen_expert(tasks, labels):
    """A shocked trial draws the shocked demand, its features keep the usual forecast, and its
    labels are MPC's plan on the shocked expected demand (``told``), which MPC-Forecast's plan is
    not, or MPC-Forecast's (``forecast``), which is not that."""
    city = load_city(tasks[1])
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    got = mi.collect_city(city, episodes=1, seed=2, lookahead=6, learner=model, seed_of=mi.dagger_seed, shock_prob=1.0, shock_labels=labels)
    shocks = np.random.default_rng(mi.dagger_seed(2, 10**6))
    shocks.random()
    shocked = meta.random_shock(city, shocks)  # the trial's shock, drawn as the collection drew it
    from marl_amod.system import FleetSystem

    system, told, usual = FleetSystem(shocked), mi.MPCToldTheShock(), MPCForecast()
    system.reset(mi.dagger_seed(2, 0))
    told.reset(system, np.random.default_rng(0)), usual.reset(system, np.random.default_rng(0))
    differ = 0
    for x, share, played in zip(got["x"][0], got["share"][0], got["action"][0], strict=True):
        np.testing.assert_allclose(x, meta.task_features(system, meta.CityScale.of(city), 6), rtol=1e-5)
        want = np.where((w := told.target(system)) < 0, system.sim.idle, w)
        plain = np.where((w := usual.target(system)) < 0, system.sim.idle, w)
        label, other = (want, plain) if labels == "told" else (plain, want)
        np.testing.assert_allclose(share, label / label.sum(), rtol=1e-5)
        differ += int(np.abs(other - label).sum() > 0)
        system.step(system.targets_from_weights(played.astype(np.float64)))
    assert differ > 0


def _structured_demos(tasks: list[str], tmp_path) -> tuple[list, list[mi.CityDemos]]:
    """(cities, their demonstrations with the structure and place columns): 3 MPC-F episodes a task."""
    mi.collect_demos(tmp_path / "d", tasks, episodes=3, seed=0, lookahead=6)
    cities = [load_city(t) for t in tasks]
    return cities, [mi.load_demos(tmp_path / "d", c, 6, structure=True, place=True) for c in cities]


@pytest.mark.parametrize(
    ("readout", "fit"),
    [("none", mi.Fit()), ("mean-max", mi.Fit()), ("mean-max", mi.Fit(own_prev_action=True)), ("mean-max", mi.Fit(imitation="l1", shortfall=2.0)),
     ("mean-max", mi.Fit(imitation="l1", end_weight=3.0))],
)
@pytest.mark.parametrize("batch", ["padded", "packed"])
def test_padded_cities_losses_equal_the_per_city_losses_and_gradients(tasks, tmp_path, readout, fit, batch):
    """One update's cities of different sizes (6 and 9 regions; one drawn twice, one with a shorter
    trial) in one padded batch, or side by side (``packed``), give the mean of the per-city losses and
    the same gradients: the padding reaches no message, pool, stay prior, value or cross-entropy, and
    nor does one packed city reach another."""
    cities, demos = _structured_demos(tasks, tmp_path)
    graphs = [meta.city_graph(c) for c in cities]
    short = mi.CityDemos(*(v[:, :4] for v in vars(demos[1]).values()))  # a city with 4 decisions per episode
    rng = np.random.default_rng(0)
    draws = [(d, rng.integers(3, size=(2, 4)), g) for d, g in [(demos[0], graphs[0]), (demos[1], graphs[1]), (demos[0], graphs[0]), (short, graphs[1])]]
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6, structure=True, place=True), hidden=8, stay_prior=True, readout=readout)

    def loss_and_grads(ce, vl):
        return [ce, vl, *torch.autograd.grad(ce + 0.5 * vl, list(model.parameters()))]

    one_by_one = [mi.imitation_losses(model, d, e, g, gamma=0.97, fit=fit) for d, e, g in draws]
    want = loss_and_grads(torch.stack([c for c, _ in one_by_one]).mean(), torch.stack([v for _, v in one_by_one]).mean())
    got = loss_and_grads(*mi.cities_losses(model, draws, gamma=0.97, batch=batch, fit=fit))
    assert demos[0].x.shape[2] != demos[1].x.shape[2] and want[0] > 0 and want[1] > 0
    for a, b in zip(got, want, strict=True):
        torch.testing.assert_close(a, b, atol=1e-6, rtol=1e-4)
    with pytest.raises(ValueError, match="same"):
        mi.Trials.padded([mi.Trials.of_city(demos[0], draws[0][1]), mi.Trials.of_city(short, draws[3][1])])


@pytest.mark.parametrize("batch", ["padded", "packed"])
def test_bf16_autocast_keeps_the_memory_and_what_the_losses_read_in_float32(tasks, tmp_path, batch):
    """``precision: bf16`` runs the teacher-forced pass under bf16 autocast: only the products are bf16.
    The memory carried across the trial's steps, the Dirichlet means and the values come out float32,
    and the losses and gradients stay those of float32 to bf16's rounding (a policy trained so plays
    as one trained in float32), the cities padded or side by side; a short run trains and saves float32 weights."""
    cities, demos = _structured_demos(tasks, tmp_path)
    rng = np.random.default_rng(0)
    draws = [(d, rng.integers(3, size=(2, 4)), meta.city_graph(c)) for d, c in zip(demos, cities, strict=True)]
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6, structure=True, place=True), hidden=16, stay_prior=True, readout="mean-max")
    fit = mi.Fit(imitation="l1", shortfall=2.0)

    def loss_and_grads(bf16: bool) -> list[torch.Tensor]:
        with C.autocast("bf16" if bf16 else "fp32")():
            ce, vl = mi.cities_losses(model, draws, gamma=0.97, batch=batch, fit=fit)
            means, values = mi.teacher_forced(model, mi.Trials.of_city(demos[0], draws[0][1]), draws[0][2])
        assert ce.dtype == vl.dtype == means.dtype == values.dtype == torch.float32
        return [ce, vl, torch.cat([g.flatten() for g in torch.autograd.grad(ce + 0.5 * vl, list(model.parameters()))])]

    ce, vl, grad = loss_and_grads(False)
    ce16, vl16, grad16 = loss_and_grads(True)
    torch.testing.assert_close(ce16, ce, rtol=1e-2, atol=0)
    torch.testing.assert_close(vl16, vl, rtol=2e-2, atol=0)
    assert F.cosine_similarity(grad16, grad, dim=0) > 0.99 and not torch.equal(grad16, grad)  # bf16 did run, and near float32
    out = ALGOS["meta-bc"].train(tiny_args(tasks, tmp_path, "bf", precision="bf16", pack_cities=batch == "packed"))
    assert out["card"]["updates"] > 0
    assert all(v.dtype == torch.float32 for v in torch.load(out["policy"], weights_only=False)["state_dict"].values())


def test_under_autocast_the_memory_is_cast_once_for_every_product_after_the_gru(tasks, tmp_path, monkeypatch):
    """The layers after the GRU read one bf16 copy of the memory (:func:`recurrent._for_products`) instead
    of each product casting the float32 memory: the products see the same values, so the losses are bit
    for bit those of casting per reader, and only the gradients' sums at the memory round differently.
    Outside autocast they read the float32 memory itself."""
    cities, demos = _structured_demos(tasks, tmp_path)
    rng = np.random.default_rng(1)
    draws = [(d, rng.integers(3, size=(2, 4)), meta.city_graph(c)) for d, c in zip(demos, cities, strict=True)]
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6, structure=True, place=True), hidden=16, stay_prior=True, readout="mean-max")

    def losses_and_grad() -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        with C.autocast("bf16")():
            ce, vl = mi.cities_losses(model, draws, gamma=0.97)
        return ce, vl, torch.cat([g.flatten() for g in torch.autograd.grad(ce + 0.5 * vl, list(model.parameters()))])

    once = losses_and_grad()
    memory = torch.rand(3, 4)
    with C.autocast("bf16")():
        assert recurrent._for_products(memory).dtype == torch.bfloat16
    assert recurrent._for_products(memory) is memory
    monkeypatch.setattr(recurrent, "_for_products", lambda m: m)
    per_reader = losses_and_grad()
    assert torch.equal(once[0], per_reader[0]) and torch.equal(once[1], per_reader[1])
    assert F.cosine_similarity(once[2], per_reader[2], dim=0) > 0.999


def test_a_resume_refuses_a_config_that_names_other_tasks(tasks, tmp_path):
    """The state's updates and DAgger rounds are of its tasks: resumed with other hotspot variants
    (or cities, or event tasks), the run would train on tasks it was not started on and collect the missing tasks'
    earlier DAgger rounds with a later model."""
    args = tiny_args(tasks, tmp_path, "bc", eval_every=2, eval_episodes=2, hotspot_variants=1, hotspot_episodes=2)
    ALGOS["meta-bc"].train(args)
    state = str(tmp_path / "bc" / "state.pt")
    with pytest.raises(DataError, match="hotspot_variants: 1 -> 0"):  # the state's own args name what changed
        ALGOS["meta-bc"].train(args.model_copy(update={"updates": 2, "hotspot_variants": 0}), resume=state)
    events = {"updates": 2, "event_tasks": 1, "event_episodes": 1, "event_share": 0.5}
    with pytest.raises(DataError, match="event_tasks: 0 -> 1"):
        ALGOS["meta-bc"].train(args.model_copy(update=events), resume=state)
    older = tmp_path / "older.pt"  # a state saved before states held their args: the tasks it names still refuse
    saved = torch.load(state, weights_only=False)
    del saved["args"]
    torch.save(saved, older)
    with pytest.raises(DataError, match=r"event settings \(event_tasks, event_multipliers\)"):  # the message names what made them
        ALGOS["meta-bc"].train(args.model_copy(update=events), resume=str(older))
    assert ALGOS["meta-bc"].train(args.model_copy(update={"updates": 2}), resume=state)["card"]["updates"] == 2


def test_skew_and_sink_variants_are_tasks_with_demonstrations_of_their_own_and_a_resume_keeps_their_settings(tasks, tmp_path):
    """One skew then one sink variant per city after the hotspot ones: their own MPC-F
    demonstrations (``skew_episodes``, ``sink_episodes``), drawn with the hotspot variants under
    ``hotspot_share`` (which skew or sink variants alone also allow), named on the card and counted
    by the transfer table; a resume with other skew or sink settings is refused (its updates were
    of other tasks)."""
    assert args_for("meta-bc", {"hotspot_share": 0.4, "skew_variants": 1}).hotspot_share == 0.4
    assert args_for("meta-bc", {"hotspot_share": 0.4, "sink_variants": 1}).hotspot_share == 0.4
    args = tiny_args(tasks, tmp_path, "bc", eval_every=2, eval_episodes=2, hotspot_variants=1, hotspot_episodes=2,
                     skew_variants=1, skew_gammas=(1.5, 2.5), skew_episodes=3, sink_variants=1, sink_multipliers=(2.0, 4.0),
                     sink_episodes=4, hotspot_share=0.5)
    plain, variants = mi.tasks(args)
    assert variants == mi.hotspot_names(args) + mi.skew_names(args) + mi.sink_names(args) and len(variants) == 3 * len(tasks)
    skewed, sinks = mi.skew_names(args), mi.sink_names(args)
    assert [meta.base_city(v) for v in sinks] == tasks and all(2.0 <= meta.task_city(v).meta["sink"]["multiplier"] <= 4.0 for v in sinks)
    assert [meta.base_city(v) for v in skewed] == tasks and all(1.5 <= meta.task_city(v).meta["skew"]["gamma"] <= 2.5 for v in skewed)
    card = ALGOS["meta-bc"].train(args)["card"]
    assert card["demonstrations"]["skew_variants"] == skewed and card["demonstrations"]["episodes_per_skew_variant"] == 3
    assert card["demonstrations"]["skew_gammas"] == [1.5, 2.5] and card["demonstrations"]["variants_share_of_draws"] == 0.5
    assert all(mi.load_demos(tmp_path / "demos", meta.task_city(v), 6).episodes == 3 for v in skewed)
    assert card["demonstrations"]["sink_variants"] == sinks and card["demonstrations"]["episodes_per_sink_variant"] == 4
    assert card["demonstrations"]["sink_multipliers"] == [2.0, 4.0]
    assert all(mi.load_demos(tmp_path / "demos", meta.task_city(v), 6).episodes == 4 for v in sinks)
    state = str(tmp_path / "bc" / "state.pt")
    for change, named in (({"skew_variants": 0}, "skew"), ({"skew_gammas": (2.6, 3.0)}, "skew"), ({"sink_variants": 0}, "sink"),
                          ({"sink_multipliers": (5.0, 6.0)}, "sink")):  # fmt: skip
        with pytest.raises(DataError, match=named):
            ALGOS["meta-bc"].train(args.model_copy(update={"updates": 2, **change}), resume=state)
    from marl_amod.transfer import run_strategy

    rec = run_strategy("meta-rl", "synthetic", episodes=1, meta_policy=str(tmp_path / "bc.pt"), adapt_episodes=0)
    assert rec["transfer"]["demonstrations"] == 2 * 2 + 2 * 2 + 2 * 3 + 2 * 4
    assert rec["transfer"]["source_city"] == "2 training cities + 2 hotspot variants + 2 skew variants + 2 sink variants"


@needs_data
def test_sink_tasks_are_a_function_of_the_seed_distinct_and_on_destinations_with_arrivals():
    names = meta.sink_tasks(["synthetic", "porto"], 2, (4.0, 8.0), seed=0)
    assert names == meta.sink_tasks(["synthetic", "porto"], 2, (4.0, 8.0), seed=0) != meta.sink_tasks(["synthetic", "porto"], 2, (4.0, 8.0), seed=1)
    assert len(set(names)) == 4 and [meta.base_city(n) for n in names] == ["synthetic"] * 2 + ["porto"] * 2
    for name in names:
        city, base = meta.task_city(name), load_city(meta.base_city(name))
        region, m = city.meta["sink"]["region"], city.meta["sink"]["multiplier"]
        assert 4.0 <= m <= 8.0 and base.forecast_rate[: base.horizon, :, region].sum() > 0
    assert meta.sink_tasks(["porto"], 0, (3.0, 1.0), seed=0) == []  # no variants: the range is not read
    with pytest.raises(ConfigError, match="sink_multipliers"):
        meta.sink_tasks(["synthetic"], 1, (3.0, 1.0), seed=0)


def test_skew_tasks_are_a_function_of_the_seed_distinct_and_never_the_city_itself():
    names = meta.skew_tasks(["synthetic", "porto"], 2, (1.3, 2.5), seed=0)
    assert names == meta.skew_tasks(["synthetic", "porto"], 2, (1.3, 2.5), seed=0) != meta.skew_tasks(["synthetic", "porto"], 2, (1.3, 2.5), seed=1)
    assert len(set(names)) == 4 and [meta.base_city(n) for n in names] == ["synthetic"] * 2 + ["porto"] * 2
    assert meta.skew_tasks(["synthetic"], 1, (0.9, 1.1), seed=0)[0] in ("synthetic~skew0.9", "synthetic~skew1.1")  # 1 is drawn again
    assert meta.skew_tasks(["porto"], 0, (3.0, 1.0), seed=0) == []  # no variants: the range is not read
    with pytest.raises(ConfigError, match="distinct skew"):
        meta.skew_tasks(["synthetic"], 2, (1.0, 1.0), seed=0)
    for bad in ((0.0, 2.0), (3.0, 2.0), (1.2, float("inf"))):
        with pytest.raises(ConfigError, match="skew_gammas"):
            meta.skew_tasks(["synthetic"], 1, bad, seed=0)


def test_own_prev_action_feeds_the_memory_the_models_own_moves_not_the_played_ones(tasks, tmp_path):
    """With ``own_prev_action`` what was played does not reach the output (no copycat channel), and the
    means are those of a trial whose played moves were the model's own means, as deployed
    deterministically; without it the played moves do reach it."""
    mi.collect_demos(tmp_path / "d", tasks[1:], episodes=2, seed=0, lookahead=6)
    city = load_city(tasks[1])
    demos, graph = mi.load_demos(tmp_path / "d", city, 6), meta.city_graph(city)
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    trials = mi.Trials.of_city(demos, np.array([[0], [1]]))  # one trial of two episodes
    shuffled = replace(trials, action=trials.action.flip(-1))
    with torch.no_grad():
        own = mi.teacher_forced(model, trials, graph, own_prev_action=True)[0]
        torch.testing.assert_close(mi.teacher_forced(model, shuffled, graph, own_prev_action=True)[0], own)
        assert not torch.allclose(mi.teacher_forced(model, shuffled, graph)[0], mi.teacher_forced(model, trials, graph)[0])
        as_played = replace(trials, action=own.reshape(trials.action.shape))
        torch.testing.assert_close(mi.teacher_forced(model, as_played, graph)[0], own)
    args = args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "own_prev_action": True})
    assert args.own_prev_action


def test_receiving_marks_the_regions_mpc_moves_vehicles_into(tasks, tmp_path):
    """On MPC-F's demonstrations the receivers are the regions whose target exceeds their idle vehicles
    (read back from the features' per-city units), and only those: the regions the l1 loss prices a
    vehicle short at 1 + shortfall_weight times."""
    mi.collect_demos(tmp_path / "d", tasks[1:], episodes=2, seed=0, lookahead=6)
    city = load_city(tasks[1])
    demos = mi.load_demos(tmp_path / "d", city, 6)
    idle = demos.x[..., 0] * meta.CityScale.of(city).vehicles  # vehicles
    target = demos.share * idle.sum(-1, keepdim=True)  # MPC-F keeps the idle fleet, so its targets in vehicles
    want = target > idle + 0.5
    got = mi.receiving(demos.x[..., 0], demos.share)
    assert want.any() and (~want).any()
    assert torch.equal(got, want)


def test_l1_shortfall_prices_a_receivers_missing_vehicles_higher(tasks):
    """The meta-policy's l1 loss with a shortfall weight: the same miss costs more where MPC-F sends
    vehicles than where it takes them from, and a shortfall weight needs the l1 loss."""
    idle, share = torch.tensor([[2.0, 2.0]]), torch.tensor([[0.75, 0.25]])  # region 0 receives
    receives = mi.receiving(idle, share)
    assert receives.tolist() == [[True, False]]
    short_at_receiver = O.shares_loss(torch.tensor([[0.65, 0.35]]), share, "l1", receives, 2.0)
    short_at_sender = O.shares_loss(torch.tensor([[0.85, 0.15]]), share, "l1", receives, 2.0)
    torch.testing.assert_close(short_at_receiver, torch.tensor([0.4]))  # 0.1 short x 3 + 0.1 over
    torch.testing.assert_close(short_at_sender, torch.tensor([0.2]))
    with pytest.raises(ConfigError, match="shortfall_weight"):
        args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "shortfall_weight": 2.0})
    assert args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "imitation": "l1", "shortfall_weight": 2.0}).fit == mi.Fit(
        imitation="l1", shortfall=2.0
    )


def test_end_weight_counts_an_episodes_last_decisions_more(tasks, tmp_path):
    """With ``end_weight`` the actor's loss is the per-decision loss weighted by step: each
    episode's last ``end_steps`` decisions 1 + end_weight times the others, the weights' mean 1 (so
    end_weight 0 is the plain mean); the critic's loss is untouched."""
    torch.testing.assert_close(mi.step_weights(2, 5, 2, 3.0), torch.tensor([1.0, 1, 1, 4, 4] * 2) / 2.2)
    assert torch.equal(mi.step_weights(1, 4, 3, 0.0), torch.ones(4))
    mi.collect_demos(tmp_path / "d", tasks[1:], episodes=3, seed=0, lookahead=6)
    city = load_city(tasks[1])
    demos, graph = mi.load_demos(tmp_path / "d", city, 6), meta.city_graph(city)
    episodes = np.random.default_rng(0).integers(3, size=(2, 4))
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8, stay_prior=True)
    trials = mi.Trials.of_city(demos, episodes)
    k, t = trials.x.shape[:2]
    per_decision = O.shares_loss(mi.teacher_forced(model, trials, graph)[0], trials.share.flatten(0, 1), "l1")  # (K T, B)
    end = torch.zeros(k, t, dtype=torch.bool)
    end[:, -3:] = True
    end = end.flatten()
    want = (per_decision[~end].sum() + 4 * per_decision[end].sum()) / (per_decision[~end].numel() + 4 * per_decision[end].numel())
    plain_actor, plain_critic = mi.trial_losses(model, trials, graph, 0.97, mi.Fit(imitation="l1"))
    actor, critic = mi.trial_losses(model, trials, graph, 0.97, mi.Fit(imitation="l1", end_weight=3.0, end_steps=3))
    torch.testing.assert_close(actor, want)
    torch.testing.assert_close(plain_actor, per_decision.mean())
    torch.testing.assert_close(critic, plain_critic)
    assert not torch.isclose(actor, plain_actor)
    assert args_for("meta-bc", {"scenario": "synthetic", "cities": tasks, "imitation": "l1", "end_weight": 3.0}).fit == mi.Fit(
        imitation="l1", end_weight=3.0, end_steps=3
    )


def test_a_run_whose_validations_stopped_moving_stops_says_so_and_keeps_the_best(tasks, tmp_path, monkeypatch):
    """Seed 7 of the tables' recipe validated 0.43814 for 2,400 updates and finished in silence.
    Validations that stay within STALL_TOL for ``stall_validations`` rounds now stop the run with a
    warning and ``stalled_at`` on the card; ones that move (as converged runs do, ~1e-3) never do."""
    assert not meta.stalled([0.5190, 0.5196, 0.5188, 0.5193, 0.5195], 5)  # a converged run's last validations
    assert meta.stalled([0.43817, 0.43814, 0.43814, 0.43814, 0.43814], 5)  # seed 7's
    assert not meta.stalled([0.43814] * 4, 5) and not meta.stalled([0.43814] * 9, 0)
    flat = iter([0.40, 0.41, 0.43814, 0.43814, 0.43815, 0.43814, 0.9])
    monkeypatch.setattr(meta, "validate", lambda *a, **k: next(flat))
    args = tiny_args(tasks, tmp_path, updates=7, stay_prior=True, stall_validations=4)
    with pytest.warns(RuntimeWarning, match="no longer moves"):
        out = ALGOS["meta-bc"].train(args)
    assert out["card"]["stalled_at"] == 6 and out["card"]["updates"] == 6


@pytest.mark.parametrize("adaptation", ["sampled", "mean"])
def test_the_dagger_trials_adaptation_episodes_are_played_as_the_policy_adapts(tasks, adaptation):
    """``adaptation``: the DAgger trials' first episodes play the Dirichlet mean (the same actions
    whatever torch's stream, and so the same trial to its end) or sample from it (other actions
    with another stream)."""
    city = load_city(tasks[0])
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(2), hidden=8, stay_prior=True)
    played = []
    for stream in (1, 2):
        torch.manual_seed(stream)
        played.append(mi.collect_city(city, 2, 0, 2, learner=model, trial_episodes=2, adaptation=adaptation)["action"])
    first, last = (np.array_equal(played[0][k], played[1][k]) for k in (0, 1))
    assert (first and last) if adaptation == "mean" else not first


def test_dagger_concentration_sets_how_widely_the_trials_adaptation_episodes_sample(tasks):
    """``concentration``: the adaptation episodes sample around the policy's mean at c x N whatever
    ``adaptation`` says (here the mean, which alone would not sample). The first decision's state is
    the same in every run (same demand seed), so its action
    lies near the mean's at a high concentration and far from it at a low one."""
    city = load_city(tasks[1])
    torch.manual_seed(0)
    model = RecurrentGNN(meta.n_task_features(2), hidden=8, stay_prior=True)
    mean = mi.collect_city(city, 2, 0, 2, learner=model, trial_episodes=2, adaptation="mean")["action"]
    off = {}
    for c in (0.5, 1e5):
        torch.manual_seed(1)
        played = mi.collect_city(city, 2, 0, 2, learner=model, trial_episodes=2, adaptation="mean", concentration=c)["action"]
        off[c] = 0.5 * np.abs(played[0, 0] - mean[0, 0]).sum()
        torch.manual_seed(2)
        again = mi.collect_city(city, 2, 0, 2, learner=model, trial_episodes=2, adaptation="mean", concentration=c)["action"]
        assert not np.array_equal(played[0], again[0])  # sampled: another stream, other actions
    assert off[1e5] < 0.01 < 0.1 < off[0.5]
    with pytest.raises(ValueError, match="dagger_rounds"):
        mi.Args(dagger_concentration=1.0)


def test_a_policys_card_says_how_it_adapts_and_validation_adapts_so(tasks, tmp_path, monkeypatch):
    args = tiny_args(tasks, tmp_path, stay_prior=True, adaptation="mean")
    ALGOS["meta-bc"].train(args)
    model, card = meta.load_meta(tmp_path / "run.pt")
    assert card["args"]["adaptation"] == "mean"
    city = load_city(tasks[0])
    torch.manual_seed(1)
    by_card = meta.load_policy(tmp_path / "run.pt", city, 1).adapted
    torch.manual_seed(2)
    torch.testing.assert_close(by_card, meta.load_policy(tmp_path / "run.pt", city, 1, adaptation="mean").adapted)
    assert not torch.allclose(by_card, meta.load_policy(tmp_path / "run.pt", city, 1, adaptation="sampled").adapted)
    cities = {name: load_city(name) for name in args.val_cities}
    scores = []
    for stream in (1, 2):  # adapting by the mean, validation does not read torch's stream
        torch.manual_seed(stream)
        scores.append(meta.validate(model, args, cities))
    assert scores[0] == scores[1]
