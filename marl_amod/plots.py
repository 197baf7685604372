"""Study figures drawn from evaluation results: per-region metrics on the region map, and the
normalised scores of a results table as bars.

``region_map`` is the paper's map of the average waiting time per region (one panel per policy,
a shared colour scale), and the same for any per-region metric of
:func:`marl_amod.metrics.region_metrics` (the service rate is the usual second row). Regions are
drawn as the Voronoi cells of ``City.positions``: for regions made by k-means (the SUMO cities)
those cells are exactly the regions, for a grid city they are its squares, and for cities
placed by multidimensional scaling they are a faithful-enough sketch. matplotlib is imported
only here, and only when something is drawn.

``score_ranking`` draws one results table (one city, many policies) as horizontal bars from best
to worst, baselines and trained policies in two colours. ``score_bars`` draws a study's table (a
few methods on a few targets): a method's normalised score (equal distribution 0, MPC-Oracle
100, the lines drawn) per target, a bar with the episode std as its whisker, one colour per
method in every group, so a method's rank reads across targets at a glance.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.scenario.types import City

ROW_STYLE: dict[str, tuple[str, str]] = {  # per-region metric -> (colour-bar label, colormap)
    "wait_time": ("mean waiting time (min)", "magma_r"),
    "service_rate": ("service rate (served / requested)", "viridis"),
    "served_demand": ("passengers served per episode", "viridis"),
    "profit": ("profit per episode", "viridis"),
}
GINI_OF = {"wait_time": "wait_time_gini", "service_rate": "service_rate_gini"}


def _caption(metrics: dict[str, dict[str, float]], key: str) -> str:
    """City-wide value and Gini of a row's metric, as far as the evaluation reports them."""
    parts = []
    if key == "service_rate" and metrics.get("demand", {}).get("mean"):
        parts.append(f"city {metrics['served_demand']['mean'] / metrics['demand']['mean']:.1%}")
    elif key in metrics:
        parts.append(f"city {metrics[key]['mean']:.2f}")
    if GINI_OF.get(key) in metrics:
        parts.append(f"Gini {metrics[GINI_OF[key]]['mean']:.3f}")
    return ", ".join(parts)


def region_cells(positions: np.ndarray) -> tuple[list[np.ndarray], tuple[float, float, float, float]]:
    """Voronoi cell (k, 2) of every region and the (xmin, xmax, ymin, ymax) box that frames them.

    Four far-away helper points close every real cell; the box (the positions plus half the
    median nearest-neighbour distance) crops what lies outside the city.
    """
    from scipy.spatial import Voronoi

    pos = np.asarray(positions, dtype=float)
    n = pos.shape[0]
    gap = np.linalg.norm(pos[:, None] - pos[None, :], axis=-1) + np.diag(np.full(n, np.inf))
    margin = 0.5 * float(np.median(gap.min(axis=1))) if n > 1 else 1.0
    lo, hi = pos.min(axis=0) - margin, pos.max(axis=0) + margin
    far = 10.0 * float(np.max(hi - lo)) + 1.0
    centre = (lo + hi) / 2
    helpers = centre + far * np.array([[-1.0, -1.0], [-1.0, 1.0], [1.0, -1.0], [1.0, 1.0]])
    vor = Voronoi(np.vstack([pos, helpers]))
    cells = [vor.vertices[vor.regions[vor.point_region[i]]] for i in range(n)]
    return cells, (lo[0], hi[0], lo[1], hi[1])


def region_map(
    results: Sequence[dict[str, Any]],
    city: City,
    path: str | Path,
    rows: Sequence[str] = ("wait_time", "service_rate"),
    title: str | None = None,
) -> Path:
    """Write :func:`region_map_figure` to ``path`` atomically (format from the suffix, png by default)."""
    path = figure_destination(path)  # a bad name fails before the drawing
    return save_figure(region_map_figure(results, city, rows, title), path)


def save_figure(fig: Any, path: Path) -> Path:
    """``fig`` written to ``path`` atomically, in the format its suffix names (none: png)."""
    from marl_amod.files import atomic_write

    return atomic_write(path, lambda fh: fig.savefig(fh, format=path.suffix.lstrip(".") or "png"))


def figure_destination(path: str | Path, *, what: str = "figure") -> Path:
    """``path`` checked as :func:`~marl_amod.files.check_destination` does, with a suffix matplotlib
    can write (none: png), so a figure name such as ``map.txt`` fails before the evaluation it
    would show, not after it."""
    from matplotlib.backend_bases import FigureCanvasBase

    from marl_amod.errors import OutputError
    from marl_amod.files import check_destination

    path = check_destination(path, what=what)
    fmt = path.suffix.lstrip(".").lower()
    formats = FigureCanvasBase.get_supported_filetypes()
    if fmt and fmt not in formats:
        raise OutputError(f"{what} {path}: matplotlib cannot write .{fmt} figures; use one of {', '.join(sorted(formats))}")
    return path


def region_map_figure(
    results: Sequence[dict[str, Any]],
    city: City,
    rows: Sequence[str] = ("wait_time", "service_rate"),
    title: str | None = None,
) -> Any:
    """Per-region metrics of several evaluations on the city map: a row per metric, a column per
    policy, one colour scale per row (so colours compare across policies). A matplotlib Figure
    on an Agg canvas: it never opens a window."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.collections import PolyCollection
    from matplotlib.colors import Normalize
    from matplotlib.figure import Figure

    if not results:
        raise ValueError("region_map needs at least one evaluation result")
    for key in rows:
        if key not in results[0]["per_region"]:
            raise ValueError(f"no per-region metric {key!r}; known: {', '.join(results[0]['per_region'])}")
    cells, (x0, x1, y0, y1) = region_cells(city.positions)
    aspect = (y1 - y0) / max(x1 - x0, 1e-9)
    width = 3.0
    fig = Figure(figsize=(width * len(results) + 1.2, (width * aspect + 0.7) * len(rows) + 0.5), dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    axes = np.atleast_2d(fig.subplots(len(rows), len(results), squeeze=False))
    src, dst = city.edge_index
    pos = np.asarray(city.positions, dtype=float)
    for r, key in enumerate(rows):
        values = np.array([res["per_region"][key] for res in results], dtype=float)  # (P, N)
        label, cmap = ROW_STYLE.get(key, (key, "viridis"))
        norm = Normalize(vmin=0.0, vmax=max(float(values.max()), 1e-9) if key != "service_rate" else 1.0)
        for p, res in enumerate(results):
            ax = axes[r, p]
            coll = PolyCollection(cells, array=values[p], cmap=cmap, norm=norm, edgecolors="white", linewidths=0.8)
            ax.add_collection(coll)
            ax.plot(np.stack([pos[src, 0], pos[dst, 0]]), np.stack([pos[src, 1], pos[dst, 1]]), color="0.5", lw=0.4, alpha=0.5)
            ax.scatter(pos[:, 0], pos[:, 1], s=4, color="0.2")
            ax.set(xlim=(x0, x1), ylim=(y0, y1), xticks=[], yticks=[], aspect="equal")
            caption = _caption(res["metrics"], key)
            ax.set_title(f"{res['policy']}\n{caption}" if r == 0 else caption, fontsize=8)
        fig.colorbar(coll, ax=list(axes[r]), fraction=0.025, pad=0.02, label=label)
    if title:
        import textwrap

        inches = fig.get_figwidth()  # a one-panel map is narrow: wrap the title to it instead of cutting it at both edges
        fig.suptitle("\n".join(textwrap.wrap(title, max(30, int(inches * 14)))), fontsize=9)
    return fig


Score = tuple[str, float, float]  # (method, normalised score, its episode std)
SCORE_SCALE = "0 = equal distribution, 100 = MPC-Oracle; whisker: episode std"  # what a score axis says


def _anchor_lines(ax: Any, vertical: bool) -> None:
    """Dashed lines, named, at the score's anchors: 0 (equal distribution) and 100 (MPC-Oracle)."""
    for level, what in ((0.0, "equal distribution"), (100.0, "MPC-Oracle")):
        if vertical:
            ax.axvline(level, color="0.4", lw=0.8, ls="--", zorder=0)
            ax.text(level, 1.0, what, transform=ax.get_xaxis_transform(), ha="center", va="bottom", size=6, color="0.3")
        else:
            ax.axhline(level, color="0.4", lw=0.8, ls="--", zorder=0)
            ax.text(0.005, level, what, transform=ax.get_yaxis_transform(), va="bottom", size=6, color="0.3", zorder=5,
                    bbox={"facecolor": "white", "edgecolor": "none", "alpha": 0.8, "pad": 0.5})  # above the bars, readable


def _two_lines(name: str, longest: int = 14) -> str:
    """A long snake_case name broken at its middle-most underscore (``shenzhen_downtown`` / ``_west``)."""
    cuts = [i for i, c in enumerate(name) if c == "_"]
    if len(name) <= longest or not cuts:
        return name
    cut = min(cuts, key=lambda i: abs(i - len(name) / 2))
    return f"{name[:cut]}\n{name[cut:]}"


def score_bars(groups: dict[str, Sequence[Score]], path: str | Path, title: str | None = None) -> Path:
    """Write :func:`score_bars_figure` to ``path`` atomically (format from the suffix, png by default)."""
    path = figure_destination(path)  # a bad name fails before the drawing
    return save_figure(score_bars_figure(groups, title), path)


def score_bars_figure(groups: dict[str, Sequence[Score]], title: str | None = None) -> Any:
    """Grouped bars of normalised scores: a group per target (a city), a bar per method in the
    order first met, the episode std as a whisker, dashed lines at 0 (equal distribution) and 100
    (MPC-Oracle), each bar labelled with its score. A matplotlib Figure on an Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not groups or not any(groups.values()):
        raise ValueError("score_bars needs at least one target with a scored method")
    methods = list(dict.fromkeys(name for rows in groups.values() for name, _, _ in rows))
    colours = {m: f"C{i % 10}" for i, m in enumerate(methods)}
    width = 0.8 / len(methods)
    ticks = [_two_lines(str(g)) for g in groups]  # long target names on two lines, and room for the longest
    bars = 1.6 + 0.45 * len(methods) * len(groups) + 0.5 * len(groups)
    names = 2.8 + 0.095 * len(groups) * max(len(line) for t in ticks for line in t.split("\n"))  # so the names never run together
    size = (max(5.5, bars, names), 3.6)
    fig = Figure(figsize=size, dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    labelled: set[str] = set()
    for g, rows in enumerate(groups.values()):
        for name, value, std in rows:
            x = g - 0.4 + width * (methods.index(name) + 0.5)
            ax.bar(x, value, width, yerr=std, color=colours[name], capsize=2, error_kw={"lw": 0.8},
                   label=None if name in labelled else name)  # fmt: skip
            labelled.add(name)
            tip = value + std if value >= 0 else value - std  # the label clears the whisker
            offset = (0, 2 if value >= 0 else -8)
            ax.annotate(f"{round(value)}", (x, tip), xytext=offset, textcoords="offset points", ha="center", size=6)
    _anchor_lines(ax, vertical=False)
    ax.set_xticks(range(len(groups)), ticks)
    ax.set_ylabel(f"normalised score\n({SCORE_SCALE})", fontsize=7)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.0, 0.9), frameon=False)
    if title:
        ax.set_title(title, fontsize=9)
    return fig


def score_ranking(rows: Sequence[tuple[str, float, float, str]], path: str | Path, title: str | None = None) -> Path:
    """Write :func:`score_ranking_figure` to ``path`` atomically (format from the suffix, png by default)."""
    path = figure_destination(path)  # a bad name fails before the drawing
    return save_figure(score_ranking_figure(rows, title), path)


def score_ranking_figure(rows: Sequence[tuple[str, float, float, str]], title: str | None = None) -> Any:
    """Policies of one table, (label, normalised score, episode std in score points, kind), as
    horizontal bars from the best at the top to the worst, coloured by kind (e.g. baseline,
    trained), with the episode std as a whisker and dashed lines at 0 and 100. A matplotlib
    Figure on an Agg canvas."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    if not rows:
        raise ValueError("score_ranking needs at least one scored policy")
    ranked = sorted(rows, key=lambda r: r[1])  # barh draws the first at the bottom
    kinds = list(dict.fromkeys(r[3] for r in rows))
    colours = {k: f"C{i % 10}" for i, k in enumerate(kinds)}
    fig = Figure(figsize=(7.5, 0.8 + 0.28 * len(rows)), dpi=120, layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.subplots()
    labelled: set[str] = set()
    for y, (_, value, std, kind) in enumerate(ranked):
        legend = None if kind in labelled else kind
        ax.barh(y, value, xerr=std, color=colours[kind], capsize=2, error_kw={"lw": 0.8}, label=legend)
        labelled.add(kind)
        tip = value + std if value >= 0 else value - std  # the label clears the whisker
        ax.annotate(f"{round(value)}", (tip, y), xytext=(3 if value >= 0 else -3, 0), textcoords="offset points",
                    ha="left" if value >= 0 else "right", va="center", size=6)  # fmt: skip
    _anchor_lines(ax, vertical=True)
    ax.set_yticks(range(len(ranked)), [r[0] for r in ranked], fontsize=7)
    ax.set_xlabel(f"normalised score ({SCORE_SCALE})", fontsize=8)
    ax.legend(fontsize=7, loc="lower right")
    if title:
        ax.set_title(title, fontsize=9, pad=12)
    return fig
