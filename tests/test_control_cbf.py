"""The exact several-constraint CBF quadratic program of SPEC §3.6 (`pipeline.control.cbf`).

Checked against the single-disc closed form of SPEC §3.4 (bit for bit), the KKT conditions, an independent
iterative solver (Dykstra's alternating projections), and hand-solved corner cases.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.control import Arena, CBFController, Obstacle, Scene
from pipeline.control.cbf import cbf_qp, disc_constraints

SETTINGS = settings(max_examples=25, deadline=None)
SEEDS = st.integers(0, 2**31 - 1)
ARENA = Arena(x=[-200.0, 200.0], y=[-200.0, 200.0])  # every drawn target and disc inside


def closed_form(u_nom, rel, h, alpha):
    """CBFController._flow's expressions for one disc (SPEC §3.4), copied verbatim."""
    gh = 2.0 * rel
    gg = np.einsum("ij,ij->i", gh, gh)
    slack = np.einsum("ij,ij->i", gh, u_nom) + alpha * h
    active = slack < 0
    with np.errstate(divide="ignore", invalid="ignore"):
        corr = np.where(active, -slack / gg, 0.0)
        u = u_nom + corr[:, None] * gh
    return u, active, gg


def feasible_problem(rng, n, m):
    """Random `(u_nom, G, b)` with a known feasible point: `b = G·u* - s`, `s >= 0` (often 0, so that
    several lines meet at one point)."""
    G = rng.normal(0, 1, (n, m, 2)) * rng.uniform(0.1, 10, (n, m, 1))
    u_star = rng.normal(0, 3, (n, 2))
    s = rng.exponential(1.0, (n, m)) * (rng.random((n, m)) < 0.7)
    b = np.einsum("nmk,nk->nm", G, u_star) - s
    u_nom = rng.normal(0, 3, (n, 2))
    return u_nom, G, b


def residual_tol(u, u_nom, G, b, rtol=1e-8):
    """`G·u - b` and a tolerance scaled by the size of its terms."""
    resid = np.einsum("nmk,nk->nm", G, u) - b
    size = np.hypot(u[:, 0], u[:, 1]) + np.hypot(u_nom[:, 0], u_nom[:, 1])
    return resid, rtol * (np.linalg.norm(G, axis=-1) * size[:, None] + np.abs(b) + 1e-12)


def dykstra(u_nom, G, b, max_cycles=100_000):
    """Projection of `u_nom` onto `{u : G_i·u >= b_i}` by Dykstra's alternating projections (batched), run
    until every constraint holds to 1e-13 relative and 100 cycles move neither the iterate nor the increments
    (a fixed point of the iteration) by more than that: the iterate alone can stall long before the end."""
    x = u_nom.copy()
    incr = np.zeros(G.shape)
    state = np.concatenate([x[:, None], incr], axis=1)
    gg = np.einsum("nmk,nmk->nm", G, G)
    for cycle in range(max_cycles):
        for i in range(G.shape[1]):
            y = x + incr[:, i]
            viol = np.maximum(0.0, b[:, i] - np.einsum("nk,nk->n", G[:, i], y))
            x = y + (viol / gg[:, i])[:, None] * G[:, i]
            incr[:, i] = y - x
        if cycle % 100 == 99:
            resid, tol = residual_tol(x, u_nom, G, b, rtol=1e-13)
            new = np.concatenate([x[:, None], incr], axis=1)
            moved = np.abs(new - state).max(axis=(1, 2)) > 1e-13 * (np.abs(new).max(axis=(1, 2)) + 1)
            if (resid >= -tol).all() and not moved.any():
                break
            state = new
    return x


# ------------------------------------------------------------------------------------------ M = 1


@SETTINGS
@given(seed=SEEDS, alpha=st.floats(0.05, 5.0), k=st.floats(0.1, 3.0), r=st.floats(0.5, 8.0),
       cx=st.floats(-50, 50), cy=st.floats(-50, 50), theta=st.floats(-math.pi, math.pi))
def test_single_disc_is_the_closed_form_bit_for_bit(seed, alpha, k, r, cx, cy, theta):
    """M = 1: disc_constraints + cbf_qp equals CBFController._flow exactly, and the controller itself."""
    rng = np.random.default_rng(seed)
    scene = Scene(target=[cx + 12 * r * math.cos(theta), cy + 12 * r * math.sin(theta)],
                  obstacles=[Obstacle(center=[cx, cy], radius=r)], arena=ARENA)
    ang = rng.uniform(-math.pi, math.pi, 1000)
    rad = rng.uniform(0.0, 6 * r, 1000)
    pts = scene.p_0 + rad[:, None] * np.stack([np.cos(ang), np.sin(ang)], axis=1)
    pts[:5] = scene.p_0  # the degenerate rows: the agent at the centre
    u_nom = -k * (pts - scene.p_T)
    rel = pts - scene.p_0
    h_ref = np.einsum("ij,ij->i", rel, rel) - (2.0 * r) ** 2
    ref, ref_active, gg = closed_form(u_nom, rel, h_ref, alpha)

    G, b, h = disc_constraints(pts, scene.p_0[None, :], np.array([2.0 * r]), alpha)
    assert np.array_equal(h[:, 0], h_ref)
    sol = cbf_qp(u_nom, G, b)
    good = gg > 0
    assert np.array_equal(sol.u[good], ref[good])  # bit for bit, also the sign of zeros
    assert np.array_equal(sol.active[:, 0], ref_active)
    assert np.array_equal(sol.degenerate, ~good & ref_active) and sol.degenerate[:5].all()
    assert np.array_equal(sol.feasible, ~sol.degenerate)
    assert np.isfinite(sol.u).all() and np.array_equal(sol.u[~good], u_nom[~good])
    ctrl = CBFController(scene, k=k, alpha=alpha, u_max=None)
    ctrl_u = ctrl.flow_map(pts, ctrl.initial_state(pts))
    assert np.array_equal(ctrl_u[good], sol.u[good])
    assert ref_active.any() and (~ref_active).any()


@SETTINGS
@given(seed=SEEDS)
def test_a_constraint_that_always_holds_changes_nothing(seed):
    """The enumeration (M = 2) agrees with the closed form when the second constraint is `0·u >= -1`."""
    rng = np.random.default_rng(seed)
    u_nom, G, b = feasible_problem(rng, 300, 1)
    one = cbf_qp(u_nom, G, b)
    G2 = np.concatenate([G, np.zeros_like(G)], axis=1)
    two = cbf_qp(u_nom, G2, np.concatenate([b, -np.ones_like(b)], axis=1))
    np.testing.assert_allclose(two.u, one.u, rtol=1e-12, atol=1e-12 * np.abs(u_nom).max())
    assert two.feasible.all() and not two.degenerate.any() and not two.active[:, 1].any()


# ---------------------------------------------------------------------------------- several constraints


@SETTINGS
@given(seed=SEEDS, m=st.integers(2, 6))
def test_solution_is_feasible_and_satisfies_kkt(seed, m):
    """On feasible problems: every constraint holds, and `u - u_nom = Σ_active λ_i G_i` with `λ_i >= 0`."""
    rng = np.random.default_rng(seed)
    u_nom, G, b = feasible_problem(rng, 200, m)
    sol = cbf_qp(u_nom, G, b)
    assert sol.feasible.all() and not sol.degenerate.any()
    resid, tol = residual_tol(sol.u, u_nom, G, b)
    assert (resid >= -tol).all()
    assert (np.abs(resid[sol.active]) <= tol[sol.active]).all()  # active constraints are tight
    assert (sol.active.sum(axis=1) <= 2).all()
    corr = sol.u - u_nom
    for n in range(len(u_nom)):
        A = G[n, sol.active[n]]  # (|A|, 2)
        if len(A) == 0:
            assert np.array_equal(sol.u[n], u_nom[n])
            continue
        lam, *_ = np.linalg.lstsq(A.T, corr[n], rcond=None)
        scale = np.linalg.norm(A, axis=1).max() * (np.linalg.norm(corr[n]) + 1)
        np.testing.assert_allclose(A.T @ lam, corr[n], atol=1e-9 * scale)
        assert (lam * np.linalg.norm(A, axis=1) >= -1e-9 * (np.linalg.norm(corr[n]) + 1)).all()
    assert sol.active.any(axis=1).any() and (sol.active.sum(axis=1) == 2).any()


@settings(max_examples=10, deadline=None)
@given(seed=SEEDS, m=st.integers(2, 4))
def test_objective_matches_dykstra(seed, m):
    """An independent solver agrees on the optimal objective to 1e-7 (lines at least 0.2 rad from parallel,
    so that the alternating projections converge in a reasonable number of cycles)."""
    rng = np.random.default_rng(seed)
    n = 40
    ang = rng.uniform(0, 2 * math.pi, (n, 1)) + np.cumsum(rng.uniform(0.2, math.pi - 0.2, (n, m)), axis=1)
    G = rng.uniform(0.5, 2.0, (n, m, 1)) * np.stack([np.cos(ang), np.sin(ang)], axis=-1)
    u_star = rng.normal(0, 2, (n, 2))
    b = np.einsum("nmk,nk->nm", G, u_star) - rng.exponential(1.0, (n, m)) * (rng.random((n, m)) < 0.5)
    u_nom = rng.normal(0, 3, (n, 2))
    sine = np.abs(np.sin(ang[:, :, None] - ang[:, None, :]))
    offdiag = ~np.eye(m, dtype=bool)
    keep = (sine[:, offdiag] > math.sin(0.2)).all(axis=1)  # drop problems with nearly parallel lines
    u_nom, G, b = u_nom[keep], G[keep], b[keep]
    sol = cbf_qp(u_nom, G, b)
    ref = dykstra(u_nom, G, b)
    resid, tol = residual_tol(ref, u_nom, G, b)
    assert (resid >= -tol).all()  # Dykstra has converged
    obj = np.sum((sol.u - u_nom) ** 2, axis=1)
    obj_ref = np.sum((ref - u_nom) ** 2, axis=1)
    np.testing.assert_allclose(obj, obj_ref, rtol=1e-7, atol=1e-12)
    assert sol.feasible.all()


@SETTINGS
@given(seed=SEEDS, m=st.integers(1, 6))
def test_nominal_velocity_kept_when_already_safe(seed, m):
    """`u_nom` satisfying every constraint is returned exactly, with no constraint active."""
    rng = np.random.default_rng(seed)
    u_nom, G, _ = feasible_problem(rng, 300, m)
    b = np.einsum("nmk,nk->nm", G, u_nom) - rng.exponential(1.0, (300, m)) - 1e-6
    sol = cbf_qp(u_nom, G, b)
    assert np.array_equal(sol.u, u_nom) and not sol.active.any() and sol.feasible.all()


@SETTINGS
@given(seed=SEEDS, alpha=st.floats(0.1, 5.0), k=st.floats(0.5, 5.0))
def test_discs_keep_the_barrier_condition(seed, alpha, k):
    """Many agents heading into one of three discs: `d/dt h_i = ∇h_i·u >= -alpha h_i` for every disc."""
    rng = np.random.default_rng(seed)
    centers = np.array([[0.0, 0.0], [10.0, 1.0], [4.0, 9.0]]) + rng.normal(0, 0.3, (3, 2))
    radii = 2.0 * rng.uniform(1.5, 2.0, 3)
    pts = rng.uniform(-8, 18, (3000, 2))
    dist = np.linalg.norm(pts[:, None, :] - centers[None], axis=-1)
    outside = (dist > radii).all(axis=1)  # outside every margin disc: h_i > 0
    pts, near = pts[outside], np.argmin(dist[outside] - radii, axis=1)
    u_nom = -k * (pts - centers[near]) + rng.normal(0, 2.0, pts.shape)  # roughly towards the nearest centre
    G, b, h = disc_constraints(pts, centers, radii, alpha)
    assert (h > 0).all()
    sol = cbf_qp(u_nom, G, b)
    assert sol.feasible.all() and not sol.degenerate.any()  # u = 0 is always feasible where every h_i > 0
    hdot = np.einsum("nmk,nk->nm", G, sol.u)
    tol = 1e-9 * (np.linalg.norm(G, axis=-1) * np.linalg.norm(sol.u, axis=1)[:, None] + alpha * h)
    assert (hdot >= -alpha * h - tol).all()
    assert (np.einsum("nmk,nk->nm", G, u_nom) < -alpha * h).any(axis=1).mean() > 0.02  # the filter acts
    keep = ~sol.active.any(axis=1)
    np.testing.assert_array_equal(sol.u[keep], u_nom[keep])


# ------------------------------------------------------------------------------- degenerate, infeasible


@pytest.mark.parametrize("m", [1, 3])
def test_agent_at_a_centre_is_degenerate_not_nan(m):
    centers = np.array([[0.0, 0.0], [10.0, 0.0], [0.0, 10.0]])[:m]
    pts = np.array([[0.0, 0.0], [5.0, 5.0], [0.0, 0.0], [1.0, 0.0]])
    u_nom = np.array([[1.0, 2.0], [-1.0, -1.0], [0.0, 0.0], [-3.0, 0.0]])
    with np.errstate(all="raise"):
        G, b, _ = disc_constraints(pts, centers, np.full(m, 2.0), 1.0)
        sol = cbf_qp(u_nom, G, b)
    assert np.isfinite(sol.u).all()
    assert sol.degenerate.tolist() == [True, False, True, False]
    assert np.array_equal(sol.u[sol.degenerate], u_nom[sol.degenerate])
    assert not sol.feasible[sol.degenerate].any() and sol.feasible[~sol.degenerate].all()
    assert sol.active[0, 0] and sol.active[2, 0]  # the offending constraint is reported


def test_pinned_between_two_discs_is_infeasible():
    """On the segment between two overlapping margin discs no velocity satisfies both constraints."""
    G, b, h = disc_constraints(np.array([[0.0, 0.0], [0.0, 0.0]]), np.array([[-1.0, 0.0], [1.0, 0.0]]),
                               np.array([2.0, 2.0]), 1.0)
    assert (h < 0).all()
    sol = cbf_qp(np.array([[0.0, 0.0], [0.5, 1.0]]), G, b)
    assert not sol.feasible.any() and not sol.degenerate.any() and np.isfinite(sol.u).all()
    # candidates: u_nom (largest violation 3, resp. 4) beats each projection (6): u_nom is returned
    np.testing.assert_array_equal(sol.u, [[0.0, 0.0], [0.5, 1.0]])


@SETTINGS
@given(seed=SEEDS)
def test_conflicting_constraints_are_flagged(seed):
    """Three half-planes `n_i·u >= s_i > 0` with normals summing to zero have no common point."""
    rng = np.random.default_rng(seed)
    n = 200
    ang = rng.uniform(0, 2 * math.pi, (n, 1)) + np.array([0.0, 2 * math.pi / 3, 4 * math.pi / 3])
    G = np.stack([np.cos(ang), np.sin(ang)], axis=-1) * rng.uniform(0.5, 2.0, (n, 1, 1))
    b = rng.uniform(0.1, 2.0, (n, 3))
    half = n // 2
    b[half:] = -b[half:]  # the second half is feasible (it contains u = 0)
    sol = cbf_qp(rng.normal(0, 3, (n, 2)), G, b)
    assert np.isfinite(sol.u).all() and not sol.degenerate.any()
    assert not sol.feasible[:half].any() and sol.feasible[half:].all()


# ---------------------------------------------------------------------------------------- known corners


def test_two_constraint_corner():
    """Solutions solved by hand; a filter handling one constraint at a time fails the first two."""
    u_nom = np.zeros((4, 2))
    G = np.array([
        [[1.0, 0.0], [0.0, 1.0], [0.0, 0.0]],  # u_x >= 1, u_y >= 2: the corner (1, 2)
        [[1.0, 1.0], [1.0, -1.0], [-1.0, 0.0]],  # u_x + u_y >= 2, u_x - u_y >= 1, -u_x >= -5: (1.5, 0.5)
        [[1.0, 0.0], [1.0, 1.0], [0.0, 0.0]],  # u_x >= 1, u_x + u_y >= 0.5, from (0, -0.2): (1, -0.2)
        [[0.0, 1.0], [-1.0, 1.0], [1.0, 1.0]],  # u_y >= 1, u_y >= 3 + u_x, u_y >= 3 - u_x: (0, 3)
    ])
    b = np.array([[1.0, 2.0, -1.0], [2.0, 1.0, -5.0], [1.0, 0.5, -1.0], [1.0, 3.0, 3.0]])
    u_nom[2] = [0.0, -0.2]
    sol = cbf_qp(u_nom, G, b)
    np.testing.assert_allclose(sol.u, [[1.0, 2.0], [1.5, 0.5], [1.0, -0.2], [0.0, 3.0]], atol=1e-12)
    assert sol.active.tolist() == [[True, True, False], [True, True, False], [True, False, False],
                                   [False, True, True]]
    assert sol.feasible.all()


def test_agent_between_two_discs():
    """Heading down between discs at (0, 0) and (10, 0) (margin 4) from (5, 3): both bind, u = (0, -3)."""
    centers = np.array([[0.0, 0.0], [10.0, 0.0]])
    G, b, h = disc_constraints(np.array([[5.0, 3.0]]), centers, np.array([4.0, 4.0]), 1.0)
    np.testing.assert_array_equal(h, [[18.0, 18.0]])
    sol = cbf_qp(np.array([[0.0, -10.0]]), G, b)
    np.testing.assert_allclose(sol.u, [[0.0, -3.0]], atol=1e-12)
    assert sol.active.tolist() == [[True, True]] and sol.feasible.all()
    # either barrier alone steers the agent into the other disc (its constraint fails by more than 1)
    for i in range(2):
        one = cbf_qp(np.array([[0.0, -10.0]]), G[:, i:i + 1], b[:, i:i + 1]).u
        assert (G[0] @ one[0] < b[0] - 1.0).any()


def test_no_constraints():
    u_nom = np.array([[1.0, -2.0]])
    sol = cbf_qp(u_nom, np.zeros((1, 0, 2)), np.zeros((1, 0)))
    assert np.array_equal(sol.u, u_nom) and sol.feasible.all() and sol.active.shape == (1, 0)


@pytest.mark.parametrize("cls", ["CBFController", "SmoothController"])
def test_a_sampled_frame_solves_the_law_once(cls, monkeypatch):
    """The loop's frame reads the flow set and the flow map at one evaluation: a CBF's QP is solved once per frame,
    not twice (it was: `flow_set` and `flow_map` each called `_flow`), and the runs are the same."""
    from pipeline import control
    from pipeline.control.dense import benchmark_scene
    from pipeline.sim import SimSettings, WorldAlternating, simulate

    scene = benchmark_scene(seed=0)
    law = getattr(control, cls)(scene, u_max=1.0)
    calls = []
    real = type(law)._flow
    monkeypatch.setattr(type(law), "_flow", lambda self, m, target: calls.append(len(m)) or real(self, m, target))
    x0 = np.array([[7.0, 0.0], [0.0, 7.0]])
    r = simulate(scene, law, x0, sim=SimSettings(horizon=1.0, stop_on_success=False), disturbance=WorldAlternating(m=0.2),
                 record=False)
    frames = int(round(1.0 / 0.05))
    assert len(calls) == frames, f"{len(calls)} evaluations for {frames} frames"
    assert r.metrics["outcome"].tolist() == ["timed_out", "timed_out"]
