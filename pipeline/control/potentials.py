"""Barrier and potential functions of SPEC §3.2 and §3.4, batched over `(N, 2)` points.

Paper: `φ(p) = -|p - p_T|^2`, `φ_q(p) = B(d_q(p))`, `V_q = φ_q - φ` on `O_q` (Eq. for V_q); SPEC applies the
barrier to `d_q / l_B^2`. All gradients are analytic.
"""

from __future__ import annotations

import numpy as np

from pipeline.control.covering import sq_dist_to_wedge_grad
from pipeline.control.scene import Scene

_SQRT1_2 = np.sqrt(0.5)


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


def _barrier_of_sqdist(scene: Scene, D: np.ndarray, with_grad: bool):
    """Barrier as a function of a squared distance `D`, and its derivative dB/dD (times the gain)."""
    val, grad = _raw_barrier_of_sqdist(scene, D, with_grad)
    g = scene.barrier_gain
    if g == 1.0:
        return val, grad
    return g * val, (None if grad is None else g * grad)


def _raw_barrier_of_sqdist(scene: Scene, D: np.ndarray, with_grad: bool):
    if scene.barrier_kind == "authors_code":
        rho = scene.barrier_rho
        d = np.sqrt(D)
        with np.errstate(divide="ignore", invalid="ignore"):
            val = np.where(d >= rho, 0.0, np.where(d > 0, (d - rho) ** 2 * np.log(rho / d), np.inf))
            if not with_grad:
                return val, None
            dBdd = 2.0 * (d - rho) * np.log(rho / d) - (d - rho) ** 2 / d
            dBdD = np.where(d >= rho, 0.0, np.where(d > 0, dBdd / (2.0 * d), -np.inf))
        return val, dBdD
    inv = 1.0 / scene.ell**2
    s = D * inv
    val = barrier(s, scene.barrier_rho)
    return val, (barrier_grad(s, scene.barrier_rho) * inv if with_grad else None)


def _target(scene: Scene, target) -> np.ndarray:
    return scene.p_T if target is None else np.asarray(target, dtype=float)


def potential(scene: Scene, q: int, points: np.ndarray, target=None) -> np.ndarray:
    """`V_q(p) = B(d_q(p)/l_B^2) + |p - p_T|^2` on `O_q`, `+inf` outside (SPEC §3.2). Shape `(N,)`.

    `target` (shape `(2,)` or `(N, 2)`) replaces `p_T` in `φ` only (moving target, SPEC §4); the covering
    stays that of the scene.
    """
    p = np.asarray(points, dtype=float)
    D, _ = sq_dist_to_wedge_grad(scene, q, p)
    B, _ = _barrier_of_sqdist(scene, D, with_grad=False)
    diff = p - _target(scene, target)
    return B + scene.phi_weight * np.einsum("ij,ij->i", diff, diff)


def potential_grad(scene: Scene, q: int, points: np.ndarray, target=None) -> np.ndarray:
    """Analytic `∇V_q(p)`, shape `(N, 2)`; NaN rows outside `O_q` (where `V_q = +inf`)."""
    p = np.asarray(points, dtype=float)
    D, gD = sq_dist_to_wedge_grad(scene, q, p)
    _, dB = _barrier_of_sqdist(scene, D, with_grad=True)
    with np.errstate(invalid="ignore"):
        grad = dB[:, None] * gD + 2.0 * scene.phi_weight * (p - _target(scene, target))
    grad[D <= 0] = np.nan
    return grad


def potential_and_grad(scene: Scene, q: int, points: np.ndarray, target=None) -> tuple[np.ndarray, np.ndarray]:
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


def _disc_sqdist_grad(scene: Scene, p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Squared distance to the disc `D_2r` around `p_0` and its gradient."""
    rel = p - scene.p_0
    norm = np.hypot(rel[:, 0], rel[:, 1])
    gap = np.maximum(norm - 2.0 * scene.obstacle_radius, 0.0)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = rel / norm[:, None]
    grad = 2.0 * gap[:, None] * np.nan_to_num(unit)
    return gap * gap, grad


def smooth_potential(scene: Scene, points: np.ndarray, target=None) -> np.ndarray:
    """`V_s(p) = |p - p_T|^2 + B(dist(p, D_2r)^2 / l_B^2)` (SPEC §3.4); +inf inside `D_2r`."""
    p = np.asarray(points, dtype=float)
    D, _ = _disc_sqdist_grad(scene, p)
    B, _ = _barrier_of_sqdist(scene, D, with_grad=False)
    diff = p - _target(scene, target)
    return B + scene.phi_weight * np.einsum("ij,ij->i", diff, diff)


def smooth_potential_grad(scene: Scene, points: np.ndarray, target=None) -> np.ndarray:
    """Analytic `∇V_s`, NaN rows inside `D_2r`."""
    p = np.asarray(points, dtype=float)
    D, gD = _disc_sqdist_grad(scene, p)
    _, dB = _barrier_of_sqdist(scene, D, with_grad=True)
    with np.errstate(invalid="ignore"):
        grad = dB[:, None] * gD + 2.0 * scene.phi_weight * (p - _target(scene, target))
    grad[D <= 0] = np.nan
    return grad


def _barrier_masked(scene: Scene, D: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Gained barrier value and dB/dD, evaluated only where the barrier is active (the hot path)."""
    B = np.zeros_like(D)
    dB = np.zeros_like(D)
    reach2 = scene.barrier_reach**2
    idx = np.flatnonzero(D < reach2)
    if idx.size:
        B[idx], dB[idx] = _barrier_of_sqdist(scene, D[idx], with_grad=True)
    return B, dB


def both_potentials_frame(scene: Scene, a: np.ndarray, b: np.ndarray, target=None):
    """`V_1, V_2` and their gradients in the obstacle frame, from frame coordinates `a, b` `(N,)`.

    The hybrid controller's hot path: one pass for both modes with no `(N, 2)` temporaries. Returns
    `(V1, V2, ga1, gb1, ga2, gb2)`; identical (to rounding) to `potential_and_grad` rotated into the frame.
    """
    if target is None:
        at, bt = scene._target_frame
    else:
        tgt = np.asarray(target, dtype=float)
        at, bt = scene.to_frame(tgt.reshape(-1, 2))
        if tgt.ndim == 1:
            at, bt = at[0], bt[0]
    w = scene.phi_weight
    da, db = a - at, b - bt
    phi = w * (da * da + db * db)
    ga_phi, gb_phi = 2.0 * w * da, 2.0 * w * db
    out = []
    for sigma in (1.0, -1.0):
        bp = scene.c + sigma * b
        mu = np.minimum(bp + a, 0.0) * _SQRT1_2
        mv = np.minimum(bp - a, 0.0) * _SQRT1_2
        D = mu * mu + mv * mv
        B, dB = _barrier_masked(scene, D)
        V = B + phi
        V[D <= 0] = np.inf
        k = np.sqrt(2.0) * dB
        out += [V, ga_phi + k * (mu - mv), gb_phi + sigma * k * (mu + mv)]
    V1, ga1, gb1, V2, ga2, gb2 = out
    return V1, V2, ga1, gb1, ga2, gb2
