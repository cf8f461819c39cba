"""The covering O_1, O_2 of SPEC §3.1 (the paper's Eq. for L_1a ... L_2b, sign typos fixed).

`O_q = R^2 \\ W_q` with the closed convex 90-degree wedges

    W_1 = {b >= |a| - c}   (O_1: pass with b < 0),     W_2 = {b <= c - |a|}   (O_2: pass with b > 0),

and `W_1 ∩ W_2` is the diamond `|a| + |b| <= c`. In the rotated coordinates
`u = (b' + a)/sqrt(2)`, `v = (b' - a)/sqrt(2)` with `b' = c + b` (q = 1) or `b' = c - b` (q = 2), each
wedge is the quadrant `{u >= 0, v >= 0}`, so the projection onto it (faces and apex) is a clip and the
squared distance is `min(u, 0)^2 + min(v, 0)^2`, which is C^1 outside the wedge.
"""

from __future__ import annotations

import numpy as np

from pipeline.control.scene import Covering

SQRT1_2 = float(np.sqrt(0.5))  # the diamond's faces are at 45 degrees: every module takes it from here


def _check_q(q: int) -> int:
    if q not in (1, 2):
        raise ValueError(f"mode q must be 1 or 2, got {q!r}")
    return 1 if q == 1 else -1  # sign of b in b'


def wedge_coords(scene: Covering, q: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rotated coordinates `(u, v)` in which `W_q = {u >= 0, v >= 0}`."""
    sigma = _check_q(q)
    a, b = scene.to_frame(points)
    bp = scene.c + sigma * b
    return (bp + a) * SQRT1_2, (bp - a) * SQRT1_2


def wedge_axes(scene: Covering, q: int) -> tuple[np.ndarray, np.ndarray]:
    """World-frame gradients of `u` and `v` (unit vectors): du/dp, dv/dp."""
    sigma = _check_q(q)
    return (sigma * scene.e_b + scene.e_a) * SQRT1_2, (sigma * scene.e_b - scene.e_a) * SQRT1_2


def sq_dist_to_wedge(scene: Covering, q: int, points: np.ndarray) -> np.ndarray:
    """`d_q(p)`: squared distance from `p` to `W_q` (zero inside), i.e. to the complement of `O_q`."""
    u, v = wedge_coords(scene, q, points)
    return np.minimum(u, 0.0) ** 2 + np.minimum(v, 0.0) ** 2


def sq_dist_to_wedge_grad(scene: Covering, q: int, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """`(d_q, ∇d_q)`, shapes `(N,)` and `(N, 2)`; the gradient is zero inside `W_q`."""
    u, v = wedge_coords(scene, q, points)
    du, dv = wedge_axes(scene, q)
    mu, mv = np.minimum(u, 0.0), np.minimum(v, 0.0)
    grad = 2.0 * (np.multiply.outer(mu, du) + np.multiply.outer(mv, dv))
    return mu * mu + mv * mv, grad


def in_covering_set(scene: Covering, q: int, points: np.ndarray) -> np.ndarray:
    """Membership in the open set `O_q` (boolean `(N,)`)."""
    u, v = wedge_coords(scene, q, points)
    return (u < 0) | (v < 0)


def in_diamond(scene, points: np.ndarray) -> np.ndarray:
    """Membership in the diamond `W_1 ∩ W_2 = {|a| + |b| <= c}` = complement of `O_1 ∪ O_2` (of a covering; for a
    scene, of any of its obstacles)."""
    inside = np.zeros(len(points), dtype=bool)
    for cov in (scene.coverings if hasattr(scene, "coverings") else [scene]):
        a, b = cov.to_frame(points)
        inside |= np.abs(a) + np.abs(b) <= cov.c
    return inside


def diamond_vertices(scene: Covering) -> np.ndarray:
    """The diamond's four corners in world coordinates, `(4, 2)`, counter-clockwise."""
    c = scene.c
    return scene.from_frame(np.array([c, 0.0, -c, 0.0]), np.array([0.0, c, 0.0, -c]))
