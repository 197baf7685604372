"""Study figures: region cells and the per-region map of evaluations (wait time, service rate)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from matplotlib.path import Path as MplPath
from typer.testing import CliRunner

from marl_amod.cli import app
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
