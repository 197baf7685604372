"""Offline -> online: the fine-tuning study on a 3x3 grid, and its numbers from hand-made curves."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch
from typer.testing import CliRunner

from marl_amod import finetune
from marl_amod.algos.registry import ALGOS, args_for
from marl_amod.cli import app
from marl_amod.errors import ConfigError, DataError

ROOT = Path(__file__).resolve().parent.parent

@pytest.fixture(scope="module")
def offline_policy(tmp_path_factory, tiny_prop_dataset) -> str:
    """A BC policy (8 updates) cloned from 4 PROP episodes on the 3x3 grid."""
    root = tmp_path_factory.mktemp("finetune")
    scenario, path = tiny_prop_dataset
    args = {"scenario": scenario, "dataset": path, "updates": 8, "batch_size": 8, "eval_every": 8, "eval_episodes": 1,
            "final_eval_episodes": 1, "hidden": 8, "run_dir": str(root / "bc"), "policy_out": str(root / "bc.pt")}  # fmt: skip
    ALGOS["bc"].train(args_for("bc", args))
    return str(root / "bc.pt")


def test_study_runs_both_arms_with_the_same_budget_and_writes_json_and_png(tmp_path, offline_policy):
    study = finetune.finetune_curve(offline_policy, episodes=8, num_envs=2, eval_every=4, eval_episodes=1, critic_warmup=2, run_root=tmp_path / "runs")
    ft, sc = study["runs"]["finetune"], study["runs"]["scratch"]
    assert study["behaviour_policy"] == "prop" and study["steps_per_episode"] == 5
    assert ft["validation"][0] == [0, study["pretrained_profit"]]  # the curve starts at the offline policy
    assert [ep for ep, _ in ft["validation"][1:]] == [ep for ep, _ in sc["validation"]] == [4, 8]
    assert [row[0] for row in ft["train"]] == [row[0] for row in sc["train"]] == [2, 4, 6, 8]
    assert ft["args"]["init_actor"] == offline_policy and sc["args"]["init_actor"] == ""
    assert all(cost >= 0 and revenue > 0 for _, revenue, cost in ft["train"] + sc["train"])
    json_path, png = finetune.write(study, tmp_path / "out")
    assert json.loads(json_path.read_text())["summary"] == study["summary"] and png.stat().st_size > 0
    assert "online steps" in finetune.describe(study)


def test_critic_warmup_holds_the_actor_still(tmp_path, offline_policy):
    """With every update a warm-up one, the fine-tuned actor's weights stay the offline policy's to the bit
    (its validations alone could not tell: on the grid, small moves round to the same vehicles); without
    the warm-up the same run moves them."""
    start = torch.load(offline_policy, weights_only=True)["state_dict"]

    def actor_after(warmup: int) -> dict[str, torch.Tensor]:
        root = tmp_path / f"warmup{warmup}"
        finetune.finetune_curve(offline_policy, episodes=4, num_envs=2, eval_every=2, eval_episodes=1, critic_warmup=warmup, run_root=root)
        return torch.load(root / "finetune" / "state.pt", weights_only=False)["actor"]

    held = actor_after(2)
    assert held.keys() == start.keys() and all(torch.equal(held[k], v) for k, v in start.items())
    moved = actor_after(0)
    assert any(not torch.equal(moved[k], v) for k, v in start.items())


def _study(scratch_val, ft_val=((0, 50.0), (10, 51.0), (20, 52.0))) -> dict:
    """Curves in the study's shape: validations every 10 episodes, train rows every 5 (batch means)."""
    rows = lambda rev, cost: [[ep, rev, cost] for ep in (5, 10, 15, 20)]  # noqa: E731
    return {
        "steps_per_episode": 19, "pretrained_profit": 50.0, "behaviour_profit": 49.0,
        "runs": {
            "finetune": {"args": {"episodes_per_update": 5}, "validation": [list(p) for p in ft_val], "train": rows(100.0, 10.0)},
            "scratch": {"args": {"episodes_per_update": 5}, "validation": [list(p) for p in scratch_val], "train": rows(90.0, 14.0)},
        },
    }


def test_summary_counts_steps_revenue_and_cost_until_scratch_matches():
    s = finetune.summarise(_study([(10, 45.0), (20, 50.5)]))
    assert s["episodes_to_match"] == 20 and s["steps_to_match"] == 20 * 19
    assert s["revenue_lost"] == pytest.approx(4 * 5 * 10.0)  # four updates of five episodes, $10 each
    assert s["excess_rebalancing_cost"] == pytest.approx(4 * 5 * 4.0)
    assert s["above_behaviour_throughout"]


def test_a_crossing_that_scratch_does_not_hold_is_no_match():
    """An early spike above the offline start that falls back is noise: the match is the validation
    from which scratch stays at or above it."""
    assert finetune.summarise(_study([(10, 50.5), (20, 45.0)]))["episodes_to_match"] is None
    s = finetune.summarise(_study([(10, 50.5), (20, 45.0), (30, 50.0), (40, 51.0)]))
    assert s["episodes_to_match"] == 30 and s["steps_to_match"] == 30 * 19


def test_summary_when_scratch_never_matches_and_fine_tuning_dips():
    s = finetune.summarise(_study([(10, 45.0), (20, 49.0)], ft_val=((0, 50.0), (10, 48.5), (20, 51.0))))
    assert not s["matched"] and s["steps_to_match"] is None and s["budget_steps"] == 20 * 19
    assert not s["above_behaviour_throughout"] and s["finetune_min_profit"] == 48.5


def test_a_policy_without_a_dataset_is_refused(tmp_path, offline_policy):
    card = json.loads(open(offline_policy.replace(".pt", ".json")).read())
    assert card["dataset"]["policy"] == "prop"
    with pytest.raises(ConfigError, match="offline policy"):
        finetune.finetune_curve(str(ROOT / "policies/a2c_gnn_synthetic.pt"), episodes=2, num_envs=2, run_root=tmp_path)


def test_cli_finetune_curve(tmp_path, offline_policy):
    res = CliRunner().invoke(app, ["finetune-curve", "--policy", offline_policy, "--episodes", "4", "--num-envs", "2", "--eval-every", "2",
                                   "--eval-episodes", "1", "--out", str(tmp_path / "o"), "--run-root", str(tmp_path / "r")])  # fmt: skip
    assert res.exit_code == 0, res.output
    assert (tmp_path / "o" / "finetune.json").is_file() and (tmp_path / "o" / "finetune.png").is_file()


def test_cli_finetune_curve_refuses_a_fresh_critic_with_a_critic_dataset(tmp_path, offline_policy):
    """The two options contradict each other: one was silently dropped before; now neither runs."""
    res = CliRunner().invoke(app, ["finetune-curve", "--policy", offline_policy, "--episodes", "2", "--fresh-critic",
                                   "--critic-dataset", str(tmp_path / "any.npz"), "--out", str(tmp_path / "o"), "--run-root", str(tmp_path / "r")])  # fmt: skip
    assert isinstance(res.exception, ConfigError) and "--fresh-critic" in str(res.exception)
    assert not (tmp_path / "r").exists() and not (tmp_path / "o").exists()


def test_concentration_cap_keeps_the_mean_and_bounds_the_total():
    """The fine-tuning cap widens samples without moving what the deterministic policy plays."""
    import torch

    from marl_amod.algos.a2c import Args, act, capped, sampling_concentrations

    alpha = torch.tensor([[60.0, 30.0, 10.0], [1.0, 2.0, 3.0]])
    out = capped(alpha, 10.0)
    assert torch.allclose(out.sum(-1), torch.tensor([10.0, 6.0]))  # the first scaled down, the second under the cap untouched
    assert torch.allclose(out / out.sum(-1, keepdim=True), alpha / alpha.sum(-1, keepdim=True))
    torch.manual_seed(0)
    sampled = sampling_concentrations(alpha[:1].expand(2000, -1), Args(concentration_cap=10.0))
    wide = torch.tensor(act(sampled, "centralised")[0])
    torch.manual_seed(0)
    narrow = torch.tensor(act(alpha[:1].expand(2000, -1), "centralised")[0])
    assert (wide.std(0) > 2.5 * narrow.std(0)).all()  # std ~ sqrt(m(1-m)/(total+1)): total 100 -> 10
    assert torch.allclose(wide.mean(0), torch.tensor([0.6, 0.3, 0.1]), atol=0.02)
    both = sampling_concentrations(alpha, Args(action_concentration=4.0, concentration_cap=10.0))
    assert torch.allclose(both.sum(-1), torch.tensor([10.0, 10.0]))  # scaled first (x4: 400, 24), then capped


def test_a_standardised_mlp_start_fine_tunes_beside_a_plain_scratch_arm(tmp_path, tiny_prop_dataset):
    """The scratch arm has no start to take input statistics from: it runs the plain MLP (what
    identity statistics amount to), the fine-tuned arm the start's standardisation."""
    scenario, path = tiny_prop_dataset
    args = {"scenario": scenario, "dataset": path, "updates": 4, "batch_size": 8, "eval_every": 4, "eval_episodes": 1, "final_eval_episodes": 1,
            "hidden": 8, "actor": "mlp", "standardise_inputs": True, "run_dir": str(tmp_path / "bc"), "policy_out": str(tmp_path / "bc.pt")}  # fmt: skip
    ALGOS["bc"].train(args_for("bc", args))
    study = finetune.finetune_curve(str(tmp_path / "bc.pt"), episodes=2, num_envs=2, eval_every=2, eval_episodes=1, critic_warmup=2, run_root=tmp_path / "runs")
    ft, sc = study["runs"]["finetune"], study["runs"]["scratch"]
    assert ft["validation"][0] == [0, study["pretrained_profit"]] and [ep for ep, _ in sc["validation"]] == [2]


def test_a_critic_pretrained_on_the_dataset_starts_the_fine_tuned_run(tmp_path, offline_policy, tiny_prop_dataset):
    """``critic_dataset``: the fine-tuned run's critic starts from one regressed on the logged episodes'
    standardised returns (it fits them: its loss falls well below a fresh critic's), the scratch run's
    stays fresh, and a critic state of another shape is refused by name."""
    import torch
    import torch.nn.functional as F

    from marl_amod.algos import a2c
    from marl_amod.algos.common import make_graph
    from marl_amod.scenario import load_city

    scenario, dataset = tiny_prop_dataset
    study = finetune.finetune_curve(offline_policy, episodes=4, num_envs=2, eval_every=4, eval_episodes=1, run_root=tmp_path / "runs")
    start = study["runs"]["finetune"]["args"]["init_critic"]  # the default: pre-trained on the policy's own dataset
    assert start.endswith("critic_init.pt") and not study["runs"]["scratch"]["args"]["init_critic"]
    fresh = finetune.finetune_curve(offline_policy, episodes=2, num_envs=2, eval_every=2, eval_episodes=1, critic_dataset=None,
                                    run_root=tmp_path / "fresh")  # fmt: skip
    assert not fresh["runs"]["finetune"]["args"]["init_critic"]
    import shutil

    moved = tmp_path / "moved.npz"
    shutil.copy(dataset, moved)
    ALGOS["bc"].train(args_for("bc", {"scenario": scenario, "dataset": str(moved), "updates": 2, "batch_size": 8, "eval_every": 2,
                                      "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8, "run_dir": str(tmp_path / "bc"),
                                      "policy_out": str(tmp_path / "bc.pt")}))  # fmt: skip
    moved.unlink()
    with pytest.raises(ConfigError, match="not there to pre-train the critic"):
        finetune.finetune_curve(str(tmp_path / "bc.pt"), episodes=2, num_envs=2, run_root=tmp_path / "gone")
    city = load_city(scenario)
    args = a2c.Args(scenario=scenario, hidden=8, num_envs=2, episodes_per_update=2, init_actor=offline_policy)
    fresh, fitted = a2c.make_critic(args, city), a2c.make_critic(args, city)
    a2c.load_critic_state(fitted, finetune.pretrain_critic(args, city, dataset, tmp_path / "c.pt", updates=300))
    from marl_amod.datasets import OfflineDataset

    data = OfflineDataset.load(dataset)
    x, graph = torch.tensor(data.global_view()["x"]), make_graph(city, args)
    target = torch.tensor(finetune.standardised_returns(data, args.gamma, args.reward_scale), dtype=torch.float32)
    assert target.mean().abs() < 1e-5 and (target.std() - 1).abs() < 0.05
    with torch.no_grad():
        loss = {k: F.smooth_l1_loss(c(x, graph), target).item() for k, c in (("fresh", fresh), ("fitted", fitted))}
    assert loss["fitted"] < 0.5 * loss["fresh"]
    wide = a2c.make_critic(args.model_copy(update={"hidden": 16}), city)
    with pytest.raises(DataError, match="does not fit this run's critic .*: size mismatch"):  # says which weights differ
        a2c.load_critic_state(wide, str(tmp_path / "c.pt"))
    (tmp_path / "text.pt").write_text("not a critic")
    (tmp_path / "empty.pt").write_bytes(b"")
    for bad, message in ((tmp_path / "text.pt", "text file"), (tmp_path / "empty.pt", "empty"), (offline_policy, "no critic state there")):
        with pytest.raises(DataError, match=message):  # one line each, not a KeyError, EOFError or unpickling traceback
            a2c.load_critic_state(wide, str(bad))
