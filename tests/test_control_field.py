"""Fields of several obstacles (SPEC §3.6): derived quantities, V1–V3, random valid fields, the authors' field.

The checks recompute each condition independently (Python loops, the diamond from its four corners) so that a
wrong frame, pair index or shortfall shows up as a mismatch.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.control import Arena, Barrier, Obstacle, Scene
from pipeline.control.fields import (
    AUTHORS_MULTI,
    analyse_field,
    authors_multi_analysis,
    random_field,
    two_in_row,
)
from pipeline.control.validity import (
    DEFAULT_ARENA,
    barrier_reach,
    cell_distance,
    check_field,
    default_apex,
    diamond_signed_distance,
    field_violations,
    influence_radius,
    to_frames,
)
from pipeline.errors import ConfigError

SETTINGS = settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
S2 = math.sqrt(2.0)
LOOP = dict(h=1.0, u_max=10.0, T_s=0.05)


def _rot(theta: float) -> np.ndarray:
    return np.array([[math.cos(theta), -math.sin(theta)], [math.sin(theta), math.cos(theta)]])


def _default_R(r):
    return 2 * S2 * np.asarray(r) + S2 * math.sqrt(0.5) * np.asarray(r)


# ----------------------------------------------------------------------------- derived quantities
def test_derived_quantities_defaults():
    r = np.array([4.0, 3.0])
    apex = default_apex(r, [np.nan, 5.0])
    assert apex == pytest.approx([8 * S2, 5.0])
    assert default_apex(r) == pytest.approx(2 * S2 * r)
    rho = barrier_reach(0.5, r)
    assert rho == pytest.approx(math.sqrt(0.5) * r)
    R = influence_radius(default_apex(r), rho)
    assert R == pytest.approx((2 * S2 + 1) * r)  # SPEC: R_i ≈ 3.83 r_i
    assert R[0] == pytest.approx(15.3137, abs=1e-4)


@SETTINGS
@given(st.integers(0, 10_000))
def test_cell_distance_matches_loop(seed):
    rng = np.random.default_rng(seed)
    p, c, R = rng.normal(0, 20, (7, 2)), rng.normal(0, 20, (4, 2)), rng.uniform(1, 10, 4)
    D = cell_distance(p, c, R)
    assert D.shape == (7, 4)
    for n in range(7):
        for m in range(4):
            assert D[n, m] == pytest.approx(math.dist(p[n], c[m]) - R[m])


@SETTINGS
@given(st.floats(-math.pi, math.pi), st.floats(2.0, 20.0), st.floats(0.0, 2 * math.pi), st.floats(0.0, 30.0))
def test_diamond_distance_against_corners(phi, apex, psi, rad):
    """The diamond is the square with corners c ± apex e_a, c ± apex e_b (e_a towards the target)."""
    c = np.array([3.0, -2.0])
    target = c + 50 * np.array([math.cos(phi), math.sin(phi)])
    e_a = np.array([math.cos(phi), math.sin(phi)])
    e_b = np.array([-e_a[1], e_a[0]])
    corners = [c + apex * e_a, c + apex * e_b, c - apex * e_a, c - apex * e_b]
    p = c + rad * np.array([math.cos(psi), math.sin(psi)])

    def seg_dist(x, a, b):
        t = np.clip((x - a) @ (b - a) / ((b - a) @ (b - a)), 0, 1)
        return float(np.linalg.norm(x - a - t * (b - a)))

    boundary = min(seg_dist(p, corners[k], corners[(k + 1) % 4]) for k in range(4))
    a, b = (p - c) @ e_a, (p - c) @ e_b
    inside = abs(a) + abs(b) <= apex
    sd = diamond_signed_distance(p[None], c[None], [apex], target)[0, 0]
    assert sd == pytest.approx(-boundary if inside else boundary, abs=1e-9)
    A, B = to_frames(p[None], c[None], target)
    assert (A[0, 0], B[0, 0]) == pytest.approx((a, b))


# ----------------------------------------------------------------------------- the default scene, M = 1
def test_default_single_obstacle_scene_is_valid():
    v = field_violations([[0.0, 0.0]], [4.0], (40.0, 0.0), apex=None, reach=barrier_reach(0.5, 4.0), **LOOP,
                         arena=DEFAULT_ARENA, starts=[(-12.0, 2.0), (-37.0, -17.0)])
    assert v == []
    check_field([[0.0, 0.0]], [4.0], (40.0, 0.0), **LOOP, arena=DEFAULT_ARENA, starts=[(-12.0, 2.0), (-37.0, -17.0)])


@SETTINGS
@given(st.floats(1.0, 8.0), st.floats(1.05, 4.0), st.floats(0.05, 1.0), st.floats(0.3, 2.0),
       st.floats(-math.pi, math.pi), st.floats(0.5, 60.0))
def test_v1_agrees_with_single_obstacle_scene(r, f, rho_b, s, phi, dist):
    """V1 is the single-obstacle Scene's target rule (it adds a rule for the smooth baseline's disc 2r)."""
    target = (dist * math.cos(phi), dist * math.sin(phi))
    apex, scale = f * S2 * r, s * r
    v1 = [v for v in field_violations([[0.0, 0.0]], [r], target, apex=apex, reach=barrier_reach(rho_b, scale))
          if v.condition == "V1"]
    try:
        Scene(target=list(target), obstacles=[Obstacle([0.0, 0.0], r, apex=apex)], barrier=Barrier(rho=rho_b, scale=scale),
              arena=Arena(x=[-70.0, 70.0], y=[-70.0, 70.0]))  # the target rule alone: every target inside the arena
        accepted = True
    except ConfigError:
        accepted = False
    if accepted:
        assert v1 == []
    if v1 == [] and dist - 2 * r > math.sqrt(rho_b) * scale + 1e-9:
        assert accepted


# ----------------------------------------------------------------------------- random fields
@SETTINGS
@given(st.integers(0, 2**31 - 1), st.integers(1, 5), st.sampled_from([0.0, 0.5]), st.booleans())
def test_random_field_valid_and_deterministic(seed, M, inflation, sampled):
    loop = LOOP if sampled else dict(h=1.0, u_max=None, T_s=None)
    starts = [(-40.0, 0.0), (-30.0, 20.0)]
    kw = dict(seed=seed, starts=starts, inflation=inflation, radius_range=(2.0, 3.5), **loop)
    c, r = random_field(M, **kw)
    assert c.shape == (M, 2) and r.shape == (M,)
    assert field_violations(c, r, (40.0, 0.0), arena=DEFAULT_ARENA, starts=starts, inflation=inflation, **loop) == []
    # independent recomputation of every condition
    rr = r + inflation
    R = _default_R(rr)
    for i in range(M):
        assert math.dist((40.0, 0.0), c[i]) > R[i]
        assert -50 <= c[i, 0] - r[i] and c[i, 0] + r[i] <= 50 and -30 <= c[i, 1] - r[i] and c[i, 1] + r[i] <= 30
        for j in range(i + 1, M):
            gap = math.dist(c[i], c[j]) - R[i] - R[j] - 1.0
            assert gap > (2 * 0.5 if sampled else 0.0)
    c2, r2 = random_field(M, **kw)
    assert np.array_equal(c, c2) and np.array_equal(r, r2)


def test_random_field_seeds_differ_and_margin_holds():
    a = random_field(3, seed=1, margin=1.0)
    b = random_field(3, seed=2, margin=1.0)
    assert not np.array_equal(a[0], b[0])
    for c, r in (a, b):
        assert field_violations(c, r, (40.0, 0.0), arena=DEFAULT_ARENA, margin=1.0, **LOOP) == []


def test_random_field_gives_up_with_config_error():
    with pytest.raises(ConfigError) as e:
        random_field(30, seed=0, max_restarts=3)
    assert e.value.field == "scene.n_obstacles" and "no valid field" in str(e.value)
    assert "\n" not in str(e.value)


# ----------------------------------------------------------------------------- violations
def _row(M, spacing=60.0):
    """M discs of radius 3 on the line y = -200, far apart, far from the target."""
    return np.stack([np.arange(M) * spacing, np.full(M, -200.0)], axis=1), np.full(M, 3.0)


@SETTINGS
@given(st.integers(2, 6), st.data(), st.floats(0.01, 5.0))
def test_v2_shortfall_is_the_displacement(M, data, delta):
    c, r = _row(M)
    i = data.draw(st.integers(0, M - 2))
    j = i + 1
    R = _default_R(r)
    c[j] = c[i] + [R[i] + R[j] + 1.0 - delta, 0.0]  # delta below V2's threshold
    for k in range(j + 1, M):  # keep later discs clear of the moved one
        c[k, 0] = c[j, 0] + (k - j) * 60.0
    v = field_violations(c, r, (0.0, 400.0), h=1.0)  # continuous loop: no V3
    assert [(x.field, x.condition) for x in v] == [(f"scene.obstacles[{i},{j}]", "V2")]
    assert v[0].shortfall == pytest.approx(delta, abs=1e-9)
    assert v[0].obstacles == (i, j)
    with pytest.raises(ConfigError) as e:
        check_field(c, r, (0.0, 400.0), h=1.0)
    assert e.value.field == f"scene.obstacles[{i},{j}]" and "V2" in e.value.reason


@SETTINGS
@given(st.floats(0.01, 0.49), st.floats(1.0, 20.0), st.floats(0.01, 0.2))
def test_v3_shortfall_per_side(delta, u_max, T_s):
    c, r = _row(2)
    R = _default_R(r)
    step = u_max * T_s
    if delta >= step:
        delta = step / 2
    c[1] = c[0] + [R[0] + R[1] + 1.0 + 2 * step - 2 * delta, 0.0]  # V3 short by delta per side, V2 holds
    v = field_violations(c, r, (0.0, 400.0), h=1.0, u_max=u_max, T_s=T_s)
    assert [(x.field, x.condition) for x in v] == [("scene.obstacles[0,1]", "V3")]
    assert v[0].shortfall == pytest.approx(delta, abs=1e-9)
    assert field_violations(c, r, (0.0, 400.0), h=1.0) == []  # continuous loop: V3 does not apply


@SETTINGS
@given(st.integers(1, 5), st.data(), st.floats(0.01, 5.0), st.floats(-math.pi, math.pi))
def test_v1_shortfall(M, data, delta, phi):
    c, r = _row(M)
    i = data.draw(st.integers(0, M - 1))
    R = _default_R(r)
    target = c[i] + (R[i] - delta) * np.array([math.cos(phi), math.sin(phi)])
    v = [x for x in field_violations(c, r, target) if x.condition == "V1"]
    assert [x.field for x in v] == [f"scene.obstacles[{i}]"]
    assert v[0].shortfall == pytest.approx(delta, abs=1e-9)
    assert "move the target" in v[0].message


@SETTINGS
@given(st.integers(1, 4), st.data(), st.floats(0.01, 3.0), st.sampled_from(["x_min", "x_max", "y_min", "y_max"]))
def test_arena_shortfall(M, data, delta, side):
    arena = ((-500.0, 500.0), (-300.0, 300.0))
    c, r = _row(M)
    c[:, 1] = 0.0
    c[:, 0] -= 100.0
    i = data.draw(st.integers(0, M - 1))
    axis, sign = {"x_min": (0, -1), "x_max": (0, 1), "y_min": (1, -1), "y_max": (1, 1)}[side]
    c[i, axis] = sign * (arena[axis][1] - r[i] + delta)
    v = field_violations(c, r, (0.0, 250.0), arena=arena)
    v = [x for x in v if x.condition == "arena"]
    assert [x.field for x in v] == [f"scene.obstacles[{i}]"]
    assert v[0].shortfall == pytest.approx(delta, abs=1e-9) and side in v[0].message


@SETTINGS
@given(st.floats(-math.pi, math.pi), st.floats(0.01, 3.0), st.floats(-0.9, 0.9), st.sampled_from([0.0, 0.5]))
def test_start_shortfall_any_direction(phi, delta, t, inflation):
    """A start `delta` inside the diamond's face (any target direction) is reported with shortfall delta +
    clearance; `delta` outside a clearance is not."""
    c, r = np.array([[0.0, 0.0], [200.0, 0.0]]), np.array([4.0, 4.0])
    target = 60 * np.array([math.cos(phi), math.sin(phi)])
    e_a = target / 60
    e_b = np.array([-e_a[1], e_a[0]])
    apex = 2 * S2 * (r[0] + inflation)
    delta = min(delta, 0.5 * (1 - abs(t)) * apex / S2)  # the nearest face stays the one moved across
    # a point on the face from (a, b) = (0, apex) to (apex, 0), moved inward by delta along the face's normal
    face = (0.5 + 0.5 * t) * apex * e_a + (0.5 - 0.5 * t) * apex * e_b
    n = (e_a + e_b) / S2
    starts = [(-30.0, -300.0), face - delta * n, face + (inflation + delta) * n]
    v = [x for x in field_violations(c, r, target, starts=starts, inflation=inflation) if x.condition == "start"]
    assert [(x.field, x.obstacles) for x in v] == [("init.points[1]", (0,))]
    assert v[0].shortfall == pytest.approx(delta + inflation, abs=1e-9)


def test_violations_ordered_and_all_reported():
    c = np.array([[0.0, 0.0], [10.0, 0.0], [48.0, 0.0]])
    r = np.array([4.0, 4.0, 4.0])
    v = field_violations(c, r, (40.0, 0.0), **LOOP, arena=DEFAULT_ARENA, starts=[(1.0, 1.0)])
    kinds = [x.condition for x in v]
    assert kinds == sorted(kinds, key=["arena", "V1", "V2", "V3", "start"].index)
    assert set(kinds) == {"arena", "V1", "V2", "V3", "start"}
    assert ("scene.obstacles[2]", "arena") in [(x.field, x.condition) for x in v]
    assert all("\n" not in x.line and x.line.startswith(x.field + ": ") for x in v)
    with pytest.raises(ConfigError) as e:
        check_field(c, r, (40.0, 0.0), **LOOP, arena=DEFAULT_ARENA, starts=[(1.0, 1.0)])
    assert e.value.field == v[0].field and f"{len(v) - 1} more" in str(e.value)


@SETTINGS
@given(st.floats(-math.pi, math.pi), st.integers(0, 1000))
def test_violations_invariant_under_rotation(theta, seed):
    """The obstacle frames follow the target: rotating the whole field changes no shortfall."""
    rng = np.random.default_rng(seed)
    c, r = rng.uniform(-30, 30, (4, 2)), rng.uniform(2, 5, 4)
    target, starts = rng.uniform(-30, 30, 2), rng.uniform(-40, 40, (5, 2))
    Q = _rot(theta)
    v0 = field_violations(c, r, target, starts=starts, **LOOP)
    v1 = field_violations(c @ Q.T, r, target @ Q.T, starts=starts @ Q.T, **LOOP)
    assert [(x.field, x.condition) for x in v0] == [(x.field, x.condition) for x in v1]
    assert [x.shortfall for x in v0] == pytest.approx([x.shortfall for x in v1], abs=1e-8)


def test_input_errors_name_the_field():
    with pytest.raises(ConfigError) as e:
        field_violations([[0, 0], [30, 0]], [4, 3], (40, 0), apex=[np.nan, 1.4 * 3])
    assert e.value.field == "scene.obstacles[1]" and "sqrt(2)" in e.value.reason
    with pytest.raises(ConfigError) as e:
        field_violations([[0, 0]], [-1], (40, 0))
    assert e.value.field == "scene.obstacles[0]"
    with pytest.raises(ConfigError) as e:
        field_violations([[0, 0]], [4], (40, 0), reach=0.0)
    assert e.value.field == "scene.obstacles[0]"
    with pytest.raises(ConfigError) as e:
        field_violations([[0, 0]], [4], (40, 0), h=0)
    assert e.value.field == "controller.cell_hysteresis"
    with pytest.raises(ConfigError) as e:
        field_violations([[0, 0]], [4], (40, 0), arena=((1, 0), (0, 1)))
    assert e.value.field == "scene.arena"


# ----------------------------------------------------------------------------- example fields
def test_two_in_row_valid_with_defaults():
    F = two_in_row()
    assert field_violations(F.centers, F.radii, F.target, **LOOP, arena=F.arena, starts=F.starts) == []
    s, t = F.starts[0], F.target
    for c in F.centers:  # on the segment start -> target, between them
        lam = (c - s) @ (t - s) / ((t - s) @ (t - s))
        assert 0 < lam < 1 and np.allclose(s + lam * (t - s), c)


def _brute_kappa_max(F, h, u_max, T_s, d=0.0):
    """sup of kappa = R_i / (r_i + d) over V1–V3, by loops."""
    step = u_max * T_s if T_s is not None else 0.0
    rr = F.radii + d
    best = min(math.dist(F.target, F.centers[i]) / rr[i] for i in range(len(rr)))
    for i in range(len(rr)):
        for j in range(i + 1, len(rr)):
            best = min(best, (math.dist(F.centers[i], F.centers[j]) - h - 2 * step) / (rr[i] + rr[j]))
    return best


@pytest.mark.parametrize("T_s,d", [(0.05, 0.0), (None, 0.0), (0.05, 0.5)])
def test_authors_field_verdict_matches_brute_force(T_s, d):
    F = AUTHORS_MULTI
    an = authors_multi_analysis(T_s=T_s, inflation=d)
    k_bf = _brute_kappa_max(F, 1.0, 10.0, T_s, d)
    assert an.kappa_max == pytest.approx(k_bf, abs=1e-12)
    assert an.feasible == (k_bf > S2)
    rr = F.radii + d
    # scan: split kappa into apex f and reach g; field_violations must agree with the bound
    for kappa in np.linspace(1.45, 4.0, 52):
        for f in (1.42, 1.5, kappa - 0.02):
            g = (kappa - f) / S2
            if f <= S2 or g <= 0:
                continue
            v = field_violations(F.centers, F.radii, F.target, apex=f * rr, reach=g * rr, h=1.0, u_max=10.0,
                                 T_s=T_s, arena=F.arena, starts=F.starts, inflation=d)
            vv = [x for x in v if x.condition in ("V1", "V2", "V3")]
            if abs(kappa - an.kappa_max) > 1e-6:
                assert (vv == []) == (kappa < an.kappa_max), (kappa, f)
            assert not [x for x in v if x.condition == "arena"]
            if f < an.start_apex_max - 1e-9:
                assert not [x for x in v if x.condition == "start"]
    # SPEC's defaults fail; the recorded example passes
    assert an.defaults_violations and an.example["violations"] == []
    assert an.default_apex_factor_max == pytest.approx(an.kappa_max - 1.0)


def test_authors_field_numbers():
    an = authors_multi_analysis()
    assert an.feasible
    assert an.kappa_binding == ("scene.obstacles[6,8]", "V3")
    assert an.kappa_max == pytest.approx((math.hypot(20, 30) - 2.0) / 17.0)
    assert tuple(an.pairs[0]) == (6, 8)
    assert an.default_apex_factor_max < S2  # SPEC's barrier (rho_b = 0.5, l = r) leaves no valid apex
    # the start (-90, 0) in obstacle 0's frame (centre (-84, 16), e_a towards (90, 40)) binds the apex
    e_a = np.array([174.0, 24.0]) / math.hypot(174.0, 24.0)
    e_b = np.array([-e_a[1], e_a[0]])
    dp = np.array([-6.0, -16.0])
    assert an.start_apex_max == pytest.approx((abs(dp @ e_a) + abs(dp @ e_b)) / 8.0)
    # the headroom of one obstacle, the others at their least: recomputed for obstacle 6
    F = AUTHORS_MULTI
    lims = [math.dist(F.centers[6], F.centers[j]) - 2.0 - S2 * F.radii[j] for j in range(12) if j != 6]
    assert an.R_headroom[6] == pytest.approx(min(lims + [math.dist(F.target, F.centers[6])]))
    # a generic field through analyse_field: the default scene admits the defaults
    one = analyse_field([[0.0, 0.0]], [4.0], (40.0, 0.0), starts=[(-12.0, 2.0)], arena=DEFAULT_ARENA)
    assert one.feasible and one.defaults_violations == [] and one.kappa_max == pytest.approx(10.0)
