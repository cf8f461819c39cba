"""Shared drawing helpers: the scene (arena, obstacle, diamond, target) on a matplotlib axis."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.animation import PillowWriter  # noqa: E402
from matplotlib.patches import Circle, Polygon  # noqa: E402

from pipeline.control import Scene, diamond_vertices  # noqa: E402


def draw_scene(ax, scene: Scene, arena=None, *, diamond: bool = True, margin_disc: bool = False):
    """Every obstacle N_i (grey) with its diamond W_1 ∩ W_2 (dashed), the target (star), the arena's bounds
    (default: the scene's)."""
    for i, cov in enumerate(scene.coverings):
        ax.add_patch(Circle(cov.p_0, cov.obstacle_radius, color="0.35", zorder=3,
                            label="obstacle $N$" if i == 0 else None))
        if margin_disc:
            ax.add_patch(Circle(cov.p_0, 2 * cov.obstacle_radius, fill=False, ls=":", color="0.4", zorder=3))
        if diamond:
            ax.add_patch(Polygon(diamond_vertices(cov), closed=True, fill=False, ls="--", color="k", lw=1, zorder=3,
                                 label=r"diamond $W_1 \cap W_2$" if i == 0 else None))
    ax.plot(*scene.p_T, marker="*", ms=14, color="gold", mec="k", zorder=5, ls="none", label="target")
    (x0, x1), (y0, y1) = arena or scene.bounds
    ax.set_xlim(x0, x1)
    ax.set_ylim(y0, y1)
    ax.set_aspect("equal")
    ax.set_xlabel("x")
    ax.set_ylabel("y")
    return ax


def legend_outside(ax, handles=None, labels=None, *, below: bool = False, **kw):
    """A legend beside the axes (right; `below`: under the x label), never over the data it keys."""
    where = dict(loc="upper center", bbox_to_anchor=(0.5, -0.2 if ax.get_xlabel() else -0.1),
                 ncol=kw.pop("ncol", 3)) if below else \
        dict(loc="upper left", bbox_to_anchor=(1.01, 1.0))
    args = () if handles is None else (handles, labels if labels is not None else [h.get_label() for h in handles])
    return ax.legend(*args, fontsize=kw.pop("fontsize", 7), borderaxespad=0.0, **where, **kw)


def save(fig, path_stem, formats=("png",), dpi=150) -> list[str]:
    """Save a figure as `<stem>.<fmt>` for each format; returns the paths."""
    out = []
    for fmt in formats:
        path = f"{path_stem}.{fmt}"
        fig.savefig(path, dpi=dpi, bbox_inches="tight")
        out.append(path)
    plt.close(fig)
    return out


def save_gif(fig, update, frames: int, path, *, fps: int, dpi: float) -> Path:
    """An animated GIF of `frames` frames, `update(j)` setting the artists of frame `j`, and the figure closed: the
    bytes `FuncAnimation(fig, update, frames, blit=False).save(path, PillowWriter(fps), dpi)` writes, each frame drawn
    once (that draws each twice: for the animation, then for the writer) and `update(0)` not called ahead of time."""
    writer = PillowWriter(fps=fps)
    with writer.saving(fig, str(path), dpi):
        for j in range(frames):
            update(j)
            writer.grab_frame()
    plt.close(fig)
    return Path(path)


def trajectory_figure(scene: Scene, p: np.ndarray, success: np.ndarray | None = None, title: str = "", arena=None):
    """Trajectories `(T, N, 2)` over the scene, each start a black dot; failures in red; the legend beside it."""
    fig, ax = plt.subplots(figsize=(9, 5))
    draw_scene(ax, scene, arena)
    n = p.shape[1]
    seen = set()
    for i in range(n):
        ok = True if success is None else bool(success[i])
        label = ("reached the target" if success is not None else "trajectory") if ok else "failed"
        ax.plot(p[:, i, 0], p[:, i, 1], lw=0.8 if n > 20 else 1.5, color="tab:blue" if ok else "tab:red", alpha=0.8,
                label=None if label in seen else label)
        seen.add(label)
    ax.plot(p[0, :, 0], p[0, :, 1], "o", ms=3, color="k", ls="none", label="start")
    legend_outside(ax)
    ax.set_title(title)
    return fig
