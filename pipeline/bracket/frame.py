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

from pipeline.bracket.enclosures import DIRS
from pipeline.control import CBFController, HybridController, Scene, SmoothController

VIEW_TOL = 1e-9  # world units: a corner this far outside the arena counts as on its edge


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
        tol = VIEW_TOL
        return ((W[..., 0] >= x0 - tol) & (W[..., 0] <= x1 + tol) & (W[..., 1] >= y0 - tol)
                & (W[..., 1] <= y1 + tol)).all(axis=1)

    def view_bounds(self, arena) -> np.ndarray | None:
        """The world arena in the grid frame as bounds on the support directions: `(J,)` with the arena's offset in
        its four outward normals and `+inf` elsewhere (`{g: DIRS g <= H}` is the rotated arena), or None when a
        normal is not one of `DIRS` (an angle not a multiple of `360° / J`: cells then count only wholly inside)."""
        (x0, x1), (y0, y1) = arena
        H = np.full(len(DIRS), np.inf)
        for n_world, offset in (((1.0, 0.0), x1), ((-1.0, 0.0), -x0), ((0.0, 1.0), y1), ((0.0, -1.0), -y0)):
            n = self.to_grid(np.array(n_world))
            j = int(np.argmax(DIRS @ n))
            if not np.allclose(DIRS[j], n, rtol=0.0, atol=1e-12):
                return None
            H[j] = float(offset)
        return H

    def meets_view(self, boxes: np.ndarray, arena) -> np.ndarray:
        """Grid cells `(N, 4)` whose interior meets the world arena's (no separating axis among the cell's and the
        arena's edge normals): a run can be in them, on their part inside the arena."""
        (x0, x1), (y0, y1) = arena
        A = self.to_grid(np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], float))  # (4, 2)
        C = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], axis=1)  # (N, 4, 2)
        normals = np.vstack([np.eye(2), self.to_grid(np.eye(2))])  # the cells' and the arena's edge normals
        pc, pa = C @ normals.T, A @ normals.T  # (N, 4, 4), (4, 4)
        return ((pc.min(axis=1) < pa.max(axis=0) - VIEW_TOL) & (pa.min(axis=0) < pc.max(axis=1) - VIEW_TOL)).all(axis=1)
