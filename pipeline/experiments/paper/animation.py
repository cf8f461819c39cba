"""Animated GIFs of the leader-follower scenarios (noise/failure, occlusion): matplotlib + Pillow only.

Left: the arena with both vehicles, their trails and the leader as the follower perceives it. Right: the
frame the follower's camera sees (with its clouds) and the perceived leader on it.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.control import Scene  # noqa: E402
from pipeline.viz import draw_scene, save_gif  # noqa: E402

Frames = np.ndarray | Callable[[int], np.ndarray]  # (T, H, W, 3) uint8, or k -> (H, W, 3) uint8


def frame_indices(n: int, max_frames: int) -> np.ndarray:
    """At most `max_frames` evenly spaced indices into `n` samples, first and last included."""
    if n < 1 or max_frames < 1:
        raise ValueError(f"need n >= 1 and max_frames >= 1, got n={n}, max_frames={max_frames}")
    return np.unique(np.linspace(0, n - 1, min(n, max_frames)).round().astype(int))


def leader_follower_gif(path, scene: Scene, arena, t: np.ndarray, lead_p: np.ndarray, foll_p: np.ndarray,
                        perceived: np.ndarray, frames: Frames, *, fps: int = 10, max_frames: int = 60,
                        title: str = "", dpi: int = 80) -> Path:
    """Write an animated GIF to `path` and return it.

    `t` `(T,)`; `lead_p`, `foll_p`, `perceived` `(T, 2)` world positions (the leader, the follower, the leader
    as the follower's camera + perception map see it, NaN where no estimate); `frames`: the follower's camera
    images `(T, H, W, 3)` uint8 or a function `k -> image` (rendered only for the frames drawn). The run is
    subsampled to at most `max_frames` frames so that a GIF takes seconds to write.
    """
    t = np.asarray(t, dtype=float)
    lead_p, foll_p, perceived = (np.asarray(a, dtype=float) for a in (lead_p, foll_p, perceived))
    n = len(t)
    for name, arr in (("lead_p", lead_p), ("foll_p", foll_p), ("perceived", perceived)):
        if arr.shape != (n, 2):
            raise ValueError(f"{name} must have shape ({n}, 2), got {arr.shape}")
    image = frames if callable(frames) else (lambda k: np.asarray(frames)[k])
    idx = frame_indices(n, max_frames)
    (x0, x1), (y0, y1) = arena

    fig, (ax, cam) = plt.subplots(1, 2, figsize=(10, 3.6), gridspec_kw={"width_ratios": [1, 1]})
    draw_scene(ax, scene, arena)
    lead_trail, = ax.plot([], [], "-", color="0.5", lw=1.2, label="leader")
    foll_trail, = ax.plot([], [], "-", color="tab:green", lw=1.2, label="follower")
    lead_dot, = ax.plot([], [], "s", ms=7, mfc="white", mec="k", zorder=6)
    foll_dot, = ax.plot([], [], "s", ms=7, color="tab:green", mec="k", zorder=6)
    seen_dot, = ax.plot([], [], "x", ms=8, mew=2, color="tab:red", zorder=7, label="perceived leader")
    ax.legend(loc="lower left", fontsize=7, framealpha=0.8)
    first = np.asarray(image(idx[0]))
    im = cam.imshow(first, extent=(x0, x1, y0, y1), origin="upper", interpolation="nearest")
    cam_seen, = cam.plot([], [], "x", ms=9, mew=2, color="tab:red")
    cam.set_xlim(x0, x1)
    cam.set_ylim(y0, y1)
    cam.set_title("follower's camera", fontsize=9)
    cam.set_xticks([])
    cam.set_yticks([])
    head = fig.suptitle(title, fontsize=10)

    def update(j):
        k = idx[j]
        lead_trail.set_data(lead_p[: k + 1, 0], lead_p[: k + 1, 1])
        foll_trail.set_data(foll_p[: k + 1, 0], foll_p[: k + 1, 1])
        lead_dot.set_data([lead_p[k, 0]], [lead_p[k, 1]])
        foll_dot.set_data([foll_p[k, 0]], [foll_p[k, 1]])
        seen_dot.set_data([perceived[k, 0]], [perceived[k, 1]])
        cam_seen.set_data([perceived[k, 0]], [perceived[k, 1]])
        im.set_data(np.asarray(image(k)))
        head.set_text(f"{title}  t = {t[k]:.2f} s".strip())
        return lead_trail, foll_trail, lead_dot, foll_dot, seen_dot, cam_seen, im, head

    return save_gif(fig, update, len(idx), path, fps=fps, dpi=dpi)
