"""The scripts behind docs/meso and docs/studies/beta_sweep.md: the paired comparison with equal
distribution, the beta table and figure, and where the meso evaluations are kept."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

sys.path.insert(0, str(Path(__file__).resolve().parent.parent / "benchmarks"))
import beta_sweep  # noqa: E402
import meso_eval  # noqa: E402
import meso_table  # noqa: E402


def _record(policy: str, profits: list[float], seed: int = 0) -> dict:
    return {"policy": policy, "seed": seed, "episodes": len(profits), "per_episode": [{"profit": p} for p in profits]}


def test_paired_gap_is_the_episode_by_episode_difference_from_equal_distribution():
    floor = _record("equal-distribution", [100.0, 200.0, 300.0])
    assert meso_table.paired_gap(_record("mine", [110.0, 190.0, 330.0]), floor) == "+10 ± 16 (2/3)"
    assert meso_table.paired_gap(_record("mine", [110.0, 190.0, 330.0], seed=1), floor) == "–"  # other demand: not paired
    assert meso_table.paired_gap(floor, floor) == "–"


def test_beta_table_and_figure_have_one_row_and_point_per_beta(tmp_path):
    def metrics(beta: float) -> dict:
        return {k: {"mean": 1000.0 * beta if k == "rebalancing_cost" else 0.5, "std": 0.1} for k in beta_sweep.COLUMNS}

    rows = [{"beta": b, "episodes_trained": 6000, "metrics": metrics(b)} for b in (0.1, 0.5)]
    table = beta_sweep.table_markdown({"rows": rows})
    lines = table.strip().splitlines()
    assert len(lines) == 2 + len(rows)
    assert lines[3].startswith("| 0.5 | 6,000 |") and "| 500 ± 0 |" in lines[3] and "50.0% ± 10.0%" in lines[3]
    beta_sweep.plot(rows, tmp_path / "sweep.png")
    assert (tmp_path / "sweep.png").stat().st_size > 0


@pytest.mark.parametrize(("policy", "name"), [("policies/a2c_gnn_lux.pt", "a2c_gnn_lux"), ("mpc-oracle", "mpc-oracle")])
def test_meso_eval_keeps_one_file_per_policy_episodes_and_seed(policy, name, tmp_path):
    assert meso_eval.output_path(policy, tmp_path, 10, 0) == tmp_path / f"{name}_10ep_seed0.json"
