"""Study figures: region cells, the per-region map of evaluations (wait time, service rate), and
normalised-score bars of the transfer tables."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from typer.testing import CliRunner

from marl_amod.cli import app
from marl_amod.errors import ConfigError, DataError, OutputError
from marl_amod.evaluation import evaluate
from marl_amod.plots import region_cells, region_map, region_map_figure
from marl_amod.scenario import grid_city


def _area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * abs(float(np.dot(x, np.roll(y, 1)) - np.dot(y, np.roll(x, 1))))


def test_region_cells_of_a_grid_are_its_squares_and_contain_their_region():
    city = grid_city(3, 4, horizon=4)
    cells, (x0, x1, y0, y1) = region_cells(city.positions)
    assert len(cells) == city.n_regions
    pos = city.positions
    np.testing.assert_allclose([x0, x1, y0, y1], [pos[:, 0].min() - 0.5, pos[:, 0].max() + 0.5, pos[:, 1].min() - 0.5, pos[:, 1].max() + 0.5])
    for k, cell in enumerate(cells):
        assert MplPath(cell).contains_point(pos[k])
    interior = [k for k in range(city.n_regions) if 0 < pos[k, 0] < 3 and -2 < pos[k, 1] < 0]
    assert interior and all(_area(cells[k]) == pytest.approx(1.0) for k in interior)


@pytest.fixture(scope="module")
def two_results():
    city = grid_city(3, 3, seed=1, horizon=6, vehicles_per_region=3, requests_per_region=3.0)
    return city, [evaluate(name, city, episodes=2, seed=0, max_wait=2) for name in ("no-rebalancing", "equal-distribution")]


def test_region_map_shares_one_colour_scale_per_row(two_results, tmp_path):
    city, results = two_results
    fig = region_map_figure(results, city)
    maps = [ax for ax in fig.axes if ax.collections and ax.get_label() != "<colorbar>"]
    assert len(maps) == 2 * len(results)  # a row per metric, a column per policy
    wait_max = max(max(r["per_region"]["wait_time"]) for r in results)
    assert wait_max > 0
    row_norms = [(ax.collections[0].norm.vmin, ax.collections[0].norm.vmax) for ax in maps]
    assert row_norms[:2] == [(0.0, pytest.approx(wait_max))] * 2 and row_norms[2:] == [(0.0, 1.0)] * 2
    np.testing.assert_allclose(maps[1].collections[0].get_array(), results[1]["per_region"]["wait_time"])
    path = region_map(results, city, tmp_path / "sub" / "map.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_region_map_names_the_metrics_it_knows(two_results):
    city, results = two_results
    with pytest.raises(ValueError, match="service_rate"):
        region_map_figure(results, city, rows=("happiness",))


def test_cli_wait_map_writes_the_figure_and_the_results(tmp_path):
    out = tmp_path / "wait.png"
    args = ["plot", "wait-map", "--policy", "no-rebalancing", "--policy", "equal-distribution", "--episodes", "1", "--output", str(out)]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    assert out.is_file()
    data = json.loads(out.with_suffix(".json").read_text())
    assert data["max_wait"] == 3 and [r["policy"] for r in data["results"]] == ["no-rebalancing", "equal-distribution"]
    assert max(data["results"][1]["per_region"]["wait_time"]) > 0  # requests waited
    (tmp_path / "taken.json").mkdir()  # where the numbers beside the figure would go: refused before the episodes
    taken = CliRunner().invoke(app, ["plot", "wait-map", "--episodes", "1", "--output", str(tmp_path / "taken.png")])
    assert isinstance(taken.exception, OutputError) and "taken.json" in str(taken.exception) and not (tmp_path / "taken.png").exists()


def test_score_bars_draw_one_bar_per_method_and_target_in_one_colour_per_method():
    from marl_amod.plots import score_bars_figure

    groups = {"city a": [("x", 10.0, 2.0), ("y", 50.0, 1.0), ("z", 100.0, 3.0)], "city b": [("x", -20.0, 4.0), ("z", 100.0, 1.0)]}
    ax = score_bars_figure(groups, "t").axes[0]
    bars = ax.patches
    assert [b.get_height() for b in bars] == [10.0, 50.0, 100.0, -20.0, 100.0]
    colour = lambda i: bars[i].get_facecolor()  # noqa: E731
    assert colour(0) == colour(3) and colour(2) == colour(4) and len({colour(i) for i in range(3)}) == 3
    assert bars[3].get_x() < 1.0 < bars[4].get_x()  # city b's bars sit in the second group
    assert [t.get_text() for t in ax.get_legend().get_texts()] == ["x", "y", "z"]  # each method named once
    assert sorted(line.get_ydata()[0] for line in ax.lines if line.get_linestyle() == "--") == [0.0, 100.0]
    with pytest.raises(ValueError, match="at least one"):
        score_bars_figure({"city a": []})



def test_score_bars_keep_long_target_names_apart():
    """Three held-out cities with two methods each ran their names together ("nyc_brooklynshenzhen_downtown_west")."""
    from marl_amod.plots import score_bars_figure

    names = ["san_francisco", "nyc_brooklyn", "shenzhen_downtown_west"]
    fig = score_bars_figure({n: [("a", 80.0, 1.0), ("b", 100.0, 1.0)] for n in names})
    fig.canvas.draw()
    renderer = fig.canvas.get_renderer()
    ticks = fig.axes[0].get_xticklabels()
    assert [t.get_text() for t in ticks] == ["san_francisco", "nyc_brooklyn", "shenzhen\n_downtown_west"]
    boxes = [t.get_window_extent(renderer) for t in ticks]
    assert all(boxes[i].x1 < boxes[i + 1].x0 for i in range(len(boxes) - 1))  # each name ends before the next begins


def _study(scores: dict[str, float]) -> dict:
    rows = {}
    for name, profit in scores.items():
        metrics = {"profit": {"mean": profit, "std": 5.0}, "served_demand": {"mean": 1.0}, "rebalancing_cost": {"mean": 2.0}}
        rows[name] = {"metrics": metrics, "normalised_score": profit - 100.0}
    return {"study": "event", "episodes": 2, "seed": 0, "targets": {"nyc_brooklyn_event": rows}}


def test_cli_transfer_table_redraw_rewrites_markdown_and_figure_from_the_json_alone(tmp_path):
    from marl_amod.transfer import study_markdown, study_scores

    payload = _study({"equal-distribution": 100.0, "meta-rl": 160.0, "mpc-oracle": 200.0})
    assert study_scores(payload) == {"nyc_brooklyn_event": [("meta-rl", 60.0, 5.0), ("mpc-oracle", 100.0, 5.0)]}
    runner = CliRunner()
    typo = runner.invoke(app, ["transfer-table", "--study", "events", "--out", str(tmp_path / "new")])
    assert isinstance(typo.exception, ConfigError) and not (tmp_path / "new").exists()  # refused before the folder is made
    missing = runner.invoke(app, ["transfer-table", "--study", "event", "--out", str(tmp_path), "--redraw"])
    assert isinstance(missing.exception, DataError) and "does not exist" in str(missing.exception)
    (tmp_path / "event.json").write_text(json.dumps(payload))
    both = runner.invoke(app, ["transfer-table", "--study", "event", "--out", str(tmp_path), "--redraw", "--strategy", "meta-rl"])
    assert isinstance(both.exception, ConfigError) and "evaluates nothing" in str(both.exception)
    result = runner.invoke(app, ["transfer-table", "--study", "event", "--out", str(tmp_path), "--redraw"])
    assert result.exit_code == 0, result.output
    header = "<!-- marl-amod transfer-table --study event --episodes 2 --seed 0 -->\n"
    assert (tmp_path / "event.md").read_text() == header + study_markdown(payload)
    assert (tmp_path / "event.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    partial = _study({"equal-distribution": 100.0, "meta-rl": 160.0})  # --strategy meta-rl on a fresh folder
    del partial["targets"]["nyc_brooklyn_event"]["meta-rl"]["normalised_score"]
    assert study_scores(partial) == {} and "| meta-rl | 0.2 ± 0.0 | - |" in study_markdown(partial)


@pytest.mark.parametrize("study", ["intercity", "event"])
def test_committed_transfer_tables_are_their_json_rendered(study):
    """docs/meta's tables are generated, never edited by hand: the markdown is its JSON rendered
    (after the header naming the command that made it)."""
    from pathlib import Path

    from marl_amod.transfer import study_markdown

    folder = Path(__file__).resolve().parent.parent / "docs" / "meta"
    payload = json.loads((folder / f"{study}.json").read_text())
    header, body = (folder / f"{study}.md").read_text().split("\n", 1)
    assert header.startswith(f"<!-- marl-amod transfer-table --study {study} ") and body == study_markdown(payload)
    assert (folder / f"{study}.png").is_file()
