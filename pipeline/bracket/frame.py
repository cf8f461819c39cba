"""Cells aligned with the diamond's faces (SPEC §5.4: "cells aligned with the wedge faces"): the abstraction runs
in a frame rotated by `angle` about the world origin, on the rotated scene with the same law.

The laws are equivariant under rotations (the attraction, the wedges' frame, the barriers, saturation, the
guard and the CBF constraint are all built from distances and the obstacle frame), so the rotated law's input
at the rotated point is the rotated input. At 45° (the default scene's axis along `x`) the four faces of the
diamond, and both faces of each wedge, are grid lines: a push-out (along a face's normal) never moves a run
along the face, and a run sliding down a face cannot climb back up it in the abstraction.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.control import CBFController, HybridController, Scene, SmoothController


def rotation(angle_deg: float) -> np.ndarray:
    t = math.radians(angle_deg)
    return np.array([[math.cos(t), -math.sin(t)], [math.sin(t), math.cos(t)]])


class Frame:
    """World <-> grid frame: `g = R(-angle) w`."""

    def __init__(self, angle_deg: float = 0.0):
        self.angle = float(angle_deg)
        self.R = rotation(self.angle)  # grid -> world

    def to_grid(self, w: np.ndarray) -> np.ndarray:
        return np.asarray(w, float) @ self.R  # R^T w per row

    def to_world(self, g: np.ndarray) -> np.ndarray:
        return np.asarray(g, float) @ self.R.T

    def scene(self, scene: Scene) -> Scene:
        """The scene in the grid frame (its arena: the bounding box of the rotated arena)."""
        (x0, x1), (y0, y1) = scene.bounds
        corners = self.to_grid(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]]))
        lo, hi = corners.min(0), corners.max(0)
        obs = [{"center": self.to_grid(np.array(o.center, float)).tolist(), "radius": o.radius, "apex": o.apex,
                "barrier_scale": o.barrier_scale} for o in scene.obstacles]
        return Scene(target=self.to_grid(scene.p_T).tolist(), obstacles=obs, barrier=scene.barrier,
                     arena={"x": [float(lo[0]), float(hi[0])], "y": [float(lo[1]), float(hi[1])]},
                     name=f"{scene.name}@{self.angle:g}")

    def law(self, law):
        """The same law (same parameters) on the rotated scene."""
        scene = self.scene(law.scene)
        common = {"k": law.k, "u_max": law.u_max, "push_speed": law.push_speed}
        if isinstance(law, HybridController):
            return HybridController(scene, chi=law.chi, lam=law.lam, cell_hysteresis=law.h, guard=law.guard,
                                    guard_gamma=law.gamma, **common)
        if isinstance(law, CBFController):
            return CBFController(scene, alpha=law.alpha, **common)
        if isinstance(law, SmoothController):
            return SmoothController(scene, **common)
        raise ValueError(f"no rotated {type(law).__name__}")

    def in_view(self, boxes: np.ndarray, arena) -> np.ndarray:
        """Grid cells `(N, 4)` lying inside the world arena (every corner rotated back is in the rectangle)."""
        (x0, x1), (y0, y1) = arena
        C = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], axis=1)
        W = self.to_world(C.reshape(-1, 2)).reshape(-1, 4, 2)
        tol = 1e-9
        return ((W[..., 0] >= x0 - tol) & (W[..., 0] <= x1 + tol) & (W[..., 1] >= y0 - tol)
                & (W[..., 1] <= y1 + tol)).all(axis=1)
