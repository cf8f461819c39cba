"""The held input's enclosure per law (SPEC §5.4): `support(law, boxes, q)` -> `(N, J)` support values of a polytope
that contains `hold(F_q(m))` for every perceived `m` in each box (saturation, push-out and guard included).

Built from :mod:`pipeline.bracket.enclosures`: per sub-box a point set `X` whose hull contains the law's
pre-saturation velocity, then saturation, the guard and the push-outs; the box's polytope is the hull over its
sub-boxes (the largest support value per direction).
"""

from __future__ import annotations

import numpy as np

from pipeline.bracket.enclosures import (
    BIG,
    DIRS,
    affine_range,
    arc_range,
    attraction_corners,
    bp_barrier_g,
    dist_range,
    minkowski,
    raw_gap,
    saturated_support,
    sector_points,
    split,
    sq_dist_range,
    support_at,
    wedge_ranges,
    wrap,
)
from pipeline.bracket.pieces import MONOTONE_RHO, guard_floor, one_face, projected
from pipeline.control import CBFController, HybridController, SmoothController


def law_kind(law) -> str:
    for cls, name in ((HybridController, "hybrid"), (SmoothController, "smooth"), (CBFController, "cbf")):
        if isinstance(law, cls):
            return name
    raise ValueError(f"no enclosure for {type(law).__name__}")


def _arc_support(centre, half, radius) -> np.ndarray:
    """Support `(..., J)` of the arc `radius e(α)`, `|α - centre| <= half`."""
    theta_d = np.arctan2(DIRS[:, 1], DIRS[:, 0])
    rel = wrap(theta_d - centre[..., None])
    inside = np.abs(rel) <= half[..., None]
    best = np.where(inside, 1.0, np.maximum(np.cos(np.abs(rel) - half[..., None]), -1.0))
    return radius * best


def hybrid_support(law: HybridController, sub: np.ndarray, q: int, period: float, obstacle: int = 0,
                   apart: bool = False) -> np.ndarray | tuple[np.ndarray, np.ndarray]:
    """`(N, S, J)` support of the hybrid law's held input in mode `q` of the active obstacle `obstacle` per sub-box
    (module docstring; with several obstacles the flow map is the active obstacle's own, SPEC §3.6).

    `apart` (the refined window's, :mod:`pipeline.bracket.refine`): the flow's and the push-out's supports as two
    pieces `(N, 2S, J)` (`-inf` where a piece is absent), not their hull, each with a least norm of its inputs
    `(N, 2S)`, and tighter (all sound): no push-out where the sub-box misses the diamond (in `W_q ∩ O_{3-q}` the
    frame's decision jumps, so a node in mode `q` holds no input there: the nodes' mode is the one after the
    decision), the barrier's exact range on one face (:func:`one_face`), and the guard's bounds toward the face
    (:func:`_guarded` with `tight`). The coarse cells keep the looser hull (their table does not move)."""
    cov = law.scene.covering(obstacle)
    k, u_max = law.k, law.u_max
    (u, v, du, dv) = wedge_ranges(sub, cov, q)
    (D_lo, D_hi), mu, nu = sq_dist_range(u, v)
    g_lo = bp_barrier_g(D_hi, k, cov.barrier_gain, cov.barrier_rho, cov.ell)
    g_hi = bp_barrier_g(D_lo, k, cov.barrier_gain, cov.barrier_rho, cov.ell)
    flow = D_hi > 0  # some perceived point outside W_q: the flow map's formula
    with np.errstate(invalid="ignore", over="ignore"):
        c1 = (np.where(mu[0] < 0, np.maximum(-BIG, g_hi * mu[0]), 0.0), np.where(mu[1] < 0, g_lo * mu[1], 0.0))
        c2 = (np.where(nu[0] < 0, np.maximum(-BIG, g_hi * nu[0]), 0.0), np.where(nu[1] < 0, g_lo * nu[1], 0.0))
    c1 = tuple(np.nan_to_num(c, nan=0.0) for c in c1)
    c2 = tuple(np.nan_to_num(c, nan=0.0) for c in c2)
    if apart and MONOTONE_RHO[0] <= cov.barrier_rho <= MONOTONE_RHO[1]:  # one face: the product's exact range
        c1 = one_face(c1, mu, nu[0] >= 0, k, cov)
        c2 = one_face(c2, nu, mu[0] >= 0, k, cov)
    rays = (c1[0] <= -BIG) | (c2[0] <= -BIG)
    Bpts = np.stack([a[..., None] * du + b[..., None] * dv for a, b in ((c1[0], c2[0]), (c1[1], c2[0]),
                                                                         (c1[1], c2[1]), (c1[0], c2[1]))], axis=-2)
    A = attraction_corners(sub, k, cov.p_T)
    X = minkowski(A, Bpts)
    extra = []
    if rays.any():  # the recession directions themselves, so that the hull's cone is exact
        for a, b in ((c1[0] <= -BIG, False), (False, c2[0] <= -BIG), (c1[0] <= -BIG, c2[0] <= -BIG)):
            a, b = np.broadcast_to(a, rays.shape), np.broadcast_to(b, rays.shape)
            ray = (-BIG * a)[..., None] * du + (-BIG * b)[..., None] * dv
            extra.append(np.where((a | b)[..., None], ray, X[..., 0, :]))  # rows without this ray: a repeat
        X = np.concatenate([X, np.stack(extra, axis=-2)], axis=-2)
    h = saturated_support(X, u_max, rays)
    floor = np.zeros(h.shape[:-1])
    if apart and u_max is not None:  # every raw point beyond u_max: the held input has norm u_max (less the guard's)
        pointed, gap = raw_gap(X)
        floor = np.where(pointed & (gap >= u_max), u_max, 0.0)
    if law.guard and u_max is not None:
        if apart:
            floor = guard_floor(floor, h, D_lo, D_hi, mu, nu, du, dv, u_max, (1.0 - law.gamma) / period)
        h = _guarded(h, law, D_lo, D_hi, mu, nu, du, dv, period, tight=apart)
    h = np.where(flow[..., None], h, -np.inf)
    # push-out (SPEC §3.3): perceived point in W_q: -d_u (crossing the u = 0 face) or -d_v, at push_speed
    inside = (u[1] >= 0) & (v[1] >= 0)
    if apart:  # in W_q off the diamond `W_1 ∩ W_2` the frame's decision jumps: mode q is not held there
        u_o, v_o, _, _ = wedge_ranges(sub, cov, 3 - q)
        inside &= (u_o[1] >= 0) & (v_o[1] >= 0)
    push = np.full_like(h, -np.inf)
    if inside.any():
        speed = law.push_speed if u_max is None else min(law.push_speed, u_max)
        a_lo, a_hi = _a_range(sub, cov)
        pu = np.where(inside & (a_lo <= 0), 1.0, 0.0)[..., None] * (speed * (DIRS @ -du))
        pv = np.where(inside & (a_hi >= 0), 1.0, 0.0)[..., None] * (speed * (DIRS @ -dv))
        push = np.maximum(push, np.where((inside & (a_lo <= 0))[..., None], pu, -np.inf))
        push = np.maximum(push, np.where((inside & (a_hi >= 0))[..., None], pv, -np.inf))
    if not apart:
        return np.maximum(h, push)
    speed = law.push_speed if u_max is None else min(law.push_speed, u_max)
    return np.concatenate([h, push], axis=-2), np.concatenate([floor, np.full(floor.shape, speed)], axis=-1)



def _guarded(h, law, D_lo, D_hi, mu, nu, du, dv, period, tight: bool = False):
    """The guard (SPEC §3.3) on the support `h`: `u' = u + max(0, -c s - n·u) n`, `c = (1 - γ)/T_s`.

    For one normal `n` (a face: `ν = 0` gives `n = -d_u`, `μ = 0` gives `n = -d_v`) the tangential part is kept
    and `n·u' = max(n·u, -c s)`: `d·u' <= d·u` where `d·n < 0` (with `tight`, also `<= |d_t| h(±t) - (d·n) c s_hi`:
    the approach to the face is at most `c s`), else `<= max(h(d), |d_t| h(±t) - (d·n) c s_lo)`.
    Near the apex (`n` in the quarter arc between `-d_u` and `-d_v`) the looser `u + β n`, `0 <= β <= u_max - c s`.
    `tight`: toward the face, also `min` with `|d_t| h(±t) - (d·n) c s_hi` and the projection bound of
    :func:`projected`.
    """
    u_max, c = law.u_max, (1.0 - law.gamma) / period
    s_lo, s_hi = np.sqrt(D_lo), np.sqrt(D_hi)
    acts = (s_hi > 0) & (s_lo < u_max / c)
    out = h.copy()
    only_u, only_v = (nu[0] >= 0) & acts, (mu[0] >= 0) & acts
    for rows, n, t in ((only_u, -du, dv), (only_v, -dv, du)):
        if not rows.any():
            continue
        dn, dt = DIRS @ n, DIRS @ t
        h_t = np.where(dt >= 0, support_at(h, t)[..., None], support_at(h, -t)[..., None])  # h(sign(d_t) t)
        alt = np.abs(dt) * h_t - dn * c * s_lo[..., None]
        cap = np.abs(dt) * h_t - dn * c * s_hi[..., None]  # toward the face: n·u' >= -c s >= -c s_hi
        new = np.where(dn > 0, np.maximum(h, alt), np.where((dn < 0) & tight, np.minimum(h, cap), h))
        out = np.where(rows[..., None], new, out)
        if tight:
            idx = np.nonzero(rows)
            out[idx] = np.minimum(out[idx], projected(h[idx], n, c * s_lo[idx], c * s_hi[idx]))
    apex = acts & ~((nu[0] >= 0) | (mu[0] >= 0))
    if apex.any():
        out[apex] = _apex_guard(h[apex], mu[0][apex], mu[1][apex], nu[0][apex], nu[1][apex], du, dv, u_max,
                                c * s_lo[apex])
    return np.minimum(out, u_max)


APEX_SAMPLES = 32  # normals sampled on a row's arc by the apex guard's bound


def _apex_guard(h, mu_lo, mu_hi, nu_lo, nu_hi, du, dv, u_max, cs):
    """The guard near the apex (`M` rows; `cs` the rows' `c s_lo`): `u' = u + β n`, `0 <= β <= max(0, -n·u - cs)`
    with `n` the outward normal, the direction of `μ d_u + ν d_v` over the box of `(μ, ν) <= 0`: an arc between
    its corners `(μ_lo, ν_hi)` and `(μ_hi, ν_lo)` (the quarter arc where the box reaches `(0, 0)`). Two bounds of
    `d·u'`, the smaller kept: `d·u + (u_max - cs)⁺ max_n (d·n)⁺`, and `max(d·u, (P_n d)·u - cs d·n)` with
    `P_n d = d - (d·n) n` (where `β > 0`: `β <= -n·u - cs`), maximised over `APEX_SAMPLES` normals at the centres
    of equal pieces of the arc plus the Lipschitz constant `u_max + cs` in the angle (`|∂ P_n d/∂φ| = |d| = 1`,
    `max |u| <= u_max`)."""
    theta = np.arctan2(*(-(du + dv))[::-1])  # the quarter arc's bisector
    ends = [wrap(np.arctan2(a * du[1] + b * dv[1], a * du[0] + b * dv[0]) - theta)
            for a, b in ((mu_lo, nu_hi), (mu_hi, nu_lo))]
    touches = (mu_hi >= 0) & (nu_hi >= 0)
    lo = np.where(touches, -np.pi / 4, np.clip(np.minimum(*ends), -np.pi / 4, np.pi / 4))[:, None]
    hi = np.where(touches, np.pi / 4, np.clip(np.maximum(*ends), -np.pi / 4, np.pi / 4))[:, None]
    rel = wrap(np.arctan2(DIRS[:, 1], DIRS[:, 0]) - theta)
    dn = np.where((rel >= lo - 1e-12) & (rel <= hi + 1e-12), 1.0, np.maximum(np.cos(rel - lo), np.cos(rel - hi)))
    beta = np.maximum(0.0, u_max - cs)[:, None]
    out = h + beta * np.maximum(dn, 0.0)
    step = (hi - lo) / APEX_SAMPLES
    phi = theta + lo + (np.arange(APEX_SAMPLES) + 0.5) * step  # (M, K)
    n = np.stack([np.cos(phi), np.sin(phi)], axis=-1)
    for j, d in enumerate(DIRS):
        x = d - (n @ d)[..., None] * n  # (M, K, 2)
        proj = (support_at(h[:, None, :], x) - cs[:, None] * (n @ d)).max(axis=1) + (u_max + cs) * step[:, 0] / 2
        out[:, j] = np.minimum(out[:, j], np.maximum(h[:, j], proj))
    return out


def _a_range(sub, cov):
    return affine_range(sub, cov.e_a, -cov.e_a @ cov.p_0)


def radial_support(law, sub: np.ndarray) -> np.ndarray:
    """`(N, S, J)` support of the smooth law's or the CBF filter's held input per sub-box: the attraction (box)
    plus a radial term `ρ e(α)` (a sector), saturated; inside the margin disc (or at the centre) the radial
    push-out. Several obstacles: :func:`_smooth_several`, :func:`_cbf_several`."""
    covs = law.scene.coverings
    if len(covs) > 1:
        return (_smooth_several if isinstance(law, SmoothController) else _cbf_several)(law, sub, covs)
    t = _radial_terms(law, sub, covs[0])
    X = minkowski(t["A"], sector_points(t["r_lo"], np.minimum(t["r_hi"], BIG), t["centre"], t["half"]))
    rays = t["r_hi"] >= BIG
    h = saturated_support(X, law.u_max, rays)
    h = np.where(t["flow"][..., None], h, -np.inf)
    return _pushed(law, h, [(t["push"], t["centre"], t["half"])])


def _pushed(law, h, arcs):
    """`h` with the radial push-outs at `push_speed`: `arcs` `(rows, centre, half)` per obstacle that may push."""
    speed = law.push_speed if law.u_max is None else min(law.push_speed, law.u_max)
    for push, centre, half in arcs:
        if push.any():
            h = np.maximum(h, np.where(push[..., None], _arc_support(centre, half, speed), -np.inf))
    return h


def _radial_terms(law, sub: np.ndarray, cov) -> dict:
    """One obstacle's part of :func:`radial_support`: the attraction's corners `A`, the radial term's interval
    `r_lo, r_hi` and arc `centre, half`, where the flow map's formula applies (`flow`) and where it may push out
    (`push`), and the distance range `d_lo, d_hi` to the centre."""
    k, R = law.k, 2.0 * cov.obstacle_radius
    d_lo, d_hi = dist_range(sub, cov.p_0)
    centre, half = arc_range(sub, cov.p_0)
    A = attraction_corners(sub, k, cov.p_T)
    if isinstance(law, SmoothController):
        gap_lo, gap_hi = np.maximum(d_lo - R, 0.0), np.maximum(d_hi - R, 0.0)
        g_lo = bp_barrier_g(gap_hi**2, k, cov.barrier_gain, cov.barrier_rho, cov.ell)
        g_hi = bp_barrier_g(gap_lo**2, k, cov.barrier_gain, cov.barrier_rho, cov.ell)
        with np.errstate(invalid="ignore"):
            r_lo = np.nan_to_num(g_lo * gap_lo, nan=0.0)
            r_hi = np.where(gap_lo > 0, g_hi * gap_hi, BIG)
        flow = gap_hi > 0
        push = d_lo <= R
    else:
        alpha = law.alpha
        # u = u_nom + κ e, κ = max(0, -(e·u_nom) - α (ρ² - R²) / (2ρ)) (SPEC §3.4's closed form, one disc)
        rho_lo, rho_hi = np.maximum(d_lo, 1e-12), d_hi
        f_lo, f_hi = (rho_lo**2 - R**2) / (2 * rho_lo), (rho_hi**2 - R**2) / (2 * rho_hi)
        cos_r, sin_r = _trig_ranges(centre, half)
        ux = (-2.0 * 0 + -k * (sub[..., 1] - cov.p_T[0]), -k * (sub[..., 0] - cov.p_T[0]))
        uy = (-k * (sub[..., 3] - cov.p_T[1]), -k * (sub[..., 2] - cov.p_T[1]))
        eu_lo = _mul_lo(cos_r, ux) + _mul_lo(sin_r, uy)
        eu_hi = _mul_hi(cos_r, ux) + _mul_hi(sin_r, uy)
        r_lo = np.maximum(0.0, -eu_hi - alpha * f_hi)
        r_hi = np.maximum(0.0, -eu_lo - alpha * f_lo)
        A = -k * (np.stack([np.stack([sub[..., i], sub[..., j]], -1) for i, j in ((0, 2), (1, 2), (1, 3), (0, 3))],
                           axis=-2) - cov.p_T)
        flow = d_hi > 0
        push = d_lo <= 0
    return {"A": A, "r_lo": r_lo, "r_hi": r_hi, "centre": centre, "half": half, "flow": flow, "push": push,
            "d_lo": d_lo, "d_hi": d_hi, "R": R}


def _ball(law, shape) -> np.ndarray:
    """The support of every input the law can hold (`|u| <= u_max`; without a limit, unbounded: unsafe)."""
    return np.full((*shape, len(DIRS)), BIG if law.u_max is None else float(law.u_max))


def _nearest_candidates(terms) -> list[np.ndarray]:
    """Per obstacle, the sub-boxes where its centre may be the nearest (the push-out's direction, `radial`)."""
    far = np.minimum.reduce([t["d_hi"] for t in terms])
    return [t["d_lo"] <= far for t in terms]


def _smooth_several(law, sub: np.ndarray, covs) -> np.ndarray:
    """The smooth law over several obstacles: the attraction plus the sum of each obstacle's radial term, the
    sectors of the (at most two) obstacles whose barrier may act on a sub-box added as point sets (more than two:
    every input of the speed limit); the push-out from any obstacle whose centre may be the nearest."""
    terms = [_radial_terms(law, sub, cov) for cov in covs]
    r_lo, r_hi, centre, half = (np.stack([t[key] for t in terms], -1) for key in ("r_lo", "r_hi", "centre", "half"))
    active = r_hi > 0
    order = np.argsort(~active, axis=-1, kind="stable")[..., :2]  # the first two acting obstacles
    sectors, rays = [], np.zeros(sub.shape[:-1], bool)
    for k in range(2):
        idx = order[..., k:k + 1]
        on = np.take_along_axis(active, idx, -1)[..., 0]
        lo, hi = (np.where(on, np.take_along_axis(a, idx, -1)[..., 0], 0.0) for a in (r_lo, r_hi))
        c, w = (np.take_along_axis(a, idx, -1)[..., 0] for a in (centre, half))
        sectors.append(sector_points(lo, np.minimum(hi, BIG), c, w))
        rays |= hi >= BIG
    X = minkowski(terms[0]["A"], sectors[0])
    h = saturated_support(X, law.u_max, rays)
    two = active.sum(-1) == 2  # a second sector to add (elsewhere it is the point 0)
    if two.any():
        h[two] = saturated_support(minkowski(X[two], sectors[1][two]), law.u_max, rays[two])
    h = np.where(np.logical_and.reduce([t["flow"] for t in terms])[..., None], h, -np.inf)
    h = np.where((active.sum(-1) > 2)[..., None], _ball(law, sub.shape[:-1]), h)
    near = _nearest_candidates(terms)
    push = np.logical_or.reduce([t["push"] for t in terms])
    return _pushed(law, h, [(push & n, t["centre"], t["half"]) for t, n in zip(terms, near)])


def _cbf_several(law, sub: np.ndarray, covs) -> np.ndarray:
    """The CBF filter over several obstacles (the exact QP): on a sub-box, the one-constraint closed form of the
    obstacle with the nearest margin disc, where every other constraint holds with slack for every input that
    form can give (`α h_j >= 2 |m - c_j| |u|` bounded with intervals: then it is the QP's solution, the optimum of a
    relaxation that is feasible); elsewhere every input of the speed limit."""
    terms = [_radial_terms(law, sub, cov) for cov in covs]
    best = np.argmin(np.stack([t["d_lo"] - t["R"] for t in terms], -1), axis=-1)
    h = _ball(law, sub.shape[:-1])
    for i, t in enumerate(terms):
        rows = best == i
        if not rows.any():
            continue
        X = minkowski(t["A"], sector_points(t["r_lo"], np.minimum(t["r_hi"], BIG), t["centre"], t["half"]))
        rays = t["r_hi"] >= BIG
        norm = np.hypot(X[..., 0], X[..., 1]).max(-1)
        ok = rows & ~rays & np.isfinite(norm)
        for j, o in enumerate(terms):
            if j != i:
                ok &= (o["d_lo"] > o["R"]) & (law.alpha * (o["d_lo"] ** 2 - o["R"] ** 2) >= 2.0 * o["d_hi"] * norm)
        hi = saturated_support(X, law.u_max, rays)
        hi = np.where(t["flow"][..., None], hi, -np.inf)
        hi = _pushed(law, hi, [(t["push"], t["centre"], t["half"])])
        h = np.where(ok[..., None], hi, h)
    return h


def _trig_ranges(centre, half):
    """Intervals of `cos α`, `sin α` over `|α - centre| <= half`."""
    out = []
    for f, peaks in ((np.cos, (0.0, np.pi)), (np.sin, (np.pi / 2, -np.pi / 2))):
        a1, a2 = centre - half, centre + half
        lo, hi = np.minimum(f(a1), f(a2)), np.maximum(f(a1), f(a2))
        for peak, val in zip(peaks, (1.0, -1.0)):
            rel = wrap(peak - centre)
            hit = np.abs(rel) <= half
            lo = np.where(hit & (val < 0), -1.0, lo)
            hi = np.where(hit & (val > 0), 1.0, hi)
        out.append((lo, hi))
    return out


def _mul_lo(a, b):
    return np.minimum.reduce([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])


def _mul_hi(a, b):
    return np.maximum.reduce([a[0] * b[0], a[0] * b[1], a[1] * b[0], a[1] * b[1]])


def support(law, boxes: np.ndarray, q: int, period: float, n_split: int = 4, chunk: int = 4096,
            obstacle: int = 0, parts: bool = False) -> np.ndarray:
    """`(N, J)` support values of `U(M, q)` for perceived boxes `M` `(N, 4)` (`x0, x1, y0, y1`): the hull over
    `n_split x n_split` sub-boxes (the hybrid law: in mode `q` of the active obstacle `obstacle`); with `parts`, each
    sub-box's own `(N, S, J)`, `S = n_split²` (the sub-boxes of :func:`split`; the hybrid law: `2 S`, the flow's
    pieces then the push-out's, sub-box by sub-box), and a least norm of each piece's inputs `(N, S)` (0: none
    claimed). `-inf`: no velocity (mode `q` is not held at any perceived point there)."""
    kind = law_kind(law)
    k = n_split * n_split * (2 if kind == "hybrid" else 1)
    out = np.empty((len(boxes), k, len(DIRS)) if parts else (len(boxes), len(DIRS)))
    floors = np.zeros((len(boxes), k))
    for s in range(0, len(boxes), chunk):
        sub = split(boxes[s:s + chunk], n_split)
        if kind == "hybrid" and parts:
            out[s:s + chunk], floors[s:s + chunk] = hybrid_support(law, sub, q, period, obstacle, True)
            continue
        h = hybrid_support(law, sub, q, period, obstacle) if kind == "hybrid" else radial_support(law, sub)
        out[s:s + chunk] = h if parts else h.max(axis=1)
    return (out, floors) if parts else out
