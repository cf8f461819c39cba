"""Tables and the switching-set figure of `make learned` (docs/learned.md)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd
import torch

from pipeline.sweep import markdown

COLUMNS = ["agent", "condition", "n", "reached", "reached_ci", "collided", "collided_ci", "stalled", "stalled_ci",
           "left_view", "timed_out", "median_time_s", "induced_along", "induced_norm"]


def write_tables(df: pd.DataFrame, folder: Path) -> None:
    df.to_csv(folder / "tab_learned.csv", index=False)
    show = df[COLUMNS].copy()
    for c in ("reached", "collided", "stalled", "left_view", "timed_out"):
        show[c] = (100 * show[c]).map(lambda v: f"{v:.0f}%")
    for c in ("median_time_s", "induced_along", "induced_norm"):
        show[c] = show[c].map(lambda v: "" if not np.isfinite(v) else f"{v:.3g}")
    (folder / "tab_learned.md").write_text(markdown(show))


def switching_values(obj, model, grid) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`e_b · π(h(p))` of the imitated policy (head 0) at the grid's positions `(ny, nx)`, and the grid."""
    (x0, x1), (y0, y1) = obj.scene.bounds
    xs, ys = np.linspace(x0 + 1, x1 - 1, grid[0]), np.linspace(y0 + 1, y1 - 1, grid[1])
    X, Y = np.meshgrid(xs, ys)
    p = np.column_stack([X.ravel(), Y.ravel()])
    out = []
    for s in range(0, len(p), 1024):
        imgs = obj.camera.render(p[s:s + 1024])
        out.append(model.act(torch.from_numpy(imgs), 0).double().numpy())
    u = np.concatenate(out)
    return X, Y, (u @ np.asarray(obj.scene.e_b, float)).reshape(X.shape)


def switching_figure(obj, model, path: Path, grid) -> None:
    """Where the imitated policy steers to each side of the obstacle's axis (sign of `e_b · π(h(p))`): the
    boundary between the colours behind the obstacle is the policy's own set `K` (Proposition 1)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    X, Y, v = switching_values(obj, model, grid)
    fig, ax = plt.subplots(figsize=(8, 5))
    lim = np.nanmax(np.abs(v)) or 1.0
    im = ax.pcolormesh(X, Y, v, cmap="coolwarm", vmin=-lim, vmax=lim, shading="auto")
    ax.contour(X, Y, v, levels=[0.0], colors="k", linewidths=1.0)
    for c, r in zip(obj.scene.arrays["center"], obj.scene.arrays["radius"]):
        ax.add_patch(plt.Circle(c, r, color="0.2"))
    ax.plot(*obj.scene.p_T, marker="*", color="gold", ms=14, mec="k")
    ax.set_aspect("equal")
    ax.set_title("imitated policy: e_b · π(h(p)) (black: its switching set)")
    fig.colorbar(im, ax=ax, label="velocity across the obstacle's axis (units/s)")
    fig.savefig(path, dpi=120, bbox_inches="tight")
    plt.close(fig)
