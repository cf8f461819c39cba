"""Sound input enclosures `U(M, q)` (SPEC §5.4): every velocity a law can hold for one frame when it perceives a
point of the box `M`, as support values `h_j = max_{u in U} d_j·u` in `J` directions `d_j` (a polytope).

Interval arithmetic on each law's closed form over sub-boxes of `M` (no sampling, no Lipschitz constant):

- the attraction `-2k (m - p_T)` is a box;
- the hybrid law's barrier term is `g(D) (μ d_u + ν d_v)` (`μ = min(u, 0)`, `ν = min(v, 0)` the wedge coordinates
  of SPEC §3.1, `D = μ² + ν²`, `g = -2k B'(D/ℓ²)/ℓ² >= 0` decreasing in `D` since `B'` increases): a box in the
  wedge's axes; unbounded where `M` touches the wedge (`g(0) = ∞`);
- the smooth law's barrier term and the CBF filter's correction are `ρ e(α)` with `ρ` in an interval and `α` in
  the arc `M` spans seen from the obstacle's centre: a sector, enclosed in a pentagon;
- saturation at `u_max` is a radial projection: `sat(U) ⊂ (U ∩ B) ∪ u_max·arc(cone U)`;
- the guard (SPEC §3.3) adds `β n` with `0 <= β <= u_max - (1 - γ) s/T_s` and `n` the wedge's outward normals;
- the push-out (perceived point in the active wedge, SPEC §3.3) is one of the two face normals at `push_speed`.

The pre-saturation set of a sub-box is the hull of a point set `X` (unbounded directions carried by points at
distance `BIG` together with the pure recession directions, so that their cone is exact). Laws: the single
obstacle of the default scene, barrier kind `squared`.
"""

from __future__ import annotations

import math

import numpy as np

BIG = 1e9
J = 32  # directions of the support function (multiples of 11.25°: the world axes and the diagonals among them)


def directions(n: int = J) -> np.ndarray:
    ang = 2.0 * np.pi * np.arange(n) / n
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


DIRS = directions()


def wrap(angle: np.ndarray) -> np.ndarray:
    """Angles wrapped into `[-π, π)` (what `np.angle(np.exp(1j x))` computes, without complex exponentials)."""
    return np.remainder(np.asarray(angle) + np.pi, 2.0 * np.pi) - np.pi


def support_at(h: np.ndarray, x: np.ndarray) -> np.ndarray:
    """An upper bound `(...)` of `max_u x·u` over the polytope `{d_j·u <= h_j}` (`h` `(..., J)`) at vectors `x`
    `(..., 2)` (broadcast against `h`'s rows): `x = α d_j + β d_{j+1}` with `α, β >= 0` (the directions around `x`),
    and a support function is sublinear. A zero coefficient ignores its `h` (which may be infinite)."""
    x = np.asarray(x, float)
    ang = np.mod(np.arctan2(x[..., 1], x[..., 0]), 2 * np.pi)
    j = np.minimum((ang / (2 * np.pi / J)).astype(np.int64), J - 1)
    j1 = (j + 1) % J
    d0, d1 = DIRS[j], DIRS[j1]
    det = d0[..., 0] * d1[..., 1] - d0[..., 1] * d1[..., 0]
    a = np.maximum((x[..., 0] * d1[..., 1] - x[..., 1] * d1[..., 0]) / det, 0.0)
    b = np.maximum((d0[..., 0] * x[..., 1] - d0[..., 1] * x[..., 0]) / det, 0.0)
    shape = np.broadcast_shapes(h.shape[:-1], j.shape)
    h = np.broadcast_to(h, (*shape, J))
    hj = np.take_along_axis(h, np.broadcast_to(j, shape)[..., None], -1)[..., 0]
    hj1 = np.take_along_axis(h, np.broadcast_to(j1, shape)[..., None], -1)[..., 0]
    with np.errstate(invalid="ignore"):
        return np.where(a > 1e-12, a * hj, 0.0) + np.where(b > 1e-12, b * hj1, 0.0)


def split(box: np.ndarray, k: int) -> np.ndarray:
    """Boxes `(N, 4)` as `x0, x1, y0, y1`, each cut into `k x k` sub-boxes: `(N, k*k, 4)`."""
    t = np.linspace(0.0, 1.0, k + 1)
    x = box[:, 0:1] + (box[:, 1:2] - box[:, 0:1]) * t[None]
    y = box[:, 2:3] + (box[:, 3:4] - box[:, 2:3]) * t[None]
    ix, iy = np.meshgrid(np.arange(k), np.arange(k), indexing="ij")
    ix, iy = ix.ravel(), iy.ravel()
    return np.stack([x[:, ix], x[:, ix + 1], y[:, iy], y[:, iy + 1]], axis=-1)


def corners(box: np.ndarray) -> np.ndarray:
    """`(..., 4, 2)` corners of boxes `(..., 4)`."""
    x0, x1, y0, y1 = (box[..., i] for i in range(4))
    return np.stack([np.stack([x0, y0], -1), np.stack([x1, y0], -1), np.stack([x1, y1], -1),
                     np.stack([x0, y1], -1)], axis=-2)


def affine_range(box: np.ndarray, w: np.ndarray, c: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    """Exact range of `w·m + c` over boxes."""
    v = corners(box) @ w + c
    return v.min(axis=-1), v.max(axis=-1)


def bp_barrier_g(D: np.ndarray, k: float, gain: float, rho: float, ell: float) -> np.ndarray:
    """`g(D) = -2 k gain B'(D/ℓ²)/ℓ² >= 0` (∞ at `D = 0`, 0 beyond the reach), decreasing in `D`."""
    s = D / ell**2
    with np.errstate(divide="ignore", invalid="ignore"):
        bp = -2.0 * (s - rho) * np.log(s) - (s - rho) ** 2 / s
    g = np.where(s >= rho, 0.0, -2.0 * k * gain * bp / ell**2)
    return np.where(s <= 0, np.inf, np.maximum(g, 0.0))


def barrier_value(D: np.ndarray, gain: float, rho: float, ell: float) -> np.ndarray:
    """`gain B(D/ℓ²)`, decreasing in `D` (∞ at 0)."""
    s = D / ell**2
    with np.errstate(divide="ignore", invalid="ignore"):
        v = (s - rho) ** 2 * -np.log(s)
    return gain * np.where(s >= rho, 0.0, np.where(s > 0, v, np.inf))


def attraction_corners(box: np.ndarray, k: float, p_T: np.ndarray) -> np.ndarray:
    """Corners `(..., 4, 2)` of the box `-2k (M - p_T)`."""
    return -2.0 * k * (corners(box) - p_T)


def minkowski(A: np.ndarray, B: np.ndarray) -> np.ndarray:
    """All sums of the point sets `(..., a, 2)` and `(..., b, 2)`: `(..., a*b, 2)`."""
    S = A[..., :, None, :] + B[..., None, :, :]
    return S.reshape(*S.shape[:-3], -1, 2)


def wedge_ranges(box: np.ndarray, cov, q: int):
    """Intervals of the wedge coordinates `u, v` of `W_q` over boxes, and the unit axes `d_u, d_v` (world)."""
    sigma = 1.0 if q == 1 else -1.0
    du = (sigma * cov.e_b + cov.e_a) * math.sqrt(0.5)
    dv = (sigma * cov.e_b - cov.e_a) * math.sqrt(0.5)
    c0 = cov.c * math.sqrt(0.5)
    u_lo, u_hi = affine_range(box, du, c0 - du @ cov.p_0)
    v_lo, v_hi = affine_range(box, dv, c0 - dv @ cov.p_0)
    return (u_lo, u_hi), (v_lo, v_hi), du, dv


def sq_dist_range(u, v):
    """Interval of `D = min(u,0)² + min(v,0)²`, and of `μ = min(u,0)`, `ν = min(v,0)`."""
    mu = (np.minimum(u[0], 0.0), np.minimum(u[1], 0.0))
    nu = (np.minimum(v[0], 0.0), np.minimum(v[1], 0.0))
    return (mu[1] ** 2 + nu[1] ** 2, mu[0] ** 2 + nu[0] ** 2), mu, nu


def barrier_range(box: np.ndarray, cov, q: int) -> tuple[np.ndarray, np.ndarray]:
    """Interval of `gain B(d_q/ℓ²)` over boxes (SPEC §3.2; ∞ where a box touches `W_q`). `V_q` is this plus
    `|m - p_T|²`, the same in both modes: comparisons of `V_1, V_2` cancel it (see `decisions`)."""
    u, v, _, _ = wedge_ranges(box, cov, q)
    (D_lo, D_hi), _, _ = sq_dist_range(u, v)
    return (barrier_value(D_hi, cov.barrier_gain, cov.barrier_rho, cov.ell),
            barrier_value(D_lo, cov.barrier_gain, cov.barrier_rho, cov.ell))


def dist_range(box: np.ndarray, c: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Exact range of `|m - c|` over boxes."""
    dx = np.maximum.reduce([box[..., 0] - c[0], c[0] - box[..., 1], np.zeros(box.shape[:-1])])
    dy = np.maximum.reduce([box[..., 2] - c[1], c[1] - box[..., 3], np.zeros(box.shape[:-1])])
    fx = np.maximum(np.abs(box[..., 0] - c[0]), np.abs(box[..., 1] - c[0]))
    fy = np.maximum(np.abs(box[..., 2] - c[1]), np.abs(box[..., 3] - c[1]))
    return np.hypot(dx, dy), np.hypot(fx, fy)


def arc_range(box: np.ndarray, c: np.ndarray):
    """The directions `e(α)` of `m - c` over boxes: `(α_mid, half-width)`; half-width π where `c` is in a box."""
    C = corners(box) - c
    mid = np.arctan2(C[..., 1].mean(-1), C[..., 0].mean(-1))
    rel = wrap(np.arctan2(C[..., 1], C[..., 0]) - mid[..., None])
    lo, hi = rel.min(-1), rel.max(-1)
    centre = mid + 0.5 * (lo + hi)
    half = 0.5 * (hi - lo)
    inside = (box[..., 0] <= c[0]) & (c[0] <= box[..., 1]) & (box[..., 2] <= c[1]) & (c[1] <= box[..., 3])
    return centre, np.where(inside | (half > 0.49 * np.pi), np.pi, half)


def sector_points(r_lo, r_hi, centre, half) -> np.ndarray:
    """Points `(..., 5, 2)` whose hull contains `{ρ e(α): ρ in [r_lo, r_hi], |α - centre| <= half}`; a half-width
    of π (or near it) gives the square `[-r_hi, r_hi]²` (plus a repeated corner)."""
    a1, a2 = centre - half, centre + half
    e = lambda a: np.stack([np.cos(a), np.sin(a)], -1)  # noqa: E731
    with np.errstate(over="ignore", invalid="ignore"):
        far = (r_hi / np.cos(np.minimum(half, 1.2)))[..., None] * e(centre)
    P = np.stack([r_lo[..., None] * e(a1), r_lo[..., None] * e(a2), r_hi[..., None] * e(a1),
                  r_hi[..., None] * e(a2), far], axis=-2)
    wide = half >= 1.2
    sq = np.stack([np.stack([-r_hi, -r_hi], -1), np.stack([r_hi, -r_hi], -1), np.stack([r_hi, r_hi], -1),
                   np.stack([-r_hi, r_hi], -1), np.stack([r_hi, r_hi], -1)], axis=-2)
    return np.where(wide[..., None, None], sq, P)


SUPPORT_CHUNK = 4096  # point sets per block of `saturated_support` (a few MB of temporaries: in the cache)


def raw_gap(X: np.ndarray, angles: bool = False):
    """`(pointed, gap)` of the hulls of point sets `X` `(..., P, 2)`: whether the points lie within an open half-plane
    through the origin, and then a lower bound `gap` of the hull's distance to the origin (the least projection on
    the bisector of their directions); with `angles`, also the mean direction and the points' angular range about it."""
    norm = np.hypot(X[..., 0], X[..., 1])
    mean = X.mean(axis=-2)
    mdir = np.arctan2(mean[..., 1], mean[..., 0])
    rel = wrap(np.arctan2(X[..., 1], X[..., 0]) - mdir[..., None])
    lo, hi = rel.min(-1), rel.max(-1)
    pointed = (hi - lo < np.pi - 1e-6) & (norm.min(-1) > 1e-12) & (np.hypot(mean[..., 0], mean[..., 1]) > 1e-12)
    bis = mdir + 0.5 * (lo + hi)
    w = np.stack([np.cos(bis), np.sin(bis)], -1)
    gap = np.einsum("...pk,...k->...p", X, w).min(-1)  # a lower bound of dist(0, hull X) when pointed
    return (pointed, gap, mdir, lo, hi) if angles else (pointed, gap)


def points_support(X: np.ndarray) -> np.ndarray:
    """`max_p d_j·X_p` `(..., J)` of point sets `X` `(..., P, 2)`: one matrix product per point, folded by `maximum`
    (the `(..., P, J)` products of `X @ DIRS.T` are never held: 2-6x faster, the same bits)."""
    D = DIRS.T
    flat = np.ascontiguousarray(X).reshape(-1, *X.shape[-2:])
    if len(flat) < 2 or flat.shape[1] < 2:  # a one-row product takes BLAS's vector path (other bits): as it was
        return (X @ D).max(axis=-2)
    h = np.ascontiguousarray(flat[:, 0]) @ D
    for p in range(1, flat.shape[1]):
        np.maximum(h, np.ascontiguousarray(flat[:, p]) @ D, out=h)
    return h.reshape(*X.shape[:-2], D.shape[1])


def saturated_support(X: np.ndarray, u_max: float | None, rays: np.ndarray | None = None) -> np.ndarray:
    """Support values `(..., J)` of a polytope containing `sat(hull X)` (`X` `(..., P, 2)`): the hull's own part
    inside the ball and the arc of the ball the hull's cone spans (`rays`: rows with an unbounded direction).
    Computed in blocks of `SUPPORT_CHUNK` point sets that stay in the cache (row by row the same: 2x faster)."""
    if u_max is None:
        return points_support(X)
    lead = X.shape[:-2]
    flat = X.reshape(-1, *X.shape[-2:])
    flat_rays = None if rays is None else np.broadcast_to(rays, lead).reshape(-1)
    out = np.empty((len(flat), len(DIRS)))
    for a in range(0, len(flat), SUPPORT_CHUNK):
        s = slice(a, a + SUPPORT_CHUNK)
        out[s] = _saturated_block(flat[s], u_max, None if flat_rays is None else flat_rays[s])
    return out.reshape(*lead, len(DIRS))


def _saturated_block(X: np.ndarray, u_max: float, rays: np.ndarray | None) -> np.ndarray:
    """:func:`saturated_support` of a block of point sets `(n, P, 2)`."""
    hX = points_support(X)
    norm = np.hypot(X[..., 0], X[..., 1])
    pointed, gap, mdir, lo, hi = raw_gap(X, angles=True)
    meets_ball = ~pointed | (gap <= u_max)
    leaves_ball = norm.max(-1) > u_max
    theta_d = np.arctan2(DIRS[:, 1], DIRS[:, 0])
    a1, a2 = (mdir + lo)[..., None], (mdir + hi)[..., None]
    rel_d = wrap(theta_d - (mdir + 0.5 * (lo + hi))[..., None])
    within = np.abs(rel_d) <= 0.5 * (hi - lo)[..., None]
    arc = np.where(within, 1.0, np.maximum(np.cos(theta_d - a1), np.cos(theta_d - a2))) * u_max
    inner = np.minimum(hX, u_max)
    if rays is not None:  # an unbounded direction: the hull's support is unbounded where the cone faces d
        inner = np.where(rays[..., None] & within, u_max, inner)
    h = np.maximum(np.where(meets_ball[..., None], inner, -np.inf), np.where(leaves_ball[..., None], arc, -np.inf))
    loose = np.minimum(u_max, np.maximum(0.0, hX))  # not pointed: sat(U) ⊂ conv(U ∪ {0}) ∩ ball
    return np.where(pointed[..., None], h, loose)
