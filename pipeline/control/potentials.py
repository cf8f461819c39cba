"""Barrier and potential functions of SPEC §3.2 and §3.4, batched over `(N, 2)` points.

Paper: `φ(p) = -|p - p_T|^2`, `φ_q(p) = B(d_q(p))`, `V_q = φ_q - φ` on `O_q` (Eq. for V_q); SPEC applies the
barrier to `d_q / l_B^2`. All gradients are analytic.
"""

from __future__ import annotations

import numpy as np

from pipeline.control.covering import SQRT1_2, sq_dist_to_wedge_grad
from pipeline.control.scene import Covering


def barrier(s: np.ndarray, rho: float) -> np.ndarray:
    """`B(s) = (s - rho)^2 log(1/s)` for `0 < s <= rho`, 0 for `s > rho`, +inf for `s <= 0` (SPEC §3)."""
    s = np.asarray(s, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        val = (s - rho) ** 2 * -np.log(s)
    return np.where(s > rho, 0.0, np.where(s > 0, val, np.inf))


def barrier_grad(s: np.ndarray, rho: float) -> np.ndarray:
    """`B'(s) = 2 (s - rho) log(1/s) - (s - rho)^2 / s` on `(0, rho]`, 0 beyond; -inf for `s <= 0`."""
    s = np.asarray(s, dtype=float)
    with np.errstate(divide="ignore", invalid="ignore"):
        val = -2.0 * (s - rho) * np.log(s) - (s - rho) ** 2 / s
    return np.where(s > rho, 0.0, np.where(s > 0, val, -np.inf))


def _barrier_of_sqdist(scene, D: np.ndarray, with_grad: bool):
    """Barrier of one covering as a function of a squared distance `D`, and its derivative dB/dD (times the gain)."""
    return _barrier_params(scene.barrier_kind, scene.barrier_rho, scene.barrier_gain, scene.ell, D, with_grad)


def _barrier_params(kind: str, rho: float, gain: float, ell, D: np.ndarray, with_grad: bool = True):
    """`(gain B, gain dB/dD)` of a squared distance `D` for the barrier `kind` (SPEC §3, §1)."""
    val, grad = _raw_barrier(kind, rho, ell, D, with_grad)
    if gain == 1.0:
        return val, grad
    return gain * val, (None if grad is None else gain * grad)


def _raw_barrier(kind: str, rho: float, ell, D: np.ndarray, with_grad: bool):
    if kind == "authors_code":
        d = np.sqrt(D)
        with np.errstate(divide="ignore", invalid="ignore"):
            val = np.where(d >= rho, 0.0, np.where(d > 0, (d - rho) ** 2 * np.log(rho / d), np.inf))
            if not with_grad:
                return val, None
            dBdd = 2.0 * (d - rho) * np.log(rho / d) - (d - rho) ** 2 / d
            dBdD = np.where(d >= rho, 0.0, np.where(d > 0, dBdd / (2.0 * d), -np.inf))
        return val, dBdD
    inv = 1.0 / ell**2
    s = D * inv
    val = barrier(s, rho)
    return val, (barrier_grad(s, rho) * inv if with_grad else None)


def _target(scene: Covering, target) -> np.ndarray:
    return scene.p_T if target is None else np.asarray(target, dtype=float)


def potential(scene: Covering, q: int, points: np.ndarray, target=None) -> np.ndarray:
    """`V_q(p) = B(d_q(p)/l_B^2) + |p - p_T|^2` on `O_q`, `+inf` outside (SPEC §3.2). Shape `(N,)`.

    `target` (shape `(2,)` or `(N, 2)`) replaces `p_T` in `φ` only (moving target, SPEC §4); the covering
    stays that of the scene.
    """
    p = np.asarray(points, dtype=float)
    D, _ = sq_dist_to_wedge_grad(scene, q, p)
    B, _ = _barrier_of_sqdist(scene, D, with_grad=False)
    diff = p - _target(scene, target)
    return B + scene.phi_weight * np.einsum("ij,ij->i", diff, diff)


def potential_grad(scene: Covering, q: int, points: np.ndarray, target=None) -> np.ndarray:
    """Analytic `∇V_q(p)`, shape `(N, 2)`; NaN rows outside `O_q` (where `V_q = +inf`)."""
    p = np.asarray(points, dtype=float)
    D, gD = sq_dist_to_wedge_grad(scene, q, p)
    _, dB = _barrier_of_sqdist(scene, D, with_grad=True)
    with np.errstate(invalid="ignore"):
        grad = dB[:, None] * gD + 2.0 * scene.phi_weight * (p - _target(scene, target))
    grad[D <= 0] = np.nan
    return grad


def potential_and_grad(scene: Covering, q: int, points: np.ndarray, target=None) -> tuple[np.ndarray, np.ndarray]:
    """`(V_q, ∇V_q)` in one pass (the controllers' hot path)."""
    p = np.asarray(points, dtype=float)
    D, gD = sq_dist_to_wedge_grad(scene, q, p)
    B, dB = _barrier_of_sqdist(scene, D, with_grad=True)
    diff = p - _target(scene, target)
    V = B + scene.phi_weight * np.einsum("ij,ij->i", diff, diff)
    with np.errstate(invalid="ignore"):
        grad = dB[:, None] * gD + 2.0 * scene.phi_weight * diff
    grad[D <= 0] = np.nan
    return V, grad


def _disc_sqdist_grad(scene: Covering, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance to the margin disc `D_2r` around `p_0` and its gradient."""
    rel = p - scene.p_0
    norm = np.hypot(rel[:, 0], rel[:, 1])
    gap = np.maximum(norm - 2.0 * scene.obstacle_radius, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = rel / norm[:, None]
    grad = 2.0 * gap[:, None] * np.nan_to_num(unit)
    return gap * gap, grad


def _coverings(scene) -> list:
    return scene.coverings if hasattr(scene, "coverings") else [scene]


def smooth_potential(scene, points: np.ndarray, target=None) -> np.ndarray:
    """`V_s(p) = |p - p_T|^2 + sum_i B(dist(p, D_2r_i)^2 / l_i^2)` (SPEC §3.4, §3.6); +inf inside a `D_2r_i`."""
    p = np.asarray(points, dtype=float)
    covs = _coverings(scene)
    B = 0.0
    for cov in covs:
        D, _ = _disc_sqdist_grad(cov, p)
        B = B + _barrier_of_sqdist(cov, D, with_grad=False)[0]
    diff = p - _target(covs[0], target)
    return B + covs[0].phi_weight * np.einsum("ij,ij->i", diff, diff)


def smooth_potential_grad(scene, points: np.ndarray, target=None) -> np.ndarray:
    """Analytic `∇V_s`, NaN rows inside a `D_2r_i`."""
    p = np.asarray(points, dtype=float)
    covs = _coverings(scene)
    acc, inside = None, np.zeros(len(p), dtype=bool)
    for cov in covs:
        D, gD = _disc_sqdist_grad(cov, p)
        _, dB = _barrier_of_sqdist(cov, D, with_grad=True)
        with np.errstate(invalid="ignore"):
            term = dB[:, None] * gD
        acc = term if acc is None else acc + term
        inside |= D <= 0
    with np.errstate(invalid="ignore"):
        grad = acc + 2.0 * covs[0].phi_weight * (p - _target(covs[0], target))
    grad[inside] = np.nan
    return grad


def _barrier_masked(kind: str, rho: float, gain: float, ell, reach, D: np.ndarray):
    """Gained barrier value and dB/dD, evaluated only where the barrier is active (the hot path); `ell` and
    `reach` are scalars or per-row arrays."""
    B = np.zeros_like(D)
    dB = np.zeros_like(D)
    idx = np.flatnonzero(D < reach**2)
    if idx.size:
        sub = (lambda v: v if np.ndim(v) == 0 else v[idx])  # noqa: E731
        B[idx], dB[idx] = _barrier_params(kind, rho, gain, sub(ell), D[idx])
    return B, dB


def fused_potentials(a, b, at, bt, c, ell, reach, *, kind: str, rho: float, gain: float, phi_weight: float):
    """`V_1, V_2` and their gradients in each row's obstacle frame, from frame coordinates `a, b` `(N,)`: the
    controllers' hot path (SPEC §3.2, one pass for both modes, no `(N, 2)` temporaries).

    `at, bt` (the target in the frame), `c` (apex), `ell` and `reach` are scalars or per-row arrays (the row's
    active obstacle). Returns `(V1, V2, ga1, gb1, ga2, gb2)`, identical (to rounding) to `potential_and_grad`
    rotated into the frame (tested).
    """
    w = phi_weight
    da, db = a - at, b - bt
    phi = w * (da * da + db * db)
    ga_phi, gb_phi = 2.0 * w * da, 2.0 * w * db
    out = []
    for sigma in (1.0, -1.0):
        bp = c + sigma * b
        mu = np.minimum(bp + a, 0.0) * SQRT1_2
        mv = np.minimum(bp - a, 0.0) * SQRT1_2
        D = mu * mu + mv * mv
        B, dB = _barrier_masked(kind, rho, gain, ell, reach, D)
        V = B + phi
        V[D <= 0] = np.inf
        k = np.sqrt(2.0) * dB
        out += [V, ga_phi + k * (mu - mv), gb_phi + sigma * k * (mu + mv)]
    V1, ga1, gb1, V2, ga2, gb2 = out
    return V1, V2, ga1, gb1, ga2, gb2


def both_potentials_frame(scene, a: np.ndarray, b: np.ndarray, target=None):
    """`V_1, V_2` and their gradients in the frame of one obstacle's covering `scene` (a :class:`Covering` or a
    single-obstacle Scene), from frame coordinates `a, b` `(N,)` (:func:`fused_potentials`)."""
    if target is None:
        at, bt = scene._target_frame
    else:
        tgt = np.asarray(target, dtype=float)
        at, bt = scene.to_frame(tgt.reshape(-1, 2))
        if tgt.ndim == 1:
            at, bt = at[0], bt[0]
    return fused_potentials(a, b, at, bt, scene.c, scene.ell, scene.barrier_reach, kind=scene.barrier_kind,
                            rho=scene.barrier_rho, gain=scene.barrier_gain, phi_weight=scene.phi_weight)
