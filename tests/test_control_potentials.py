"""Potentials, barrier and controllers of SPEC §3.2-§3.4, and config validation of the control core.

The feedback laws are pure maps of the perceived point `m` and the logic state `xd`; the sampled-data step
(one jump where `D`, then the flow map of the new mode; the old `controller(m)`) is the closed loop's frame
(:func:`sampled_step`: `pipeline.hybrid.sampled.frame_update` on `pipeline.sim.SampledLoop`)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_control_geometry import scenes, world

from pipeline.config import build
from pipeline.control import (
    Barrier,
    CBFController,
    HybridController,
    Obstacle,
    Scene,
    SmoothController,
    barrier,
    barrier_grad,
    in_covering_set,
    in_diamond,
    potential,
    potential_and_grad,
    potential_grad,
    smooth_potential,
    smooth_potential_grad,
    sq_dist_to_wedge,
)
from pipeline.control.potentials import both_potentials_frame
from pipeline.errors import ConfigError
from pipeline.hybrid import State
from pipeline.hybrid.sampled import frame_update
from pipeline.plants import SingleIntegrator
from pipeline.sim import SampledLoop

SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])
KINDS = ("squared", "authors_code")


def target_frame(scene: Scene) -> float:
    return float(np.hypot(*np.subtract(scene.target, scene.obstacle_center)))


def box_points(scene: Scene, seed: int, n: int):
    """Random frame coordinates covering the diamond, the wedges' faces and the target."""
    rng = np.random.default_rng(seed)
    L = max(3 * scene.c, 1.5 * target_frame(scene))
    a = rng.uniform(-L, L, n)
    b = rng.uniform(-L, L, n)
    return a, b, world(scene, a, b)


def default_scene(**barrier) -> Scene:
    """The paper's scene: target (40, 0), one obstacle of radius 4 at the origin."""
    return Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)], barrier=Barrier(**barrier))


def sampled_step(ctrl, m: np.ndarray, xd: dict, target=None):
    """One frame of the sampled loop at the measurement `m` (what the old stateful `controller(m)` did): jump
    where `(m, xd) ∈ D` (priority), count the states left outside `C ∪ D`, hold `u = flow_map(m, xd+)`.

    Runs `pipeline.hybrid.sampled.frame_update` on the closed loop itself; returns `(u, xd+, jumped, outside)`."""
    loop = SampledLoop(ctrl.scene, ctrl, SingleIntegrator())
    m = np.asarray(m, dtype=float)
    x = State(m.copy(), m=m, target=target, **{k: np.array(v) for k, v in xd.items()})
    x, w, jumped, outside, _ = frame_update(loop, x, 0, np.random.default_rng(0), np.ones(len(m), dtype=bool))
    return w, {k: x.d[k] for k in ctrl.logic}, jumped, outside


def fd_grad(f, pts: np.ndarray, h: np.ndarray | float) -> np.ndarray:
    h = np.broadcast_to(np.asarray(h, dtype=float), (len(pts),))
    out = np.empty_like(pts)
    for k in range(2):
        e = np.zeros_like(pts)
        e[:, k] = h
        out[:, k] = (f(pts + e) - f(pts - e)) / (2 * h)
    return out


# --------------------------------------------------------------------------------------------- barrier


def test_barrier_shape():
    rho = 0.5
    s = np.linspace(1e-6, 2.0, 20001)
    B, dB = barrier(s, rho), barrier_grad(s, rho)
    assert (B >= 0).all() and (B[s > rho] == 0).all() and (B[s < rho] > 0).all()
    assert np.all(np.diff(B) <= 1e-15)  # non-increasing
    assert barrier(np.array([0.0, -1.0]), rho).tolist() == [np.inf, np.inf]
    assert np.isfinite(dB).all() and (dB <= 0).all()
    # C^1 at s = rho: value and slope vanish from the left
    assert barrier(np.array([rho * (1 - 1e-6)]), rho)[0] < 1e-11
    assert abs(barrier_grad(np.array([rho * (1 - 1e-6)]), rho)[0]) < 1e-5
    # derivative agrees with central differences
    s = np.linspace(0.01, 0.99, 500)
    h = 1e-7
    fd = (barrier(s + h, rho) - barrier(s - h, rho)) / (2 * h)
    np.testing.assert_allclose(barrier_grad(s, rho), fd, rtol=1e-5, atol=1e-6)


# ------------------------------------------------------------------------------------------ potentials


@SETTINGS
@given(scene=scenes(kinds=KINDS), q=st.sampled_from([1, 2]), seed=st.integers(0, 2**31 - 1))
def test_potential_positive_except_at_target_and_infinite_outside(scene, q, seed):
    a, b, pts = box_points(scene, seed, 3000)
    V = potential(scene, q, pts)
    inside = in_covering_set(scene, q, pts)
    assert np.isinf(V[~inside]).all() and (V[~inside] > 0).all()
    dist2 = np.einsum("ij,ij->i", pts - scene.p_T, pts - scene.p_T)
    Vin = V[inside]
    assert np.isfinite(Vin).all()
    # V_q = barrier (>= 0) + weight |p - p_T|^2, so V_q > 0 away from p_T
    assert (Vin >= scene.phi_weight * dist2[inside] * (1 - 1e-12)).all()
    assert (Vin[dist2[inside] > 0] > 0).all()
    # zero exactly at the target, positive next to it
    tgt = scene.p_T[None]
    assert potential(scene, q, tgt)[0] == 0.0
    ring = scene.p_T + 1e-3 * np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    assert (potential(scene, q, ring) > 0).all()
    # +inf on W_q's boundary and grows without bound towards it
    grad = potential_grad(scene, q, pts)
    assert np.isnan(grad[~inside]).all() and np.isfinite(grad[inside]).all()


@SETTINGS
@given(scene=scenes(kinds=KINDS), q=st.sampled_from([1, 2]))
def test_potential_blows_up_at_the_wedge(scene, q):
    # approach W_q's apex from outside along the symmetry axis: the barrier term grows without bound
    sigma = 1.0 if q == 1 else -1.0
    eps = np.array([2.0, 1e-1, 1e-3, 1e-6, 1e-9, -1e-6]) * scene.barrier_reach
    pts = world(scene, np.zeros(len(eps)), -sigma * (scene.c + eps))
    V = potential(scene, q, pts)
    barrier_term = V - scene.phi_weight * np.einsum("ij,ij->i", pts - scene.p_T, pts - scene.p_T)
    assert abs(barrier_term[0]) < 1e-9 * V[0]  # beyond the barrier's reach
    assert np.all(np.diff(barrier_term[1:-1]) > 0) and barrier_term[1] > 0
    assert np.isinf(V[-1])  # just inside W_q
    # and grows as |p| -> infinity
    far = world(scene, np.array([1e2, 1e3, 1e4]) * scene.c, np.zeros(3))
    assert np.all(np.diff(potential(scene, q, far)) > 0)


def _away_from_kinks(scene: Scene, q: int, pts: np.ndarray, h: float) -> np.ndarray:
    """Points in O_q whose distance to W_q is neither tiny (log singularity) nor within h of the
    barrier's reach (where the barrier is C^1 but not C^2)."""
    d = np.sqrt(sq_dist_to_wedge(scene, q, pts))
    reach = scene.barrier_reach
    return (d > 0.05 * reach) & (np.abs(d - reach) > 10 * h)


@SETTINGS
@given(scene=scenes(kinds=KINDS), q=st.sampled_from([1, 2]), seed=st.integers(0, 2**31 - 1))
def test_potential_grad_matches_finite_differences(scene, q, seed):
    _, _, pts = box_points(scene, seed, 1500)
    # oversample the barrier's band around the wedge
    rng = np.random.default_rng(seed + 1)
    sigma = 1.0 if q == 1 else -1.0
    a = rng.uniform(-2 * scene.c, 2 * scene.c, 1500)
    b = sigma * (np.abs(a) - scene.c - math.sqrt(2) * rng.uniform(0, 1.2 * scene.barrier_reach, 1500))
    pts = np.concatenate([pts, world(scene, a, b)])
    h = 1e-6 * max(scene.c, scene.barrier_reach)
    sel = in_covering_set(scene, q, pts) & _away_from_kinks(scene, q, pts, h)
    pts = pts[sel]
    g = potential_grad(scene, q, pts)
    fd = fd_grad(lambda p: potential(scene, q, p), pts, h)
    scale = np.hypot(g[:, 0], g[:, 1])[:, None] + 1.0
    assert np.all(np.abs(g - fd) <= 1e-4 * scale), np.max(np.abs(g - fd) / scale)
    # the one-pass version agrees
    V2, g2 = potential_and_grad(scene, q, pts)
    np.testing.assert_allclose(V2, potential(scene, q, pts), rtol=1e-12)
    np.testing.assert_allclose(g2, g, rtol=1e-12, atol=1e-12)


@SETTINGS
@given(scene=scenes(kinds=KINDS), seed=st.integers(0, 2**31 - 1))
def test_smooth_potential_grad_matches_finite_differences(scene, seed):
    rng = np.random.default_rng(seed)
    r, reach = scene.obstacle_radius, scene.barrier_reach
    ang = rng.uniform(-math.pi, math.pi, 2000)
    rad = np.concatenate([2 * r + rng.uniform(0, 1.2 * reach, 1000), rng.uniform(0, 3 * target_frame(scene), 1000)])
    pts = scene.p_0 + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    V = smooth_potential(scene, pts)
    inner = rad <= 2 * r
    assert np.isinf(V[inner]).all() and np.isfinite(V[~inner]).all()
    h = 1e-6 * max(r, reach)
    gap = rad - 2 * r
    sel = (gap > 0.05 * reach) & (np.abs(gap - reach) > 10 * h)
    g = smooth_potential_grad(scene, pts[sel])
    fd = fd_grad(lambda p: smooth_potential(scene, p), pts[sel], h)
    scale = np.hypot(g[:, 0], g[:, 1])[:, None] + 1.0
    assert np.all(np.abs(g - fd) <= 1e-4 * scale), np.max(np.abs(g - fd) / scale)
    assert np.isnan(smooth_potential_grad(scene, pts[inner])).all()


@SETTINGS
@given(scene=scenes(kinds=KINDS), q=st.sampled_from([1, 2]))
def test_no_critical_point_but_the_target(scene, q):
    """On a dense grid of O_q, |∇V_q| stays a fixed fraction of the attraction 2|p - p_T| (> 0 off p_T).

    Where the barrier opposes the attraction (the faces of W_q turned away from the target) the gradient
    keeps a tangential part of at least ~(a_T - c - sqrt(2) reach) / sqrt(2): the fraction is scaled by
    that margin, which the scene's validity condition keeps positive.
    """
    c, aT = scene.c, target_frame(scene)
    L = max(3 * c, 1.5 * aT)
    g = np.linspace(-L, L, 301)
    A, B = np.meshgrid(g, g)
    a, b = A.ravel(), B.ravel()
    # and a fine band along W_q's faces, where the barrier balances the attraction
    rng = np.random.default_rng(0)
    sigma = 1.0 if q == 1 else -1.0
    a2 = rng.uniform(-L, L, 20000)
    b2 = sigma * (np.abs(a2) - c - math.sqrt(2) * scene.barrier_reach * rng.uniform(0, 1.1, 20000) ** 2)
    a, b = np.concatenate([a, a2]), np.concatenate([b, b2])
    pts = world(scene, a, b)
    dT = np.hypot(a - aT, b)
    # O_q in floating point: a grid node within ~1e-154 of W_q (e.g. its apex, for a target direction
    # like 1e-206 rad) has u < 0 but a squared distance that underflows to 0, hence V_q = inf there.
    sel = in_covering_set(scene, q, pts) & (sq_dist_to_wedge(scene, q, pts) > 0) & (dT > 0.02 * c)
    grad = potential_grad(scene, q, pts[sel])
    norm = np.hypot(grad[:, 0], grad[:, 1])
    ratio = norm / (2 * scene.phi_weight * dT[sel])
    margin = (aT - c - math.sqrt(2) * scene.barrier_reach) / (aT + c)
    assert margin > 0
    assert ratio.min() > 0.25 * margin, (ratio.min(), margin, a[sel][ratio.argmin()], b[sel][ratio.argmin()])
    # the target itself is a critical point
    np.testing.assert_allclose(potential_grad(scene, q, scene.p_T[None]), [[0.0, 0.0]], atol=1e-12)


def test_smooth_potential_has_a_saddle_behind_the_obstacle():
    """Proposition 1's set K: V_s has a critical point on the ray behind the obstacle (V_q has none)."""
    scene = default_scene()
    r, reach = scene.obstacle_radius, scene.barrier_reach
    a = -(2 * r + np.linspace(1e-4, 1.5 * reach, 20001))
    pts = np.stack([a, np.zeros_like(a)], axis=1)
    ga = smooth_potential_grad(scene, pts)
    assert np.abs(ga[:, 1]).max() < 1e-9  # symmetric: the gradient stays on the axis
    sign = np.sign(ga[:, 0])
    assert sign[0] > 0 > sign[-1]  # barrier pushes back near the disc, target pulls beyond the barrier
    assert (np.diff(sign) != 0).sum() == 1
    behind = np.stack([np.linspace(-scene.c - 1e-6, -3 * scene.c, 20001), np.zeros(20001)], axis=1)
    for q in (1, 2):  # the hybrid potentials have no critical point on that ray (outside the diamond)
        gq = potential_grad(scene, q, behind)
        assert np.hypot(gq[:, 0], gq[:, 1]).min() > 1.0


@SETTINGS
@given(scene=scenes(kinds=KINDS), seed=st.integers(0, 2**31 - 1))
def test_both_potentials_frame_matches_potential_and_grad(scene, seed):
    a, b, pts = box_points(scene, seed, 2000)
    with np.errstate(invalid="ignore"):  # 0 * inf on W_q itself, where V_q = inf
        V1, V2, ga1, gb1, ga2, gb2 = both_potentials_frame(scene, a, b)
    for q, V, ga, gb in ((1, V1, ga1, gb1), (2, V2, ga2, gb2)):
        Vr, gr = potential_and_grad(scene, q, pts)
        fin = np.isfinite(Vr)
        np.testing.assert_array_equal(np.isfinite(V), fin)
        np.testing.assert_allclose(V[fin], Vr[fin], rtol=1e-9)
        # the readable potential (SPEC §3.2 as written) agrees with the fused path too
        Vp = potential(scene, q, pts)
        np.testing.assert_array_equal(np.isfinite(Vp), fin)
        np.testing.assert_allclose(V[fin], Vp[fin], rtol=1e-9)
        gw = ga[fin, None] * scene.e_a + gb[fin, None] * scene.e_b
        np.testing.assert_allclose(gw, gr[fin], rtol=1e-8, atol=1e-8 * (1 + np.abs(gr[fin]).max()))


@SETTINGS
@given(scene=scenes(kinds=KINDS), seed=st.integers(0, 2**31 - 1), moving=st.booleans())
def test_readable_potential_matches_the_controllers_fused_evaluation(scene, seed, moving):
    """`potential(scene, q, p)` (SPEC §3.2 as written) is what the hybrid controller's fused evaluation reads,
    for the rows it evaluates (near the wedge of their mode), with a fixed or a moving target."""
    a, b, pts = box_points(scene, seed, 2000)
    rng = np.random.default_rng(seed)
    target = scene.p_T + rng.normal(0.0, 0.5, pts.shape) if moving else None
    ctrl = HybridController(scene)
    xd = {"i": np.zeros(len(pts), dtype=np.int64), "q": rng.choice(np.array([1, 2], dtype=np.int8), len(pts))}
    ev = ctrl.evaluate(pts, xd, target)
    assert ev.idx.size > 0
    tgt = None if target is None else target[ev.idx]
    for q, V in ((1, ev.V1), (2, ev.V2)):
        Vr = potential(scene, q, pts[ev.idx], tgt)
        fin = np.isfinite(Vr)
        np.testing.assert_array_equal(np.isfinite(V), fin)
        np.testing.assert_allclose(V[fin], Vr[fin], rtol=1e-9)
    # rows left out are far from the wedge of their mode: there V_q = |p - p_T|^2 <= V_{3-q}
    rest = np.setdiff1d(np.arange(len(pts)), ev.idx)
    qr = xd["q"][rest]
    tr = None if target is None else target[rest]
    Vq = np.where(qr == 1, potential(scene, 1, pts[rest], tr), potential(scene, 2, pts[rest], tr))
    Vo = np.where(qr == 1, potential(scene, 2, pts[rest], tr), potential(scene, 1, pts[rest], tr))
    diff = pts[rest] - (scene.p_T if target is None else tr)
    np.testing.assert_allclose(Vq, scene.phi_weight * np.einsum("ij,ij->i", diff, diff), rtol=1e-12)
    assert (Vq <= Vo * (1 + 1e-12)).all()


def test_readable_potential_matches_the_fused_path_with_two_obstacles():
    """With several obstacles the controller evaluates `fused_potentials` on per-row arrays of its active
    obstacle `i`: the readable `potential(scene.covering(i), q, p)` agrees."""
    scene = Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0),
                                                 Obstacle(center=[-25.0, 12.0], radius=3.0, apex=6.0)])
    rng = np.random.default_rng(5)
    pts = rng.uniform([-50.0, -30.0], [50.0, 30.0], (4000, 2))
    ctrl = HybridController(scene)
    xd = ctrl.initial_state(pts)
    ev = ctrl.evaluate(pts, xd)
    assert set(np.unique(ev.i[ev.idx])) == {0, 1}
    for j in (0, 1):
        rows = ev.idx[ev.i[ev.idx] == j]
        sel = ev.i[ev.idx] == j
        for q, V in ((1, ev.V1[sel]), (2, ev.V2[sel])):
            Vr = potential(scene.covering(j), q, pts[rows])
            fin = np.isfinite(Vr)
            np.testing.assert_array_equal(np.isfinite(V), fin)
            np.testing.assert_allclose(V[fin], Vr[fin], rtol=1e-9)


# ----------------------------------------------------------------------------------------- controllers


@SETTINGS
@given(scene=scenes(kinds=KINDS), seed=st.integers(0, 2**31 - 1))
def test_hybrid_flow_and_jump_rule(scene, seed):
    """One frame = at most one jump by SPEC §3.3's rule, then u = -k ∇V_q+ (no speed limit)."""
    a, b, pts = box_points(scene, seed, 2000)
    ctrl = HybridController(scene, k=0.7, chi=1.1, lam=0.09, u_max=None, guard=False)  # the literal rule
    xd0 = ctrl.initial_state(pts)
    rng = np.random.default_rng(seed)
    q0 = rng.choice(np.array([1, 2], dtype=np.int8), len(pts))
    u, xd, jumped, outside = sampled_step(ctrl, pts, {"i": xd0["i"], "q": q0})
    q = xd["q"]
    assert np.isfinite(u).all()
    V = {q: potential(scene, q, pts) for q in (1, 2)}
    Vq = np.where(q0 == 1, V[1], V[2])
    Vo = np.where(q0 == 1, V[2], V[1])
    with np.errstate(invalid="ignore"):
        jump = (Vq > 0) & np.isfinite(Vo) & (Vq >= (1.1 - 0.09) * Vo)
    np.testing.assert_array_equal(q, np.where(jump, 3 - q0, q0))
    np.testing.assert_array_equal(jumped.astype(int), jump.astype(int))
    # flow: outside the diamond the velocity is the gradient of the (new) mode's potential
    dia = in_diamond(scene, pts)
    for mode in (1, 2):
        sel = (q == mode) & ~dia & in_covering_set(scene, mode, pts)
        np.testing.assert_allclose(u[sel], -0.7 * potential_grad(scene, mode, pts[sel]), rtol=1e-7,
                                   atol=1e-7 * (1 + np.abs(u[sel]).max(initial=0)))
    # after a jump the agent is in the flow set: V_q <= chi V_{3-q}
    Vnew = np.where(q == 1, V[1], V[2])
    Voth = np.where(q == 1, V[2], V[1])
    fin = np.isfinite(Vnew)
    assert (Vnew[fin] <= 1.1 * Voth[fin]).all()
    # inside the diamond: no jump, push out of W_q at push_speed, counted
    np.testing.assert_array_equal(outside.astype(int), dia.astype(int))
    np.testing.assert_array_equal(q[dia], q0[dia])
    np.testing.assert_allclose(np.hypot(u[dia, 0], u[dia, 1]), ctrl.push_speed)


def test_hybrid_hysteresis():
    """Between chi - lam and chi the mode is kept; the switch happens once the ratio passes chi - lam."""
    # a strong barrier (gain 1000) so that V_2 / V_1 spans the hysteresis band within |b| < 0.5
    scene = default_scene(gain=1000.0)
    ctrl = HybridController(scene, chi=1.1, lam=0.09)
    # behind the obstacle, V_2 / V_1 grows as b decreases (the barrier of W_2 grows)
    c = scene.c
    b = np.linspace(-0.5, 0.5, 2001)
    pts = np.stack([np.full_like(b, -c - 0.6), b], axis=1)
    V1, V2 = potential(scene, 1, pts), potential(scene, 2, pts)
    ratio = V2 / V1
    assert ratio.min() < 1.0 < 1.005 < ratio.max() and ratio.max() > 1.05
    keep = (ratio > 1.0) & (ratio < 1.1 - 0.09)
    switch = ratio >= 1.1 - 0.09
    assert keep.any() and switch.any()
    xd = ctrl.initial_state(pts)
    xd["q"][:] = 2
    _, xd, jumps, _ = sampled_step(ctrl, pts, xd)
    assert (xd["q"][keep] == 2).all()
    assert (xd["q"][switch] == 1).all()
    # and the switch is not undone at the next sample (hysteresis: 1.01 * V_2 > V_1 there)
    _, xd, again, _ = sampled_step(ctrl, pts, xd)
    jumps = jumps.astype(int) + again
    assert (jumps[switch] == 1).all() and (jumps[keep] == 0).all()


def test_hybrid_jumps_when_measurement_leaves_its_set_and_never_at_target():
    scene = default_scene()
    c = scene.c
    ctrl = HybridController(scene)
    below, above = np.array([[0.0, -c - 1.0]]), np.array([[0.0, c + 1.0]])
    xd = ctrl.initial_state(below)
    assert xd["q"].tolist() == [1]
    _, xd, jumps, _ = sampled_step(ctrl, above, xd)  # above the diamond: not in O_1, in O_2 -> jump
    jumps = jumps.astype(int)
    assert xd["q"].tolist() == [2] and jumps.tolist() == [1]
    _, xd, again, _ = sampled_step(ctrl, above, xd)
    assert (jumps + again).tolist() == [1]
    at_target = np.array([scene.p_T])
    xd = ctrl.initial_state(at_target)
    jumps = np.zeros(1, dtype=int)
    for _ in range(5):
        u, xd, jumped, _ = sampled_step(ctrl, at_target, xd)
        jumps += jumped
    assert jumps.tolist() == [0] and np.abs(u).max() == 0.0


def test_controllers_never_return_nan():
    scene = default_scene()
    g = np.linspace(-15, 15, 61)
    pts = np.stack(np.meshgrid(g, g), axis=-1).reshape(-1, 2)
    pts = np.concatenate([pts, [[0.0, 0.0], list(scene.p_T)]])
    for cls in (HybridController, SmoothController, CBFController):
        ctrl = cls(scene, u_max=10.0)
        xd = ctrl.initial_state(pts)
        u = ctrl.flow_map(pts, xd)
        assert np.isfinite(u).all(), cls
        assert (np.hypot(u[:, 0], u[:, 1]) <= 10.0 * (1 + 1e-12)).all()
        u_loop, _, _, _ = sampled_step(ctrl, pts, xd)
        assert np.isfinite(u_loop).all() and (np.hypot(*u_loop.T) <= 10.0 * (1 + 1e-12)).all(), cls
    # the smooth controller pushes radially out of the 2r disc where V_s is infinite (counted: outside C ∪ D)
    ctrl = SmoothController(scene, u_max=10.0)
    inner = pts[np.hypot(pts[:, 0], pts[:, 1]) < 2 * scene.obstacle_radius]
    u, _, _, pushed = sampled_step(ctrl, inner, ctrl.initial_state(inner))
    assert (np.einsum("ij,ij->i", u, inner) >= 0).all() and pushed.all()
    np.testing.assert_array_equal(u, ctrl.flow_map(inner, ctrl.initial_state(inner)))


@SETTINGS
@given(scene=scenes(kinds=KINDS), seed=st.integers(0, 2**31 - 1),
       alpha=st.floats(0.05, 5.0), k=st.floats(0.1, 3.0))
def test_cbf_filter_is_the_min_norm_safe_velocity(scene, seed, alpha, k):
    """u = argmin |u - u_nom|^2 s.t. ∇h·u >= -alpha h, h = |p - p_0|^2 - (2r)^2 (SPEC §3.4)."""
    rng = np.random.default_rng(seed)
    r = scene.obstacle_radius
    ang = rng.uniform(-math.pi, math.pi, 2000)
    rad = 2 * r + rng.exponential(2 * r, 2000)
    pts = scene.p_0 + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    ctrl = CBFController(scene, k=k, alpha=alpha, u_max=None)
    u = ctrl.flow_map(pts, ctrl.initial_state(pts))
    rel = pts - scene.p_0
    h = np.einsum("ij,ij->i", rel, rel) - (2 * r) ** 2
    gh = 2 * rel
    u_nom = -k * (pts - scene.p_T)
    lhs = np.einsum("ij,ij->i", gh, u)
    tol = 1e-9 * (np.abs(lhs) + alpha * np.abs(h) + 1)
    assert (lhs >= -alpha * h - tol).all()  # the CBF condition
    active = np.einsum("ij,ij->i", gh, u_nom) < -alpha * h
    assert active.any() and (~active).any()
    np.testing.assert_array_equal(u[~active], u_nom[~active])  # nominal when already safe
    np.testing.assert_allclose(lhs[active], -alpha * h[active], rtol=1e-9, atol=1e-9)  # tight otherwise
    # the correction is along ∇h, so no other feasible velocity is closer to u_nom
    corr = u - u_nom
    cross = corr[:, 0] * gh[:, 1] - corr[:, 1] * gh[:, 0]
    np.testing.assert_allclose(cross, 0.0, atol=1e-9 * (1 + np.abs(corr).max() * np.abs(gh).max()))
    v = u[:, None, :] + rng.normal(0, 1, (len(u), 8, 2))
    feas = np.einsum("ik,ijk->ij", gh, v) >= -alpha * h[:, None]
    dv = np.linalg.norm(v - u_nom[:, None, :], axis=2)
    du = np.linalg.norm(corr, axis=1)[:, None]
    assert (dv[feas] >= np.broadcast_to(du, dv.shape)[feas] * (1 - 1e-9) - 1e-9).all()
    # with the speed limit, the output is the same direction scaled down: the condition still holds
    ctrl_sat = CBFController(scene, k=k, alpha=alpha, u_max=1.0)
    us = ctrl_sat.flow_map(pts, ctrl_sat.initial_state(pts))
    assert (np.einsum("ij,ij->i", gh, us) >= -alpha * h - tol).all()


# ------------------------------------------------------------------------------------------ validation

SCENE_NODE = {"_target_": "pipeline.control.Scene", "target": [40.0, 0.0],
              "obstacles": [{"center": [0.0, 0.0], "radius": 4.0}]}


def _obstacle(**kw) -> dict:
    return {"obstacles": [{"center": [0.0, 0.0], "radius": 4.0} | kw]}


@pytest.mark.parametrize(
    ("patch", "field", "direct"),
    [
        (_obstacle(radius=0.0), "scene.obstacles[0].radius", "scene.obstacles[0].radius"),
        (_obstacle(radius=-1.0), "scene.obstacles[0].radius", "scene.obstacles[0].radius"),
        (_obstacle(radius=float("nan")), "scene.obstacles[0].radius", "scene.obstacles[0].radius"),
        ({"target": [5.0, 0.0]}, "scene.target", "scene.target"),  # inside the diamond (c = 11.3)
        ({"target": [0.0, 11.0]}, "scene.target", "scene.target"),  # inside W_1 / W_2 in any direction
        ({"target": [14.0, 0.0]}, "scene.target", "scene.target"),  # outside the wedges but within the reach
        ({"target": [0.0, 0.0]}, "scene.target", "scene.target"),
        ({"target": [1.0, 2.0, 3.0]}, "scene.target", "scene.target"),
        # wrong types and choices are the config's to check (by the signature), naming the element
        ({"target": ["a", "b"]}, "scene.target[0]", None),
        (_obstacle(center=[float("inf"), 0.0]), "scene.obstacles[0].center[0]", "scene.obstacles[0].center[0]"),
        (_obstacle(apex=5.0), "scene.obstacles[0].apex", "scene.obstacles[0].apex"),  # < sqrt(2) r
        ({"barrier": {"rho": 0.0}}, "scene.barrier.rho", "scene.barrier.rho"),
        ({"barrier": {"rho": 1.5}}, "scene.barrier.rho", "scene.barrier.rho"),
        ({"barrier": {"scale": -2.0}}, "scene.barrier.scale", "scene.barrier.scale"),
        ({"barrier": {"kind": "cubic"}}, "scene.barrier.kind", None),
        ({"barrier": {"gain": 0.0}}, "scene.barrier.gain", "scene.barrier.gain"),
    ],
)
def test_scene_validation(patch, field, direct):
    """A bad scene node is one ConfigError naming its key, through the config (`pipeline.config.build`) and,
    for range and cross-field rules, from the constructor itself."""
    node = SCENE_NODE | patch
    with pytest.raises(ConfigError) as info:
        build(node, "scene")
    assert info.value.field == field
    assert field in str(info.value) and "\n" not in str(info.value)
    if direct is not None:
        with pytest.raises(ConfigError) as info, np.errstate(invalid="ignore"):  # an infinite centre's frame
            Scene(**{k: v for k, v in node.items() if k != "_target_"})
        assert info.value.field == direct
        assert direct in str(info.value) and "\n" not in str(info.value)


def test_scene_from_its_config_node():
    """`pipeline.config.build(node, "scene")` (was `Scene.from_config`): every key of the node is the scene's."""
    scene = build(SCENE_NODE | _obstacle(apex=12.0) | {"barrier": {"rho": 8.0, "scale": 1.0, "kind": "authors_code"},
                                                      "name": "authors"}, "scene")
    assert isinstance(scene, Scene) and scene.name == "authors"
    assert scene.c == 12.0 and scene.ell == 1.0 and scene.barrier_kind == "authors_code"
    with pytest.raises(ConfigError) as info:
        build(SCENE_NODE | {"obstacle": {"radius": 4.0}}, "scene")  # the old single-obstacle key
    assert info.value.field == "scene.obstacle"
    with pytest.raises(ConfigError) as info:
        build(SCENE_NODE | _obstacle(radiuss=4.0), "scene")
    assert info.value.field == "scene.obstacles[0].radiuss"


@pytest.mark.parametrize("theta", np.linspace(0, 2 * math.pi, 9))
def test_scene_target_inside_wedge_rejected_in_any_direction(theta):
    # the wedges plus the barrier's reach extend to c + sqrt(2) * reach = 11.31 + 4.0 along e_a for r = 4
    near = [15.2 * math.cos(theta), 15.2 * math.sin(theta)]
    far = [15.4 * math.cos(theta), 15.4 * math.sin(theta)]
    with pytest.raises(ConfigError, match="scene.target"):
        Scene(target=near, obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])
    Scene(target=far, obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"chi": 1.0}, "controller.chi"),
        ({"chi": 0.9}, "controller.chi"),
        ({"chi": float("inf")}, "controller.chi"),
        ({"chi": 1.1, "lam": 0.0}, "controller.lam"),
        ({"chi": 1.1, "lam": -0.01}, "controller.lam"),
        ({"chi": 1.1, "lam": 0.11}, "controller.lam"),
        ({"chi": 1.1, "lam": 0.5}, "controller.lam"),
        ({"k": 0.0}, "controller.k"),
        ({"u_max": -1.0}, "controller.u_max"),
    ],
)
def test_hybrid_controller_validation(kwargs, field):
    scene = default_scene()
    with pytest.raises(ConfigError) as info:
        HybridController(scene, **kwargs)
    assert info.value.field == field
    # the same through the config node
    with pytest.raises(ConfigError) as info:
        build({"_target_": "pipeline.control.HybridController", **kwargs}, "controller", scene=scene)
    assert info.value.field == field and "\n" not in str(info.value)


def test_controller_validation_accepts_valid_and_checks_alpha():
    scene = default_scene()
    ctrl = HybridController(scene, chi=2.0, lam=0.99, u_max=None)
    assert (ctrl.chi, ctrl.lam, ctrl.u_max) == (2.0, 0.99, None)
    with pytest.raises(ConfigError) as info:
        CBFController(scene, alpha=0.0)
    assert info.value.field == "controller.alpha"
    with pytest.raises(ConfigError, match=r"controller\.scene: must be"):  # one line naming it (before: a TypeError)
        SmoothController("not a scene")
