"""Meta-RL through recurrence: per-city units, the recurrent GNN, trials, adaptation, transfer strategies."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from marl_amod.algos import meta
from marl_amod.algos.registry import ALGOS
from marl_amod.errors import ConfigError
from marl_amod.evaluation import evaluate
from marl_amod.models.recurrent import RecurrentGNN
from marl_amod.scenario import grid_city, load_city
from marl_amod.system import FleetSystem
from marl_amod.transfer import STRATEGIES, normalised, run_strategy


def _city_yaml(tmp_path, name, **keys):
    text = f"name: {name}\nsource: synthetic\nhorizon: 6\n" + "".join(f"{k}: {v}\n" for k, v in keys.items())
    (tmp_path / f"{name}.yaml").write_text(text)
    return str(tmp_path / f"{name}.yaml")


def test_city_scale_makes_a_tenfold_city_look_alike():
    """Ten times the fleet and the demand: the same scaled request features, rewards scaled 10x."""
    small = grid_city(rows=3, cols=3, vehicles_per_region=12, requests_per_region=3.0)
    big = grid_city(rows=3, cols=3, vehicles_per_region=120, requests_per_region=30.0)
    s_small, s_big = meta.CityScale.of(small), meta.CityScale.of(big)
    assert s_big.reward == pytest.approx(10 * s_small.reward) and s_big.vehicles == 10 * s_small.vehicles
    feats = []
    for city, scale in ((small, s_small), (big, s_big)):
        system = FleetSystem(city)
        system.reset(np.random.SeedSequence(0))
        feats.append(meta.task_features(system, scale, lookahead=3))
    assert feats[0].shape == (9, meta.n_task_features(3))
    np.testing.assert_allclose(feats[0][:, 4:], feats[1][:, 4:], rtol=1e-5)  # request values and t / horizon
    # idle vehicles after the first dispatch: in units of fleet / N, about the same in both cities
    assert abs(feats[0][:, 0].mean() - feats[1][:, 0].mean()) < 0.3


def test_recurrent_gnn_is_size_agnostic_and_its_memory_changes_the_action():
    torch.manual_seed(0)
    model = RecurrentGNN(n_features=5, hidden=8)
    for city in (grid_city(rows=2, cols=3), grid_city(rows=4, cols=4)):
        n = city.n_regions
        edges = torch.as_tensor(np.array(city.edge_index), dtype=torch.long)
        x, a, r = torch.rand(n, 5), torch.ones(n), torch.tensor(0.5)
        alpha, v, mem = model(x, a, r, model.initial_memory(n), edges)
        assert alpha.shape == (n,) and (alpha > 0).all() and v.shape == () and mem.shape == (n, 8)
        again, _, _ = model(x, a, r, mem, edges)  # same input, what it remembers differs
        assert not torch.allclose(alpha, again)


def test_the_deployed_policy_replays_the_trained_agent_exactly():
    """MetaPolicy (through evaluate) rebuilds the previous reward from the booked money: its
    episode must be the trial agent's deterministic episode from the same memory, to the cent."""
    city = grid_city(rows=3, cols=3, horizon=6)
    torch.manual_seed(1)
    model = RecurrentGNN(meta.n_task_features(6), hidden=8)
    policy = meta.adapt(model, city, episodes=2, lookahead=6)
    got = evaluate(policy, city, episodes=2, seed=0)["metrics"]["profit"]["mean"]
    want = []
    for k in range(2):
        agent = meta.MetaAgent(model, city, 6)
        agent.memory = policy.adapted.clone()
        trial = meta.run_trial(agent, FleetSystem(city), [np.random.SeedSequence([0, k])], sample=False)
        want.append(trial.profits[0])
    # the trial's profit omits the first dispatch (booked at reset), evaluate counts it
    first = []
    for k in range(2):
        system = FleetSystem(city)
        system.reset(np.random.SeedSequence([0, k]))
        first.append(float(system.sim.totals.profit.sum()))
    assert got == pytest.approx(np.mean(np.add(want, first)), rel=1e-9)


def test_meta_training_resumes_exactly_and_ships_a_policy_that_adapts(tmp_path):
    tasks = [_city_yaml(tmp_path, "small", rows=2, cols=3, vehicles_per_region=5),
             _city_yaml(tmp_path, "large", rows=3, cols=3, vehicles_per_region=40, requests_per_region=20)]  # fmt: skip
    args = meta.Args(scenario="synthetic", cities=tasks, val_cities=tasks[:1], hidden=8, episodes=8, trial_episodes=2,
                     trials_per_update=2, eval_every=4, final_eval_episodes=2, run_dir=str(tmp_path / "full"),
                     policy_out=str(tmp_path / "full.pt"))  # fmt: skip
    assert "meta" in ALGOS
    summary = ALGOS["meta"].train(args)
    assert summary["card"]["algorithm"] == "meta" and summary["card"]["episodes_trained"] == 8
    half = args.model_copy(update={"run_dir": str(tmp_path / "half"), "policy_out": str(tmp_path / "resumed.pt")})
    ALGOS["meta"].train(half.model_copy(update={"episodes": 4}))
    ALGOS["meta"].train(half, resume=str(tmp_path / "half" / "state.pt"))
    full, resumed = (torch.load(tmp_path / f, weights_only=True)["state_dict"] for f in ("full.pt", "resumed.pt"))
    for key in full:
        torch.testing.assert_close(full[key], resumed[key], rtol=0, atol=0)
    # the checkpoint evaluates like any policy file: it adapts (1 episode) to the city first
    result = evaluate(str(tmp_path / "full.pt"), "synthetic", episodes=1)
    assert result["policy"] == "full" and np.isfinite(result["metrics"]["profit"]["mean"])


def test_held_out_cities_cannot_be_training_tasks():
    with pytest.raises(ConfigError, match="held-out"):
        meta.train(meta.Args(cities=["chicago", "san_francisco"]))
    with pytest.raises(ConfigError, match="held-out"):
        meta.train(meta.Args(scenario="porto", cities=["porto", "rome"]))


def test_transfer_strategies_and_the_normalised_score(tmp_path):
    assert normalised(150.0, 100.0, 200.0) == 50.0 and normalised(100.0, 100.0, 200.0) == 0.0
    with pytest.raises(ConfigError, match="unknown strategy"):
        run_strategy("wishful", "synthetic")
    with pytest.raises(ConfigError, match="needs --policy"):
        run_strategy("zero-shot", "synthetic")
    assert len(STRATEGIES) == 6
    rec = run_strategy("mpc-forecast", "synthetic", episodes=1)
    assert rec["transfer"]["target_episodes"] == 0


def test_fine_tuning_takes_k_episodes_and_changes_the_actor():
    from marl_amod.checkpoints import load_actor
    from marl_amod.transfer import fine_tune

    city = load_city("synthetic")
    before, _ = load_actor("policies/a2c_gnn_synthetic.pt", city)
    policy = fine_tune("policies/a2c_gnn_synthetic.pt", city, episodes=2, per_update=2)
    changed = [not torch.equal(p, q) for p, q in zip(before.state_dict().values(), policy.actor.state_dict().values(), strict=True)]
    assert any(changed)
    rec = run_strategy("fine-tune", "synthetic", policy="policies/a2c_gnn_synthetic.pt", adapt_episodes=2, episodes=1)
    assert rec["transfer"]["target_episodes"] == 2


def test_a_study_reruns_only_the_rows_asked_for(monkeypatch):
    from marl_amod import transfer

    monkeypatch.setitem(transfer.STUDIES, "toy", ("synthetic",))
    first = transfer.run_study("toy", episodes=1, strategies=("mpc-forecast", "mpc-oracle"))
    rows = first["targets"]["synthetic"]
    assert set(rows) == {"equal-distribution", "mpc-forecast", "mpc-oracle"}
    assert rows["equal-distribution"]["normalised_score"] == 0.0 and rows["mpc-oracle"]["normalised_score"] == 100.0
    again = transfer.run_study("toy", episodes=1, strategies=("mpc-forecast",), previous=first)
    assert again["targets"]["synthetic"]["mpc-oracle"] is rows["mpc-oracle"]  # kept, not rerun
    assert "# toy" not in transfer.study_markdown(again) and "| mpc-forecast |" in transfer.study_markdown(again)
    other_seed = transfer.run_study("toy", episodes=1, seed=1, strategies=("mpc-forecast",), previous=first)
    assert "mpc-oracle" not in other_seed["targets"]["synthetic"]  # rows of another seed are never mixed in
