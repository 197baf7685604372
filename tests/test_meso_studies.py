"""The scripts behind docs/meso and docs/studies/beta_sweep.md: the paired comparison with equal
distribution, the beta table and figure, and where the meso evaluations are kept."""

from __future__ import annotations

from pathlib import Path

import beta_sweep  # benchmarks/ (pytest's pythonpath)
import meso_eval
import meso_table
import pytest

ROOT = Path(__file__).resolve().parent.parent


def _record(policy: str, profits: list[float], seed: int = 0) -> dict:
    return {"policy": policy, "seed": seed, "episodes": len(profits), "per_episode": [{"profit": p} for p in profits]}


def test_paired_gap_is_the_episode_by_episode_difference_from_equal_distribution():
    floor = _record("equal-distribution", [100.0, 200.0, 300.0])
    assert meso_table.paired_gap(_record("mine", [110.0, 190.0, 330.0]), floor) == "+10 ± 16 (2/3)"
    assert meso_table.paired_gap(_record("mine", [110.0, 190.0, 330.0], seed=1), floor) == "–"  # other demand: not paired
    assert meso_table.paired_gap(floor, floor) == "–"


def test_beta_table_and_figure_have_one_row_and_point_per_route_and_beta(tmp_path):
    def metrics(beta: float) -> dict:
        return {k: {"mean": 1000.0 * beta if k == "rebalancing_cost" else 0.5, "std": 0.1} for k in beta_sweep.COLUMNS}

    a2c = [{"beta": b, "episodes_trained": 6000, "metrics": metrics(b)} for b in (0.1, 0.5)]
    clone = [{"beta": 0.5, "episodes_trained": 0, "expert": {"policy": "mpc-forecast", "episodes": 40}, "metrics": metrics(0.5)}]
    payload = {"routes": {"a2c": {"rows": a2c}, "imitation": {"rows": clone}}}
    lines = beta_sweep.table_markdown(payload).strip().splitlines()
    assert len(lines) == 2 + len(a2c) + len(clone)
    assert lines[3].startswith("| a2c | 0.5 | 6,000 A2C ep. |") and "| 500 ± 0 |" in lines[3] and "50.0% ± 10.0%" in lines[3]
    assert lines[4].startswith("| imitation | 0.5 | BC on 40 mpc-forecast ep. |")
    beta_sweep.plot(payload, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 0


def test_imitation_route_clones_an_expert_that_rebalances_less_when_trips_cost_more(tmp_path):
    """Route imitation on the synthetic city: MPC-Forecast's objective carries beta, so its clone
    at a high beta moves far fewer vehicles than at a low one; the figure keeps the route already
    there, and a second call reuses the dataset and the clone."""
    out = tmp_path / "out"
    out.mkdir()
    (out / "beta_sweep.json").write_text('{"routes": {"a2c": {"rows": []}}}')
    argv = [
        "--route", "imitation", "--betas", "0.2", "2.0", "--train-scenario", "synthetic", "--eval-scenario", "synthetic",
        "--collect-episodes", "2", "--bc-updates", "200", "--eval-episodes", "1", "--runs", str(tmp_path / "runs"), "--out", str(out),
    ]  # fmt: skip
    payload = beta_sweep.main(argv)
    assert list(payload["routes"]) == ["a2c", "imitation"]
    low, high = payload["routes"]["imitation"]["rows"]
    assert low["expert"] == {**low["expert"], "policy": "mpc-forecast", "episodes": 2}
    moved = [r["metrics"]["rebalancing_cost"]["mean"] / r["beta"] for r in (low, high)]  # vehicle-steps moved empty
    assert moved[1] < 0.5 * moved[0]
    data = sorted((tmp_path / "runs").glob("mpc-forecast_synthetic_beta*_2ep_seed0.npz"))
    assert len(data) == 2
    stamps = [p.stat().st_mtime_ns for p in data]
    assert beta_sweep.main(argv)["routes"]["imitation"]["rows"] == [low, high]
    assert [p.stat().st_mtime_ns for p in data] == stamps
    refine = tmp_path / "refine.yaml"  # A2C from each clone with the anti-forgetting options
    refine.write_text(
        f"extends: {ROOT / beta_sweep.RECIPE}\nargs:\n  critic_warmup: 1\n  kl_coef: 1.0\n  action_concentration: 10\n  eval_episodes: 1\n  final_eval_episodes: 1\n"
    )
    refined = beta_sweep.main([*argv, "--refine", str(refine), "--episodes", "16"])["routes"]
    assert list(refined) == ["a2c", "imitation", "imitation+a2c"]
    assert [r["policy"].split("/")[-1] for r in refined["imitation+a2c"]["rows"]] == [
        "a2c_from_clone_synthetic_beta0.2.pt",
        "a2c_from_clone_synthetic_beta2.pt",
    ]
    assert "BC on 2 mpc-forecast ep. + 16 A2C ep." in (out / "beta_sweep_table.md").read_text()


@pytest.mark.parametrize(("policy", "name"), [("policies/a2c_gnn_lux.pt", "a2c_gnn_lux"), ("mpc-oracle", "mpc-oracle")])
def test_meso_eval_keeps_one_file_per_policy_episodes_and_seed(policy, name, tmp_path):
    assert meso_eval.output_path(policy, tmp_path, 10, 0) == tmp_path / f"{name}_10ep_seed0.json"
