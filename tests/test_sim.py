"""Closed loop on the true state (SPEC §1, §3.3-§3.5): `pipeline.sim.simulate`, its settings, and the objects
`pipeline.config.build` makes from config nodes (controllers, disturbances, initial conditions)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.config import build
from pipeline.control import (
    CBFController,
    Feedback,
    HybridController,
    Obstacle,
    Scene,
    SmoothController,
    in_diamond,
)
from pipeline.errors import ConfigError
from pipeline.sim import (
    TERMINATIONS,
    Adversarial,
    Alternating,
    CameraSettings,
    Gaussian,
    NoDisturbance,
    SimSettings,
    frame_steps,
    simulate,
)
from pipeline.sim.starts import Grid, NearK

EPS, DELTA = 0.5, 1.0
DISTURBANCES = {"none": NoDisturbance(), "adversarial": Adversarial(EPS), "alternating": Alternating(EPS)}


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])


@pytest.fixture(scope="module")
def grid_x0(scene) -> np.ndarray:
    """The `init=grid` initial conditions (a coarser grid), covering the arena around the diamond."""
    x0 = Grid(nx=15, ny=9, margin=2.0)(scene)
    assert not in_diamond(scene, x0).any()
    # covers the whole arena, the line behind the obstacle included
    assert x0[:, 0].min() == -48.0 and x0[:, 0].max() == 48.0 and np.abs(x0[:, 1]).max() == 28.0
    assert ((x0[:, 0] < -scene.c) & (x0[:, 1] == 0.0)).sum() >= 3
    return x0


@pytest.fixture(scope="module")
def near_k_x0(scene) -> np.ndarray:
    """`init=near_k`: behind the obstacle, within eps of the set K (|b| < eps)."""
    x0 = NearK(n=120, seed=0, band=EPS)(scene)
    a, b = scene.to_frame(x0)
    assert len(x0) == 120 and (a < -scene.c).all() and (np.abs(b) < EPS).all()
    return x0


def run(scene, ctrl, x0, disturbance=None, *, seed=0, record=True, target_fn=None, camera_period=0.05, p_fail=0.0,
        **sim):
    """One run at this file's defaults; `sim`: keys of :class:`SimSettings`."""
    return simulate(scene, ctrl, x0, disturbance=disturbance, seed=seed, record=record, target_fn=target_fn,
                    sim=SimSettings(**({"dt": 0.01, "horizon": 30.0, "delta": DELTA} | sim)),
                    camera=CameraSettings(period=camera_period, p_fail=p_fail))


# ------------------------------------------------------------------------------------- main claims


@pytest.mark.parametrize("dist", list(DISTURBANCES))
def test_hybrid_reaches_target_from_grid(scene, grid_x0, dist):
    res = run(scene, HybridController(scene), grid_x0, DISTURBANCES[dist], record_every=10)
    m = res.metrics
    assert m["success"].all(), grid_x0[~m["success"]]
    assert not m["collision"].any() and (m["min_clearance"] > 0).all()
    assert (m["final_error"] <= DELTA + 1e-9).all()
    assert (m["time_to_target"] <= 30.0).all()
    assert set(m["termination"]) == {"target"}
    assert m["jumps"].max() <= 20  # no chattering
    if dist == "none":  # started with the better mode, nothing pushes a clean run across
        assert m["jumps"].max() <= 1
    # the recorded arc agrees with the metrics
    np.testing.assert_array_equal(res.j[-1], m["jumps"])
    np.testing.assert_allclose(np.hypot(*(res.p[-1] - scene.p_T).T), m["final_error"])


@pytest.mark.parametrize("cls", [SmoothController, CBFController])
def test_smooth_baselines_stall_near_k_under_adversarial(scene, near_k_x0, cls):
    """Proposition 1: started within eps of K, the adversarial disturbance stalls continuous feedback."""
    res = run(scene, cls(scene), near_k_x0, Adversarial(EPS), record=False)
    m = res.metrics
    assert m["success"].mean() <= 0.02
    assert not m["collision"].any()
    # stalled behind the obstacle, short of its far side
    a, b = scene.to_frame(res.p[-1])
    assert (a[~m["success"]] < 0).all()
    assert (m["final_error"][~m["success"]] > scene.p_T[0]).all()


def test_hybrid_reaches_target_near_k_under_adversarial(scene, near_k_x0):
    res = run(scene, HybridController(scene), near_k_x0, Adversarial(EPS), record=False)
    m = res.metrics
    assert m["success"].all() and not m["collision"].any()
    assert 0 < m["jumps"].max() <= 20


@pytest.mark.parametrize("cls", [HybridController, SmoothController, CBFController])
def test_no_collision_clean(scene, grid_x0, cls):
    res = run(scene, cls(scene), grid_x0, record=False, horizon=20.0)
    m = res.metrics
    assert not m["collision"].any() and (m["min_clearance"] > 0).all()
    # the smooth baselines stall only on the line behind the obstacle (the set K)
    a, b = scene.to_frame(grid_x0)
    failed = ~m["success"]
    assert (np.abs(b[failed]) < 1e-9).all() and (a[failed] < 0).all()


def test_halving_dt(scene, grid_x0):
    """Same camera rate (ZOH every 0.05 s), half the Euler step: same outcomes, nearly the same arcs."""
    x0 = grid_x0[::3]
    out = []
    for dt in (0.01, 0.005):
        res = run(scene, HybridController(scene), x0, Alternating(EPS), dt=dt, record_every=round(0.1 / dt))
        out.append(res)
    a, b = out
    np.testing.assert_array_equal(a.metrics["success"], b.metrics["success"])
    np.testing.assert_array_equal(a.metrics["jumps"], b.metrics["jumps"])
    n = min(len(a.t), len(b.t)) - 1  # the last record is the stopping time of each run
    np.testing.assert_allclose(a.t[:n], b.t[:n])
    assert np.abs(a.p[:n] - b.p[:n]).max() < 0.1
    assert np.abs(a.p[-1] - b.p[-1]).max() < 0.1
    np.testing.assert_allclose(a.metrics["time_to_target"], b.metrics["time_to_target"], atol=0.02)
    np.testing.assert_allclose(a.metrics["path_length"], b.metrics["path_length"], rtol=0.01)


def test_halving_dt_every_step_control(scene, grid_x0):
    """Without a camera (control every step) halving dt also halves the control period."""
    x0 = grid_x0[::3]
    a, b = (run(scene, HybridController(scene), x0, dt=dt, camera_period=None, record=False) for dt in (0.01, 0.005))
    np.testing.assert_array_equal(a.metrics["success"], b.metrics["success"])
    assert a.metrics["success"].all()
    ta, tb = a.metrics["time_to_target"], b.metrics["time_to_target"]
    assert np.median(np.abs(ta - tb) / ta) < 0.02
    np.testing.assert_allclose(a.metrics["path_length"], b.metrics["path_length"], rtol=0.1)


# ------------------------------------------------------------------------------ semantics of the loop


def test_determinism(scene, grid_x0):
    x0 = grid_x0[::4]
    kw = {"p_fail": 0.3, "horizon": 8.0, "record_every": 5}
    a = run(scene, HybridController(scene), x0, Gaussian(0.5), seed=7, **kw)
    b = run(scene, HybridController(scene), x0, Gaussian(0.5), seed=np.random.default_rng(7), **kw)
    c = run(scene, HybridController(scene), x0, Gaussian(0.5), seed=8, **kw)
    for k in ("t", "p", "m", "u", "q", "j"):
        np.testing.assert_array_equal(getattr(a, k), getattr(b, k))
    for k, v in a.metrics.items():
        np.testing.assert_array_equal(v, b.metrics[k])
    assert not np.array_equal(a.m, c.m)


def test_camera_failure_holds_last_estimate(scene):
    """A lost frame keeps the previous measurement (and the velocity computed from it)."""
    x0 = np.array([[-40.0, 20.0], [-40.0, -20.0], [-45.0, 5.0], [30.0, 25.0]] * 10)
    dt, p_fail = 0.01, 0.5
    ctrl = SmoothController(scene)
    res = simulate(scene, ctrl, x0, sim=SimSettings(dt=dt, horizon=1.0, record_every=1),
                   camera=CameraSettings(period=dt, p_fail=p_fail), seed=3)
    p, m, u = res.p, res.m, res.u
    assert (res.metrics["termination"] == "horizon").all()
    np.testing.assert_array_equal(m[0], x0)  # the first frame is always delivered
    np.testing.assert_array_equal(m[1], x0)  # step 0 uses the first frame
    # m[k] was measured at the start of step k-1 (recorded after it): fresh = p[k-1], or held = m[k-1]
    fresh = (m[2:] == p[1:-1]).all(axis=2)
    held = (m[2:] == m[1:-1]).all(axis=2)
    assert (fresh | held).all() and not (fresh & held).any()
    lost = held.mean()
    n = held.size
    assert abs(lost - p_fail) < 5 * math.sqrt(p_fail * (1 - p_fail) / n)
    # the velocity is that of the (possibly held) measurement
    ref = SmoothController(scene)
    for k in (1, 10, 50, 100):
        np.testing.assert_allclose(u[k], ref.flow_map(m[k], ref.initial_state(m[k])), rtol=1e-12)


def test_camera_period_zero_order_hold(scene):
    x0 = np.array([[-40.0, 20.0], [20.0, -25.0]])
    res = simulate(scene, HybridController(scene), x0, sim=SimSettings(dt=0.01, horizon=2.0, record_every=1),
                   camera=CameraSettings(period=0.05))
    # u (and m) change only at frame starts: steps 0, 5, 10, ... -> recorded indices 1, 6, 11, ...
    change = (np.diff(res.u[1:], axis=0) != 0).any(axis=(1, 2))
    idx = np.flatnonzero(change) + 1  # step whose velocity differs from the step before
    assert len(idx) > 0 and (idx % 5 == 0).all()
    # Euler: p advances by dt * u each step
    np.testing.assert_allclose(np.diff(res.p, axis=0), 0.01 * res.u[1:], atol=1e-12)


def test_p_fail_and_other_arguments_are_validated(scene):
    x0 = np.array([[-20.0, 10.0]])
    ctrl = HybridController(scene)
    cases = [
        ({"p_fail": 1.0}, "camera.p_fail"),
        ({"p_fail": -0.1}, "camera.p_fail"),
        ({"delta": 0.0}, "sim.delta"),
        ({"record_every": 0}, "sim.record_every"),
        ({"dt": 0.0}, "sim.dt"),
        ({"camera_period": 0.015}, "camera.period"),
    ]
    for kw, field in cases:
        with pytest.raises(ConfigError) as info:
            camera = {"period": kw.pop("camera_period", 0.05)} | ({"p_fail": kw.pop("p_fail")} if "p_fail" in kw else {})
            simulate(scene, ctrl, x0, sim=SimSettings(**({"horizon": 1.0} | kw)), camera=CameraSettings(**camera))
        assert info.value.field == field, kw
    with pytest.raises(ConfigError, match="init.points"):
        simulate(scene, ctrl, np.zeros((0, 2)))
    with pytest.raises(ConfigError, match="init.points"):
        simulate(scene, ctrl, np.zeros((3, 3)))


def check_timing(dt: float, horizon: float, period: float | None) -> int:
    """The timing checks `simulate` runs (`sim.dt`, `sim.horizon`, then the camera period): steps per frame."""
    SimSettings(dt=dt, horizon=horizon)
    CameraSettings(period=period)
    return frame_steps(dt, period)


@pytest.mark.parametrize(
    ("dt", "horizon", "period", "field"),
    [
        (0.01, 30.0, 0.015, "camera.period"),
        (0.01, 30.0, 0.0, "camera.period"),
        (0.01, 30.0, -0.05, "camera.period"),
        (0.01, 30.0, 0.005, "camera.period"),
        (0.0, 30.0, 0.05, "sim.dt"),
        (-0.01, 30.0, 0.05, "sim.dt"),
        (float("nan"), 30.0, 0.05, "sim.dt"),
        (0.01, 0.001, 0.05, "sim.horizon"),
    ],
)
def test_check_timing_rejects(dt, horizon, period, field):
    with pytest.raises(ConfigError) as info:
        check_timing(dt, horizon, period)
    assert info.value.field == field and "\n" not in str(info.value)


def test_check_timing_accepts_multiples():
    assert check_timing(0.01, 30.0, 0.05) == 5
    assert check_timing(0.01, 30.0, 0.01) == 1
    assert check_timing(0.001, 1.0, 0.033) == 33
    assert check_timing(0.01, 30.0, None) == 1


class _Straight(Feedback):
    """Drives straight at the target, blind to the obstacle."""

    name = "straight"

    def _flow(self, m, target):
        return self._finalise(-(m - self.scene.p_T), np.zeros(len(m), bool), np.zeros_like(m))


def test_collision_detection_and_termination(scene):
    x0 = np.array([[-20.0, 0.0], [-20.0, 10.0], [1.0, 1.0], [-20.0, 3.9]])
    res = simulate(scene, _Straight(scene, u_max=10.0), x0, sim=SimSettings(dt=0.01, horizon=30.0, record_every=1),
                   camera=CameraSettings(period=None))
    m = res.metrics
    assert m["collision"].tolist() == [True, False, True, True]
    assert m["success"].tolist() == [False, True, False, False]
    assert m["termination"].tolist() == ["collision", "target", "collision", "collision"]
    assert (m["min_clearance"][m["collision"]] < 0).all() and m["min_clearance"][1] > 0
    assert m["path_length"][2] == 0.0  # started inside the obstacle: stopped at once
    # a colliding agent stops just inside the obstacle
    d_end = np.hypot(*(res.p[-1] - scene.p_0).T)
    assert d_end[0] < scene.obstacle_radius and d_end[0] > scene.obstacle_radius - 0.2
    assert set(m["termination"]) <= set(TERMINATIONS)


def test_metrics_are_consistent_with_arcs(scene, grid_x0):
    x0 = grid_x0[::5]
    res = run(scene, HybridController(scene), x0, Adversarial(EPS), record_every=1, horizon=20.0)
    m = res.metrics
    df = res.metrics_frame()
    assert list(df.columns[:3]) == ["controller", "x0", "y0"]
    np.testing.assert_array_equal(df[["x0", "y0"]].to_numpy(), x0)
    steps = np.hypot(*np.diff(res.p, axis=0).transpose(2, 0, 1)).sum(axis=0)
    np.testing.assert_allclose(m["path_length"], steps, rtol=1e-9)
    d0 = np.hypot(*(res.p - scene.p_0).transpose(2, 0, 1))
    np.testing.assert_allclose(m["min_clearance"], d0.min(axis=0) - scene.obstacle_radius, rtol=1e-12)
    err = np.hypot(*(res.p - scene.p_T).transpose(2, 0, 1))
    first = np.argmax(err <= DELTA, axis=0)
    np.testing.assert_allclose(m["time_to_target"], res.t[first], atol=1e-9)
    assert (m["path_length"] >= np.hypot(*(res.p[-1] - x0).T) - 1e-9).all()
    assert res.q.shape == res.j.shape == (len(res.t), len(x0)) and set(np.unique(res.q)) <= {1, 2}
    # modes switch exactly when the jump counter moves
    np.testing.assert_array_equal((np.diff(res.q.astype(int), axis=0) != 0), np.diff(res.j, axis=0) > 0)


def test_stop_on_success_false_keeps_flowing(scene):
    x0 = np.array([[-30.0, 15.0], [20.0, -20.0]])
    res = run(scene, HybridController(scene), x0, stop_on_success=False, horizon=30.0)
    m = res.metrics
    assert m["success"].all() and (m["termination"] == "target").all()
    assert (m["final_error"] < 1e-3).all()  # converged to p_T, well inside delta
    assert (m["time_to_target"] < 30.0).all()


def test_constant_target_fn_matches_static_target(scene, grid_x0):
    x0 = grid_x0[::4]
    fn = lambda t, frame, p, idx, rng: np.broadcast_to(scene.p_T, p.shape)  # noqa: E731
    a = run(scene, HybridController(scene), x0, Adversarial(EPS), horizon=20.0)
    b = run(scene, HybridController(scene), x0, Adversarial(EPS), horizon=20.0, target_fn=fn)
    np.testing.assert_array_equal(a.metrics["success"], b.metrics["success"])
    np.testing.assert_allclose(a.metrics["time_to_target"], b.metrics["time_to_target"], atol=1e-9)
    assert b.target is not None and np.allclose(b.target, scene.p_T)


# ---------------------------------------------------------------------------------------- disturbances


def test_disturbances(scene):
    rng = np.random.default_rng(0)
    p = rng.uniform(-40, 40, (500, 2))
    _, b = scene.to_frame(p)
    e = Adversarial(EPS)(p, 3, rng, scene)
    np.testing.assert_allclose(np.hypot(*e.T), EPS)
    _, bm = scene.to_frame(p + e)
    assert (np.sign(bm - b) == -np.where(b >= 0, 1, -1)).all()  # towards (and across) b = 0
    near = np.abs(b) < EPS
    assert near.any() and (np.sign(bm[near]) != np.sign(b[near])).all()
    e0, e1 = Alternating(EPS)(p, 0, rng, scene), Alternating(EPS)(p, 1, rng, scene)
    np.testing.assert_allclose(e0, -e1)
    np.testing.assert_allclose(e0 @ scene.e_a, 0.0, atol=1e-12)
    np.testing.assert_allclose(np.abs(e0 @ scene.e_b), EPS)
    g = Gaussian(0.5)(np.zeros((20000, 2)), 0, rng, scene)
    assert abs(g.std() - 0.5) < 0.02 and abs(g.mean()) < 0.02
    with pytest.raises(ConfigError, match="disturbance.eps"):
        Adversarial(-1.0)


def test_build_helpers(scene):
    """Controllers, disturbances and initial conditions from their config nodes (`pipeline.config.build`)."""
    ctrl = build({"_target_": "pipeline.control.HybridController", "chi": 1.2, "lam": 0.1}, "controller", scene=scene)
    assert isinstance(ctrl, HybridController) and ctrl.name == "hybrid" and ctrl.chi == 1.2
    with pytest.raises(ConfigError) as info:
        build({"_target_": "pipeline.control.HybridController", "chi": 0.9}, "controller", scene=scene)
    assert info.value.field == "controller.chi"
    with pytest.raises(ConfigError) as info:
        build({"name": "x"}, "controller", scene=scene)
    assert info.value.field == "controller"
    dist = build({"_target_": "pipeline.sim.Adversarial", "eps": 0.25}, "disturbance")
    assert isinstance(dist, Adversarial) and dist.eps == 0.25
    pts = build({"_target_": "pipeline.sim.starts.Random", "n": 50, "seed": 1, "margin": 2.0}, "init")(scene)
    assert pts.shape == (50, 2) and not in_diamond(scene, pts).any()
    assert (np.abs(pts[:, 0]) <= 48.0).all() and (np.abs(pts[:, 1]) <= 28.0).all()
    # an unknown kind of initial condition (was `mode: spiral`), and the old `mode:` key itself
    with pytest.raises(ConfigError, match="init._target_"):
        build({"_target_": "pipeline.sim.starts.Spiral"}, "init")
    with pytest.raises(ConfigError, match="init.mode"):
        build({"_target_": "pipeline.sim.starts.Grid", "mode": "grid"}, "init")
    with pytest.raises(ConfigError, match="init.points"):
        build({"_target_": "pipeline.sim.starts.Points", "points": [[1.0, 2.0, 3.0]]}, "init")(scene)


@pytest.mark.parametrize("dist", [*DISTURBANCES, "gaussian"])
def test_hybrid_reaches_target_from_stage_grid_with_camera_failures(scene, dist):
    """The stage's full `init=grid` (21 x 13) under every disturbance, half the frames lost."""
    x0 = Grid(nx=21, ny=13, margin=2.0)(scene)
    d = Gaussian(0.5) if dist == "gaussian" else DISTURBANCES[dist]
    res = run(scene, HybridController(scene), x0, d, p_fail=0.5, record=False)
    m = res.metrics
    assert len(x0) > 200
    assert m["success"].all() and not m["collision"].any() and m["jumps"].max() <= 20
