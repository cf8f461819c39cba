"""Covering geometry of SPEC §3.1 on random valid scenes with any target direction.

Every check computes the obstacle frame and the wedges independently of `pipeline.control` (from the
target's angle), so a wrong frame orientation, apex or face shows up as a mismatch.
"""

from __future__ import annotations

import math

import numpy as np
from hypothesis import HealthCheck, assume, given, settings
from hypothesis import strategies as st

from pipeline.control import (
    Arena,
    Barrier,
    Obstacle,
    Scene,
    diamond_vertices,
    in_covering_set,
    in_diamond,
    sq_dist_to_wedge,
    sq_dist_to_wedge_grad,
)
from pipeline.errors import ConfigError

SETTINGS = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@st.composite
def scenes(draw, kinds=("squared",)):
    """A valid scene: random obstacle, radius 1..8, apex, barrier, and a target in a random direction
    at a distance outside the diamond and the barrier's reach (invalid draws are rejected)."""
    cx = draw(st.floats(-50, 50))
    cy = draw(st.floats(-50, 50))
    r = draw(st.floats(1.0, 8.0))
    kind = draw(st.sampled_from(kinds))
    apex = draw(st.one_of(st.none(), st.floats(1.05 * math.sqrt(2) * r, 4.0 * r)))
    c = 2 * math.sqrt(2) * r if apex is None else apex
    if kind == "squared":
        rho = draw(st.floats(0.05, 1.0))
        scale = draw(st.one_of(st.none(), st.floats(0.5, 2.0 * r)))
        reach = math.sqrt(rho) * (r if scale is None else scale)
    else:
        rho = draw(st.floats(0.1, 1.0)) * r
        scale = None
        reach = rho
    theta = draw(st.floats(-math.pi, math.pi))
    # far enough from both wedges (c + sqrt(2) reach) and from the smooth baseline's 2r disc
    min_dist = max(c + math.sqrt(2) * reach, 2 * r + reach)
    dist = min_dist * draw(st.floats(1.05, 4.0)) + draw(st.floats(0.0, 20.0))
    target = (cx + dist * math.cos(theta), cy + dist * math.sin(theta))
    # an arena that holds the obstacle and the target (the scene checks both lie inside it)
    arena = Arena(x=[min(cx, target[0]) - 1.0, max(cx, target[0]) + 1.0],
                  y=[min(cy, target[1]) - 1.0, max(cy, target[1]) + 1.0])
    try:
        scene = Scene(target=list(target), obstacles=[Obstacle(center=[cx, cy], radius=r, apex=apex)],
                      barrier=Barrier(rho=rho, scale=scale, kind=kind), arena=arena)
    except ConfigError:
        assume(False)
    return scene


def frame(scene: Scene):
    """Independent obstacle frame: (p_0, e_a, e_b) from the target's angle."""
    p0 = np.asarray(scene.obstacle_center, dtype=float)
    d = np.asarray(scene.target, dtype=float) - p0
    th = math.atan2(d[1], d[0])
    e_a = np.array([math.cos(th), math.sin(th)])
    e_b = np.array([-math.sin(th), math.cos(th)])
    return p0, e_a, e_b


def world(scene: Scene, a, b) -> np.ndarray:
    p0, e_a, e_b = frame(scene)
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    return p0 + a[:, None] * e_a + b[:, None] * e_b


def frame_samples(scene: Scene, seed: int, n: int = 4000, extent: float = 3.0):
    """Random frame coordinates in a box of half-width `extent * c`, plus points close to the diamond."""
    rng = np.random.default_rng(seed)
    c = scene.c
    a = rng.uniform(-extent * c, extent * c, n)
    b = rng.uniform(-extent * c, extent * c, n)
    # points at |a| + |b| = c (1 +- 1e-6): just inside / just outside the diamond's faces
    t = rng.uniform(-1, 1, n // 4)
    s = rng.choice([-1.0, 1.0], n // 4)
    scale = 1.0 + rng.choice([-1e-6, 1e-6], n // 4)
    a2 = t * c * scale
    b2 = s * (1 - np.abs(t)) * c * scale
    return np.concatenate([a, a2]), np.concatenate([b, b2])


def test_scene_frame_matches_independent_frame():
    for theta in np.linspace(-math.pi, math.pi, 13):
        p0 = np.array([3.0, -7.0])
        target = p0 + 40 * np.array([math.cos(theta), math.sin(theta)])
        scene = Scene(target=target.tolist(), obstacles=[Obstacle(center=p0.tolist(), radius=4)],
                      arena=Arena(x=[-60.0, 60.0], y=[-60.0, 60.0]))
        _, e_a, e_b = frame(scene)
        np.testing.assert_allclose(scene.e_a, e_a, atol=1e-12)
        np.testing.assert_allclose(scene.e_b, e_b, atol=1e-12)
        a, b = scene.to_frame(target[None])
        np.testing.assert_allclose([a[0], b[0]], [40.0, 0.0], atol=1e-9)


@SETTINGS
@given(scene=scenes(), seed=st.integers(0, 2**31 - 1))
def test_covering_sets_are_complement_of_diamond(scene, seed):
    a, b = frame_samples(scene, seed)
    pts = world(scene, a, b)
    c = scene.c
    o1 = in_covering_set(scene, 1, pts)
    o2 = in_covering_set(scene, 2, pts)
    dia = in_diamond(scene, pts)
    # O_1 ∪ O_2 is exactly the complement of the diamond
    np.testing.assert_array_equal(o1 | o2, ~dia)
    # ... and the diamond is |a| + |b| <= c in the independently computed frame
    margin = 1e-9 * (c + np.abs(a) + np.abs(b))
    clear = np.abs(np.abs(a) + np.abs(b) - c) > margin
    np.testing.assert_array_equal(dia[clear], (np.abs(a) + np.abs(b) <= c)[clear])
    # O_1 = {b < |a| - c} (pass with b < 0), O_2 = {b > c - |a|} (pass with b > 0)
    clear1 = np.abs(b - (np.abs(a) - c)) > margin
    clear2 = np.abs(b - (c - np.abs(a))) > margin
    np.testing.assert_array_equal(o1[clear1], (b < np.abs(a) - c)[clear1])
    np.testing.assert_array_equal(o2[clear2], (b > c - np.abs(a))[clear2])
    # the target lies in both sets
    tgt = np.asarray(scene.target, dtype=float)[None]
    assert in_covering_set(scene, 1, tgt)[0] and in_covering_set(scene, 2, tgt)[0]
    assert not in_diamond(scene, tgt)[0]


@SETTINGS
@given(scene=scenes(), seed=st.integers(0, 2**31 - 1))
def test_diamond_contains_disc_of_radius_2r_and_lies_in_ball_c(scene, seed):
    rng = np.random.default_rng(seed)
    p0 = np.asarray(scene.obstacle_center, dtype=float)
    r = scene.obstacle_radius
    ang = rng.uniform(-math.pi, math.pi, 3000)
    unit = np.stack([np.cos(ang), np.sin(ang)], axis=1)
    # inside the disc of radius 2r (up to its boundary) -> inside the diamond (default apex: c = 2 sqrt(2) r)
    if scene.obstacles[0].apex is None:
        rad = 2 * r * (1 - 1e-9) * np.sqrt(rng.uniform(0, 1, len(ang)))
        rad[:200] = 2 * r * (1 - 1e-9)
        assert in_diamond(scene, p0 + rad[:, None] * unit).all()
    # the obstacle itself is always inside the diamond (c > sqrt(2) r)
    rad = r * np.sqrt(rng.uniform(0, 1, len(ang)))
    assert in_diamond(scene, p0 + rad[:, None] * unit).all()
    # outside the ball of radius c -> outside the diamond
    rad = scene.c * (1 + 1e-9) + rng.exponential(scene.c, len(ang))
    assert not in_diamond(scene, p0 + rad[:, None] * unit).any()
    # its corners are at distance c along +-e_a, +-e_b
    _, e_a, e_b = frame(scene)
    corners = p0 + scene.c * np.array([e_a, e_b, -e_a, -e_b])
    np.testing.assert_allclose(diamond_vertices(scene), corners, atol=1e-9 * (1 + np.abs(corners).max()))


def wedge_boundary(scene: Scene, q: int, length: float, h: float) -> np.ndarray:
    """Dense samples of the two rays bounding W_q: apex at b = -c (q=1) or b = +c (q=2)."""
    s = np.arange(0.0, length, h)
    sigma = 1.0 if q == 1 else -1.0
    apex_b = -sigma * scene.c
    a = np.concatenate([s, -s]) / math.sqrt(2)
    b = apex_b + sigma * np.concatenate([s, s]) / math.sqrt(2)
    return world(scene, a, b)


def inside_wedge(scene: Scene, q: int, a, b):
    return b >= np.abs(a) - scene.c if q == 1 else b <= scene.c - np.abs(a)


@SETTINGS
@given(scene=scenes(), q=st.sampled_from([1, 2]), seed=st.integers(0, 2**31 - 1))
def test_sq_dist_to_wedge_matches_brute_force(scene, q, seed):
    rng = np.random.default_rng(seed)
    c = scene.c
    a = rng.uniform(-3 * c, 3 * c, 300)
    b = rng.uniform(-3 * c, 3 * c, 300)
    pts = world(scene, a, b)
    D = sq_dist_to_wedge(scene, q, pts)
    inside = inside_wedge(scene, q, a, b)
    # zero inside W_q (the complement of O_q), positive outside
    assert (D[inside] == 0).all()
    margin = 1e-9 * c
    strictly_out = ~inside_wedge(scene, q, a - margin * np.sign(a), b + (margin if q == 2 else -margin))
    assert (D[strictly_out] > 0).all()
    np.testing.assert_array_equal(D > 0, in_covering_set(scene, q, pts))
    # outside: squared distance to the densely sampled boundary rays
    out = ~inside
    h = 2e-3 * c
    bnd = wedge_boundary(scene, q, length=8 * c, h=h)
    diff = pts[out][:, None, :] - bnd[None, :, :]
    brute = np.min(np.einsum("ijk,ijk->ij", diff, diff), axis=1)
    d_true = np.sqrt(D[out])
    # the samples lie on the wedge, so brute >= true; sampling error at most h/2 in distance
    assert (brute >= D[out] - 1e-9 * (1 + D[out])).all()
    assert (np.sqrt(brute) - d_true <= h / 2 + 1e-9 * (1 + d_true)).all()


@SETTINGS
@given(scene=scenes(), q=st.sampled_from([1, 2]), seed=st.integers(0, 2**31 - 1))
def test_sq_dist_to_wedge_grad_matches_finite_differences(scene, q, seed):
    rng = np.random.default_rng(seed)
    c = scene.c
    a = rng.uniform(-3 * c, 3 * c, 400)
    b = rng.uniform(-3 * c, 3 * c, 400)
    pts = world(scene, a, b)
    D, g = sq_dist_to_wedge_grad(scene, q, pts)
    np.testing.assert_array_equal(D, sq_dist_to_wedge(scene, q, pts))
    assert (g[D == 0] == 0).all()
    h = 1e-5 * c
    fd = np.empty_like(pts)
    for k in range(2):
        e = np.zeros(2)
        e[k] = h
        fd[:, k] = (sq_dist_to_wedge(scene, q, pts + e) - sq_dist_to_wedge(scene, q, pts - e)) / (2 * h)
    # d_q is C^1 with a piecewise-constant Hessian (norm <= 2): central differences are within ~h
    np.testing.assert_allclose(g, fd, atol=4 * h + 1e-7 * (1 + np.abs(g).max()))
    # |grad d_q|^2 = 4 d_q (squared distance to a convex set)
    np.testing.assert_allclose(np.einsum("ij,ij->i", g, g), 4 * D, rtol=1e-9, atol=1e-9 * c * c)


def test_wedge_apex_side():
    """W_1's apex is at b = -c (mode 1 passes below the obstacle), W_2's at b = +c."""
    scene = Scene(target=[0.0, 40.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4)],  # e_a = +y, e_b = -x
                  arena=Arena(x=[-50.0, 50.0], y=[-50.0, 50.0]))
    c = scene.c
    below = world(scene, [0.0], [-c - 1.0])  # just beyond W_1's apex: in O_1
    above = world(scene, [0.0], [c + 1.0])
    assert in_covering_set(scene, 1, below)[0] and not in_covering_set(scene, 1, above)[0]
    assert in_covering_set(scene, 2, above)[0] and not in_covering_set(scene, 2, below)[0]
    np.testing.assert_allclose(sq_dist_to_wedge(scene, 1, below), [1.0], rtol=1e-9)
    np.testing.assert_allclose(sq_dist_to_wedge(scene, 2, above), [1.0], rtol=1e-9)
