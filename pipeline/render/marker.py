"""The unicycle's heading marker (SPEC §1): an isosceles triangle whose area centroid is the vehicle's position,
drawn with its exact area coverage of each pixel (Green's theorem, column by column, batched over images)."""

from __future__ import annotations

import numpy as np

_MARKER = np.array([[4.0 / 3.0, 0.0], [-2.0 / 3.0, 0.5], [-2.0 / 3.0, -0.5]])
MARKER_REACH = 4.0 / 3.0  # farthest vertex from the centroid, in units of L


def heading_marker(uv, heading, size: float) -> np.ndarray:
    """Vertices `(N, 3, 2)` in pixel coordinates `(u, v)` of the unicycle marker (apex first).

    `uv (N, 2)`: the vehicle's position in pixels; `heading (N,)`: world-frame angle (radians, from +x
    towards +y); `size`: L = robot_size in pixels. Apex `4/3 L` ahead, base `2/3 L` behind, base width `L`.
    The image's row axis points down (-y), so the world direction `(cos t, sin t)` is `(cos t, -sin t)` in
    `(u, v)`.
    """
    uv = np.asarray(uv, dtype=np.float64).reshape(-1, 2)
    t = np.asarray(heading, dtype=np.float64).reshape(-1)
    c, s = np.cos(t)[:, None], np.sin(t)[:, None]
    ax, ay = _MARKER[None, :, 0] * size, _MARKER[None, :, 1] * size  # (1, 3) vehicle frame
    # world rotation (x', y') = R(t) (ax, ay); pixels: u = u0 + x', v = v0 - y'
    du = c * ax - s * ay
    dv = -(s * ax + c * ay)
    return np.stack([uv[:, 0, None] + du, uv[:, 1, None] + dv], axis=-1)


def _ramp_integral(t: np.ndarray) -> np.ndarray:
    """Antiderivative of clip(t, 0, 1): 0 for t <= 0, t^2/2 on [0, 1], t - 1/2 for t >= 1."""
    tc = np.clip(t, 0.0, 1.0)
    return 0.5 * tc * tc + np.maximum(t - 1.0, 0.0)


def polygon_coverage(verts: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Exact area of each polygon inside each pixel of its window: `(N, k, k)` in [0, 1].

    `verts (N, m, 2)`: simple polygons in pixel coordinates `(u, v)` (either orientation); `rows (N, k)`,
    `cols (N, k)`: the integer pixel indices of each window. Green's theorem column by column: for every
    edge, the integral over the pixel's `u`-range (clipped to the edge's) of the clipped height
    `clip(v_edge(u) - r, 0, 1)`, signed by the edge's `u`-direction; summed over the edges this is the
    length of the polygon's vertical section inside `[r, r + 1]` integrated over `u`, i.e. the area.
    """
    a = verts
    b = np.roll(verts, -1, axis=1)
    ua, va, ub, vb = a[..., 0], a[..., 1], b[..., 0], b[..., 1]  # (N, m)
    lo, hi = np.minimum(ua, ub), np.maximum(ua, ub)
    sign = np.sign(ub - ua)  # 0 for vertical edges (they bound no u-range)
    du = np.where(ub != ua, ub - ua, 1.0)
    c = cols[:, None, :].astype(np.float64)  # (N, 1, k)
    x0 = np.maximum(c, lo[..., None])  # (N, m, k): the part of [c, c+1] under the edge
    x1 = np.minimum(c + 1.0, hi[..., None])
    width = np.maximum(x1 - x0, 0.0)

    def v_at(x):  # the edge's v at x (interpolated, clipped to the edge so near-vertical edges stay tame)
        t = np.clip((x - ua[..., None]) / du[..., None], 0.0, 1.0)
        return va[..., None] + t * (vb - va)[..., None]

    r = rows[:, None, :, None].astype(np.float64)  # (N, 1, k, 1)
    g0 = v_at(x0)[:, :, None, :] - r  # (N, m, k, k): height above the row's top at both ends
    g1 = v_at(x1)[:, :, None, :] - r
    dg = g1 - g0
    flat = np.abs(dg) < 1e-9
    mean_h = np.clip(0.5 * (g0 + g1), 0.0, 1.0)
    slope_part = (_ramp_integral(g1) - _ramp_integral(g0)) / np.where(flat, 1.0, dg)
    part = np.where(flat, mean_h, slope_part) * width[:, :, None, :]
    area = np.einsum("nm,nmij->nij", sign, part)
    # orientation: the sum is -(shoelace signed area) restricted to the pixel, so its sign fixes the overall one
    orient = -np.sign(np.sum(ua * vb - ub * va, axis=1))
    return np.clip(area * orient[:, None, None], 0.0, 1.0)
