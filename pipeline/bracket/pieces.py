"""The refined window's tighter input enclosures (:mod:`pipeline.bracket.refine`; used by
:func:`pipeline.bracket.inputs.hybrid_support` with `apart`): the barrier's exact range on one face, the guard's image
bounded through the projection onto its half-plane, and the least norm of the guarded input. Each is a sound bound
(docstrings), checked against the law by sampling in tests/test_bracket_refine.py."""

from __future__ import annotations

import numpy as np

from pipeline.bracket.enclosures import BIG, DIRS, bp_barrier_g, support_at

MONOTONE_RHO = (0.032, 1.0)  # barrier shapes rho_b for which d g(d²) is decreasing (see one_face)


def one_face(c, mu, alone, k, cov):
    """The barrier's coefficient `g(μ²) μ` on one face (`alone`: the other coordinate is >= 0 on the whole box, so
    `D = μ²`): its exact range `[g(μ_hi²) μ_hi, g(μ_lo²) μ_lo]` (`-BIG` for the face itself), intersected with the
    interval `c` of separate bounds. `d ↦ d g(d²)` is decreasing: with `s = d²/ℓ²` it is a positive multiple of
    `F(s) = √s |B'(s)| = 2(ρ-s)√s log(1/s) + (ρ-s)²/√s` on `(0, ρ)` (0 beyond), and `s^{3/2} F'(s) = -2s² log(1/s) +
    (ρ-s) s (log(1/s) - 4) - (ρ-s)²/2 < 0`: the middle term is positive only for `s < e^-4`, where `s (log(1/s) - 4)
    <= e^-5 < (ρ - s)/2` as soon as `ρ >= 0.032`; `log(1/s) >= 0` needs `ρ <= 1` (`MONOTONE_RHO`)."""
    g = lambda m: bp_barrier_g(m * m, k, cov.barrier_gain, cov.barrier_rho, cov.ell)  # noqa: E731
    with np.errstate(invalid="ignore", over="ignore"):
        lo = np.where(mu[1] < 0, np.maximum(-BIG, g(mu[1]) * mu[1]), -BIG)
        hi = np.where(mu[0] < 0, g(mu[0]) * mu[0], 0.0)
    lo, hi = np.nan_to_num(lo, nan=-BIG), np.nan_to_num(hi, nan=0.0)
    return np.where(alone, np.maximum(c[0], lo), c[0]), np.where(alone, np.minimum(c[1], hi), c[1])


MULTIPLIERS = np.array([0.0, 0.05, 0.1, 0.2, 0.3, 0.45, 0.6, 0.8, 1.0, 1.3, 1.7, 2.2, 3.0, 4.5, 7.0])


def projected(h: np.ndarray, n: np.ndarray, cs_lo: np.ndarray, cs_hi: np.ndarray, chunk: int = 4096) -> np.ndarray:
    """Support `(M, J)` of the guarded set `{u + max(0, -cs - n·u) n : u in U, cs in [cs_lo, cs_hi]}` for polytopes
    `U` `(M, J)`: the projection onto the half-plane `n·u >= -cs` along `n`. For a direction `d`, the points kept
    (`n·u >= -cs`) give `max d·u <= h(d + μ n) + μ cs` and the projected ones (`n·u <= -cs`) give
    `max (P d)·u - cs d·n <= h(P d - μ n) - cs (μ + d·n)` (`P d = d - (d·n) n`), for every `μ >= 0` (Lagrange):
    the least over `MULTIPLIERS` of each, the larger of the two, the worst `cs` of its interval."""
    dn = DIRS @ n  # (J,)
    Pd = DIRS - dn[:, None] * n  # (J, 2)
    mu = MULTIPLIERS
    xa = DIRS[:, None, :] + mu[None, :, None] * n  # (J, K, 2)
    xb = Pd[:, None, :] - mu[None, :, None] * n
    out = np.empty_like(h)
    for s in range(0, len(h), chunk):
        hc = h[s:s + chunk][:, None, None, :]
        lo, hi = cs_lo[s:s + chunk, None, None], cs_hi[s:s + chunk, None, None]
        a = (support_at(hc, xa[None]) + mu * hi).min(axis=-1)
        k = mu[None, :] + dn[:, None]  # (J, K)
        b = (support_at(hc, xb[None]) - k * np.where(k >= 0, lo, hi)).min(axis=-1)
        out[s:s + chunk] = np.maximum(a, b)
    return out


def guard_floor(floor, h, D_lo, D_hi, mu, nu, du, dv, u_max, c):
    """The least norm of the guarded input where the guard may act on one face (outward normal `n`): it keeps the
    tangential part and raises `n·u` to `-c s`, so `|u'|² >= u_max² - a²` with `a = max(0, max -n·u)` the fastest
    approach; near the apex (two faces) no floor is claimed (0)."""
    s_lo, s_hi = np.sqrt(D_lo), np.sqrt(D_hi)
    acts = (s_hi > 0) & (s_lo < u_max / c)
    out = np.where(acts, 0.0, floor)
    for rows, n in (((nu[0] >= 0) & acts, -du), ((mu[0] >= 0) & acts, -dv)):
        a = np.maximum(0.0, support_at(h, -n))
        out = np.where(rows, np.minimum(floor, np.sqrt(np.maximum(0.0, u_max * u_max - a * a))), out)
    return out
