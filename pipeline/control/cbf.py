"""The CBF safety filter's quadratic program with several constraints, exact in 2-D (SPEC §3.4, §3.6).

`cbf_qp` solves `min_u |u - u_nom|^2  s.t.  G_i·u >= b_i` for every agent at once; `disc_constraints` builds
the constraints `∇h_i·u >= -alpha h_i` of the discs `h_i(p) = |p - c_i|^2 - radii_i^2` (SPEC §3.6 passes
`radii_i = 2 r_i`). Pure numpy, no solver library.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

# feasibility tolerance of a candidate, relative to the size of the terms of `G·u - b`
RTOL = 1e-9
# two constraint lines count as parallel (no intersection candidate) when |sin(angle)| is below this
PARALLEL = 1e-12


@dataclass(frozen=True)
class CBFSolution:
    """Result of `cbf_qp` for `N` agents and `M` constraints.

    `u` `(N, 2)`: the filtered velocity. `active` `(N, M)`: the binding constraints at `u` (at most two, held
    with equality and with multipliers `>= 0`; on degenerate rows: the zero-gradient constraints that `u_nom`
    violates). `feasible` `(N,)`: `u` satisfies
    every constraint. `degenerate` `(N,)`: a violated constraint has `G = 0` (e.g. the agent at a disc
    centre); `u = u_nom` there and the caller applies its own fallback.
    """

    u: np.ndarray
    active: np.ndarray
    feasible: np.ndarray
    degenerate: np.ndarray


def disc_constraints(p, centers, radii, alpha) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """CBF constraints of discs (SPEC §3.6): `(G, b, h)` with shapes `(N, M, 2)`, `(N, M)`, `(N, M)`.

    `h_i = |p - c_i|^2 - radii_i^2`, `G_i = ∇h_i = 2 (p - c_i)`, `b_i = -alpha h_i` for points `p` `(N, 2)`,
    centres `(M, 2)` and margin radii `(M,)` (the caller passes `2 r_i`).
    """
    p = np.asarray(p, dtype=float)
    centers = np.asarray(centers, dtype=float).reshape(-1, 2)
    radii = np.asarray(radii, dtype=float).reshape(-1)
    n, m = len(p), len(centers)
    # the same expressions as CBFController._flow, so that M = 1 reproduces it bit for bit
    rel = p[:, None, :] - centers[None, :, :]
    flat = rel.reshape(-1, 2)
    h = np.einsum("ij,ij->i", flat, flat).reshape(n, m) - radii**2
    gh = 2.0 * rel
    return gh, -alpha * h, h


def cbf_qp(u_nom, G, b) -> CBFSolution:
    """Exact batched solution of `min_u |u - u_nom|^2 s.t. G[n, i]·u >= b[n, i]` (SPEC §3.4, §3.6).

    `u_nom` `(N, 2)`, `G` `(N, M, 2)`, `b` `(N, M)`. In 2-D the optimum has at most two (linearly independent)
    active constraints, so it is one of the candidates: `u_nom`, its projection onto each constraint line,
    and the intersection of each non-parallel pair of lines. Keep the candidates that satisfy every
    constraint (relative tolerance `RTOL`) and take one whose multipliers are `>= 0` (a KKT point, hence the
    optimum; should rounding reject all of them, the feasible one nearest `u_nom`). Where none is feasible,
    return the candidate with the smallest largest violation `max_i (b_i - G_i·u)` (ties: nearest `u_nom`) and
    `feasible=False`. With `M = 1` this is CBFController._flow's closed form, operation for operation.
    """
    u_nom = np.asarray(u_nom, dtype=float)
    G = np.asarray(G, dtype=float)
    b = np.asarray(b, dtype=float)
    n, m = b.shape
    if m == 1:
        return _single(u_nom, G[:, 0, :], b[:, 0])
    if m == 0:
        z = np.zeros((n, 0), dtype=bool)
        return CBFSolution(u_nom.copy(), z, np.ones(n, dtype=bool), np.zeros(n, dtype=bool))

    gg = np.einsum("nmk,nmk->nm", G, G)
    slack = np.einsum("nmk,nk->nm", G, u_nom) - b  # G·u_nom - b: >= 0 where u_nom satisfies constraint i
    bad = (gg <= 0) & (slack < 0)  # a violated constraint without a gradient: nothing can fix it
    degenerate = bad.any(axis=1)
    u, active, feasible = u_nom.copy(), bad.copy(), ~degenerate
    need = (slack < 0).any(axis=1) & ~degenerate  # elsewhere u_nom is the solution
    if need.any():
        sub = _enumerate(u_nom[need], G[need], b[need], gg[need], slack[need])
        u[need], active[need], feasible[need] = sub
    return CBFSolution(u, active, feasible, degenerate)


def _enumerate(u_nom, G, b, gg, slack) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(u, active, feasible)` of `cbf_qp` by enumerating the active sets (rows without a degenerate one)."""
    n, m = b.shape
    # candidates d = u - u_nom = Σ_active λ_i G_i for the active sets none, {i}, {i, j}, with min_i λ_i |G_i|
    ii, jj = np.triu_indices(m, 1)
    with np.errstate(divide="ignore", invalid="ignore", over="ignore"):
        lam_single = -slack / np.sqrt(gg)  # λ_i |G_i| of the projection onto line i
        d_single = (-slack / gg)[..., None] * G
        gi, gj = G[:, ii, :], G[:, jj, :]
        det = gi[..., 0] * gj[..., 1] - gi[..., 1] * gj[..., 0]
        ok_pair = det * det > PARALLEL**2 * gg[:, ii] * gg[:, jj]
        safe = np.where(ok_pair, det, 1.0)
        si, sj = -slack[:, ii], -slack[:, jj]  # Cramer's rule for G_i·d = -slack_i, G_j·d = -slack_j
        d_pair = np.stack([si * gj[..., 1] - sj * gi[..., 1], gi[..., 0] * sj - gj[..., 0] * si], axis=-1)
        d_pair = d_pair / safe[..., None]
        lam_i = (d_pair[..., 0] * gj[..., 1] - d_pair[..., 1] * gj[..., 0]) / safe * np.sqrt(gg[:, ii])
        lam_j = (gi[..., 0] * d_pair[..., 1] - gi[..., 1] * d_pair[..., 0]) / safe * np.sqrt(gg[:, jj])
    d = np.concatenate([np.zeros((n, 1, 2)), d_single, d_pair], axis=1)  # (N, C, 2), C = 1 + M + M(M-1)/2
    lam_min = np.concatenate([np.zeros((n, 1)), lam_single, np.minimum(lam_i, lam_j)], axis=1)
    valid = np.concatenate([np.ones((n, 1), dtype=bool), gg > 0, ok_pair], axis=1)
    valid &= np.isfinite(d).all(axis=-1) & np.isfinite(lam_min)
    d = np.where(valid[..., None], d, 0.0)
    n_pairs = len(ii)
    act = np.zeros((1 + m + n_pairs, m), dtype=bool)
    act[1 + np.arange(m), np.arange(m)] = True
    act[1 + m + np.arange(n_pairs), ii] = True
    act[1 + m + np.arange(n_pairs), jj] = True

    # residuals G_i·u - b_i of every candidate, and the tolerance they are judged with
    resid = slack[:, None, :] + np.einsum("nck,nmk->ncm", d, G)
    size = np.hypot(u_nom[:, 0], u_nom[:, 1])[:, None] + np.hypot(d[..., 0], d[..., 1])
    tol = RTOL * (np.sqrt(gg)[:, None, :] * size[..., None] + np.abs(b)[:, None, :])
    tol[:, 0, :] = 0.0  # u_nom itself is kept only if it satisfies every constraint exactly, as for M = 1
    ok = valid & (resid >= -tol).all(axis=-1)
    # a feasible candidate with every λ_i >= 0 is the optimum (KKT): preferring those picks a correct active
    # set where three or more lines meet at the optimum
    kkt = ok & (lam_min >= -RTOL * size)
    obj = np.einsum("nck,nck->nc", d, d)
    worst = np.where(ok, 0.0, (-resid).max(axis=-1))  # > 0 on every infeasible candidate
    # order: KKT points, then other feasible candidates, then the least violating; ties: nearest u_nom
    rank = np.where(kkt, 0, np.where(ok, 1, np.where(valid, 2, 3)))
    pick = np.lexsort((np.where(valid, obj, np.inf), worst, rank), axis=-1)[:, 0]
    rows = np.arange(n)
    return u_nom + d[rows, pick], act[pick], ok[rows, pick]


def _single(u_nom: np.ndarray, g: np.ndarray, b: np.ndarray) -> CBFSolution:
    """`M = 1`: the closed form of CBFController._flow, with the same expressions in the same order."""
    g = np.ascontiguousarray(g)
    gg = np.einsum("ij,ij->i", g, g)
    slack = np.einsum("ij,ij->i", g, u_nom) - b
    active = slack < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = np.where(active, -slack / gg, 0.0)
        u = u_nom + corr[:, None] * g
    degenerate = active & ((gg <= 0) | ~np.isfinite(u).all(axis=1))  # also a gradient so small gg underflows
    u[degenerate] = u_nom[degenerate]
    return CBFSolution(u, active[:, None], ~degenerate, degenerate)
