"""Drawing the fleet: a map of regions with idle vehicles, open demand and rebalancing flows.

Kept apart from the env logic; matplotlib is imported only when something is drawn. Regions sit
at ``city.positions``; a node's area and colour grow with its idle vehicles, a grey ring around
it with the open (unserved) requests, and each rebalancing flow i -> j of the last step is an
arrow whose width grows with the number of vehicles.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from marl_amod.system import FleetSystem

FIGSIZE = (6.0, 5.0)
DPI = 80
MAX_ARROWS = 200


def _figure(size: tuple[float, float] = FIGSIZE) -> Any:
    """A figure that never opens a window (object-oriented Agg canvas)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=DPI)
    FigureCanvasAgg(fig)
    return fig


def draw(ax: Any, system: FleetSystem, rebalance: np.ndarray | None = None, step_reward: float | None = None) -> None:
    """Draw the state of ``system`` on a matplotlib axis; ``rebalance`` (N, N) are the last flows."""
    city, sim = system.city, system.sim
    pos = np.asarray(city.positions, dtype=float)
    idle = sim.idle.astype(float)
    open_requests = sim.requests().sum(axis=1).astype(float)
    scale = max(float(np.max(idle, initial=0.0)), float(np.max(open_requests, initial=0.0)), 1.0)
    src, dst = city.edge_index
    ax.plot(np.stack([pos[src, 0], pos[dst, 0]]), np.stack([pos[src, 1], pos[dst, 1]]), color="0.88", lw=0.8, zorder=0)
    ax.scatter(pos[:, 0], pos[:, 1], s=60 + 900 * open_requests / scale, facecolors="none", edgecolors="0.45",
               linewidths=1.2, zorder=1, label="open requests")
    nodes = ax.scatter(pos[:, 0], pos[:, 1], s=30 + 600 * idle / scale, c=idle, cmap="viridis",
                       vmin=0, vmax=scale, zorder=2, label="idle vehicles")
    if rebalance is not None and np.any(rebalance > 0):
        i, j = np.nonzero(rebalance)
        flow = rebalance[i, j].astype(float)
        keep = np.argsort(-flow)[:MAX_ARROWS]  # the largest flows; a huge city stays readable
        for a, b, f in zip(i[keep], j[keep], flow[keep], strict=True):
            ax.annotate("", xy=pos[b], xytext=pos[a], zorder=3,
                        arrowprops={"arrowstyle": "-|>", "color": "tab:red", "alpha": 0.75, "shrinkA": 6, "shrinkB": 6,
                                    "lw": 0.8 + 3.0 * f / flow.max(), "connectionstyle": "arc3,rad=0.15"})
    if city.n_regions <= 30:
        for k, (x, y) in enumerate(pos):
            ax.annotate(str(int(idle[k])), (x, y), ha="center", va="center", fontsize=7, color="white", zorder=4)
    ax.figure.colorbar(nodes, ax=ax, fraction=0.046, pad=0.04, label="idle vehicles")
    hour = (city.start_hour + sim.t * city.tstep / 60.0) % 24
    title = f"{city.name}  step {sim.t}/{city.horizon - 1}  {int(hour):02d}:{int(round(hour % 1 * 60)) % 60:02d}"
    served = float(sim.totals.served.sum())
    subtitle = f"served {served:.0f}  profit {float(sim.totals.profit.sum()):.0f}"
    if step_reward is not None:
        subtitle += f"  step reward {step_reward:.1f}"
    ax.set_title(f"{title}\n{subtitle}  (red: rebalancing, ring: open requests)", fontsize=8)
    ax.set_aspect("equal", adjustable="datalim")
    ax.margins(0.12)
    ax.set_xticks([])
    ax.set_yticks([])


def render_rgb(system: FleetSystem, rebalance: np.ndarray | None = None, step_reward: float | None = None) -> np.ndarray:
    """(H, W, 3) uint8 image of the current state."""
    fig = _figure()
    ax = fig.add_subplot(1, 1, 1)
    draw(ax, system, rebalance, step_reward)
    fig.tight_layout()
    fig.canvas.draw()
    image = np.asarray(fig.canvas.buffer_rgba())[..., :3].copy()
    return image


class HumanViewer:
    """A pyplot window updated in place; falls back to drawing off-screen when no display exists."""

    def __init__(self) -> None:
        self._fig: Any = None

    def show(self, system: FleetSystem, rebalance: np.ndarray | None = None, step_reward: float | None = None) -> None:
        import matplotlib.pyplot as plt

        if self._fig is None or not plt.fignum_exists(self._fig.number):
            self._fig = plt.figure(figsize=FIGSIZE, dpi=DPI)
        self._fig.clf()
        draw(self._fig.add_subplot(1, 1, 1), system, rebalance, step_reward)
        self._fig.tight_layout()
        if "agg" not in plt.get_backend().lower():
            plt.pause(0.001)  # let an interactive backend paint the window
        else:
            self._fig.canvas.draw()

    def close(self) -> None:
        if self._fig is not None:
            import matplotlib.pyplot as plt

            plt.close(self._fig)
            self._fig = None


def write_episode_gif(frames: Sequence[np.ndarray], path: str | Path, fps: float = 4.0) -> Path:
    """Write rgb frames (H, W, 3) as an animated GIF (or MP4 if the suffix says so and ffmpeg exists)."""
    import imageio.v2 as imageio

    if not frames:
        raise ValueError("no frames to write")
    path = Path(path)
    if path.suffix.lower() == ".gif":
        imageio.mimsave(path, list(frames), duration=1000.0 / fps, loop=0)
    else:
        imageio.mimsave(path, list(frames), fps=fps)
    return path


def record_episode(
    env: Any, policy: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]] | None = None, *, seed: int | None = None,
    path: str | Path | None = None, fps: float = 4.0,
) -> list[np.ndarray]:
    """Roll out ``policy`` (observations -> actions; random if None) on an rgb_array env; optionally write a GIF."""
    from pettingzoo import ParallelEnv

    if getattr(env, "render_mode", None) != "rgb_array":
        raise ValueError("record_episode needs an env made with render_mode='rgb_array'")
    if not isinstance(env, ParallelEnv):
        raise ValueError("record_episode plays a ParallelEnv (all agents act at once), not the AEC env: use marl_amod.parallel_env(...)")
    obs, _ = env.reset(seed=seed)
    frames = [env.render()]
    while env.agents:
        actions = policy(obs) if policy is not None else {a: env.action_space(a).sample() for a in env.agents}
        obs, *_ = env.step(actions)
        frames.append(env.render())
    if path is not None:
        write_episode_gif(frames, path, fps)
    return frames
