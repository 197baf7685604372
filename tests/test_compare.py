"""``marl-amod compare``: says what it will train before it does, can skip it, and draws readable plots."""

from __future__ import annotations

import json
from pathlib import Path

import matplotlib
import pytest
import yaml
from typer.testing import CliRunner

from marl_amod.cli import app
from marl_amod.comparison import architecture, learning_curves_figure, markdown_table, served_figure

matplotlib.use("Agg")


@pytest.fixture
def compare_config(tmp_path: Path) -> Path:
    """A comparison on a 3x3 city with one A2C run whose policy file does not exist yet."""
    city = tmp_path / "tiny.yaml"
    city.write_text(yaml.safe_dump({"name": "tiny", "source": "synthetic", "rows": 3, "cols": 3, "horizon": 6, "vehicles_per_region": 5}))
    args = {"episodes": 4, "episodes_per_update": 2, "eval_every": 4, "eval_episodes": 1, "final_eval_episodes": 1, "hidden": 8,
            "run_dir": str(tmp_path / "run"), "policy_out": str(tmp_path / "policies" / "p.pt")}  # fmt: skip
    config = tmp_path / "compare.yaml"
    config.write_text(yaml.safe_dump({"scenario": str(city), "episodes": 2, "baselines": ["equal-distribution"],
                                      "output": str(tmp_path / "cmp"), "runs": [{"label": "gnn", "algo": "a2c", "args": args}]}))  # fmt: skip
    return config


def test_compare_no_train_skips_missing_policies_and_says_so(compare_config: Path, tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["compare", "--config", str(compare_config), "--no-train"])
    assert res.exit_code == 0, res.output
    assert "skipping 'gnn'" in res.output and "not found" in res.output
    assert not (tmp_path / "policies" / "p.pt").exists()  # nothing trained
    rows = json.loads((tmp_path / "cmp" / "compare.json").read_text())["rows"]
    assert [r["label"] for r in rows] == ["equal-distribution"]


def test_two_runs_writing_one_policy_are_refused_before_any_training(compare_config: Path, tmp_path: Path) -> None:
    from marl_amod.comparison import load_compare_config
    from marl_amod.errors import ConfigError

    raw = yaml.safe_load(compare_config.read_text())
    mlp = {"label": "mlp", "algo": "a2c", "args": {**raw["runs"][0]["args"], "actor": "mlp", "run_dir": str(tmp_path / "run_mlp")}}
    raw["runs"].append(mlp)  # its own run folder, the gnn run's policy file
    compare_config.write_text(yaml.safe_dump(raw))
    with pytest.raises(ConfigError, match="run 'gnn'.* and .*run 'mlp'.* share policy_out"):
        load_compare_config(compare_config)


def test_a_comparison_without_baselines_is_refused(compare_config: Path) -> None:
    from marl_amod.comparison import load_compare_config
    from marl_amod.errors import ConfigError

    raw = yaml.safe_load(compare_config.read_text())
    compare_config.write_text(yaml.safe_dump({**raw, "baselines": []}))  # the gap column would be nan
    with pytest.raises(ConfigError, match="baselines: List should have at least 1 item"):
        load_compare_config(compare_config)


def test_compare_announces_training_before_it_starts(compare_config: Path, tmp_path: Path) -> None:
    res = CliRunner().invoke(app, ["compare", "--config", str(compare_config)])
    assert res.exit_code == 0, res.output
    text = " ".join(res.output.split())
    assert "will train 'gnn' (a2c, centralised, 4 episodes" in text and "--no-train" in text
    assert text.index("will train") < text.index("evaluating equal-distribution")  # said before anything runs
    assert (tmp_path / "policies" / "p.pt").is_file()
    res = CliRunner().invoke(app, ["compare", "--config", str(compare_config)])  # found now: nothing to announce
    assert res.exit_code == 0 and "will train" not in res.output


def _row(label: str, kind: str, profit: float, served: list[float], run_dir: str = "") -> dict:
    metrics = {"profit": {"mean": profit, "std": 1.0}, "served_demand": {"mean": sum(served), "std": 0.0},
               "rebalancing_cost": {"mean": 0.0, "std": 0.0}}  # fmt: skip
    return {"label": label, "kind": kind, "run_dir": run_dir, "gap_to_best_baseline": 0.0,
            "result": {"metrics": metrics, "per_region": {"served_demand": served}}}  # fmt: skip


def _overlaps(a, b) -> bool:
    return a.x0 < b.x1 and b.x0 < a.x1 and a.y0 < b.y1 and b.y0 < a.y1


def test_compare_plots_keep_legends_and_baseline_names_off_the_data(tmp_path: Path) -> None:
    from marl_amod.algos.common import Logger

    run_dir = tmp_path / "run"
    log = Logger(run_dir, tensorboard=False)
    for ep, profit in enumerate([90.0, 100.0, 110.0, 120.0]):  # crosses the baseline at 100
        log.log(ep * 10, **{"eval/profit": profit})
    log.close()
    rows = [_row("equal-distribution", "baseline", 100.0, [5, 6, 7, 8]), _row("gnn", "learned", 120.0, [9, 9, 9, 9], str(run_dir))]
    for fig in (learning_curves_figure(rows, "x"), served_figure(rows, "x")):
        (ax,) = fig.axes
        fig.canvas.draw()
        renderer = fig.canvas.get_renderer()
        legend = ax.get_legend()
        labels = [t.get_text() for t in legend.get_texts()]
        assert any("equal-distribution" in t for t in labels) and "gnn" in labels
        assert not _overlaps(legend.get_window_extent(renderer), ax.get_window_extent(renderer))
        assert not ax.texts  # no names written on the plot, where a curve can cross them
    missing = [*rows, _row("shipped", "learned", 110.0, [9, 9, 9, 9], str(tmp_path / "no_run"))]  # a policy trained elsewhere
    (ax,) = learning_curves_figure(missing, "x").axes
    assert "no training log (run_dir) for: shipped" in ax.get_xlabel() and "shipped" not in [t.get_text() for t in ax.get_legend().get_texts()]


@pytest.mark.parametrize(
    ("card", "label"),
    [({"actor": "mlp", "conv": "gcn"}, "MLP"), ({"actor": "cnn", "conv": "gcn"}, "CNN"),
     ({"actor": "gnn", "conv": "sage"}, "GNN, sage"), ({"actor": "local", "conv": "gcn"}, "local GNN layer, sage"),
     ({"actor": "gnn", "conv": "gcn", "readout": "mean-max"}, "GNN, gcn, mean-max readout")],
)  # fmt: skip
def test_compare_table_names_message_passing_only_for_gnn_actors(card: dict, label: str) -> None:
    assert architecture(card) == label
    full = {**card, "algorithm": "a2c", "mode": "centralised", "training_wall_s": 60.0, "episodes_trained": 4}
    row = {**_row("r", "learned", 1.0, [1.0]), "card": full}
    assert f"A2C / centralised ({label}) |" in markdown_table([row], "x", 1, 0, "-")
