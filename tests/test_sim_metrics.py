"""Per-agent outcome classes and `summarise_agents` (issue 12 §2); constructors take the keywords they use."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.config import build
from pipeline.control import CBFController, Feedback, HybridController, Obstacle, Scene, SmoothController
from pipeline.errors import ConfigError
from pipeline.sim import (
    OUTCOMES,
    Adversarial,
    Alternating,
    CameraSettings,
    Gaussian,
    NoDisturbance,
    SimSettings,
    simulate,
    summarise_agents,
    wilson,
)
from pipeline.sim.metrics import StallMonitor

MODELS = ["sampled", "continuous"]


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])


class _Straight(Feedback):
    """Drives straight at the target at u_max, blind to the obstacle."""

    name = "straight"

    def _flow(self, m, target):
        return self._finalise(-(m - self.scene.p_T), np.zeros(len(m), bool), np.zeros_like(m))


# ------------------------------------------------------------------------------------------ outcomes


@pytest.mark.parametrize("model", MODELS)
def test_smooth_on_the_saddle_is_stalled_not_timed_out(scene, model):
    """Started on K behind the obstacle, the smooth flow goes to its saddle and stays (Proposition 1)."""
    x0 = np.array([[-20.0, 0.0], [-40.0, 0.0]])
    res = simulate(scene, SmoothController(scene), x0, sim=SimSettings(dt=0.01, horizon=20.0, model=model),
                   camera=CameraSettings(period=0.05), record=False)
    m = res.metrics
    assert list(m["outcome"]) == ["stalled", "stalled"]
    assert list(m["termination"]) == ["horizon", "horizon"]
    a, b = scene.to_frame(res.p[-1])
    assert (a < -scene.obstacle_radius).all() and np.allclose(b, 0.0)  # behind the obstacle, on K


@pytest.mark.parametrize("model", MODELS)
def test_outcome_classes(scene, model):
    """reached / collided / timed_out on constructed cases; a short horizon is never `stalled`."""
    x0 = np.array([[-5.0, 25.0], [-20.0, 0.0], [-45.0, 29.0]])
    res = simulate(scene, _Straight(scene), x0, sim=SimSettings(dt=0.01, horizon=8.0, model=model),
                   camera=CameraSettings(period=0.05), record=False)
    m = res.metrics
    # the third still drives towards the target at the horizon (|x0 - p_T| = 90 at 10 units/s)
    assert list(m["outcome"]) == ["reached", "collided", "timed_out"]
    assert m["min_clearance"][1] < 0 < m["min_clearance"][0]
    assert set(m["outcome"]) <= set(OUTCOMES)
    # a horizon shorter than stall_time cannot tell a stall: the smooth saddle is `timed_out` then
    res = simulate(scene, SmoothController(scene), np.array([[-20.0, 0.0]]),
                   sim=SimSettings(dt=0.01, horizon=4.0, model=model, stall_time=5.0),
                   camera=CameraSettings(period=None), record=False)
    assert list(res.metrics["outcome"]) == ["timed_out"]


def test_stall_thresholds_are_config(scene):
    x0 = np.array([[-20.0, 0.0], [-45.0, 20.0]])
    # the second agent moves at ~10 units/s: stalled only if the threshold is above its speed
    slow = simulate(scene, SmoothController(scene), x0,
                    sim=SimSettings(dt=0.01, horizon=5.0, stall_time=2.0, stall_speed=0.1),
                    camera=CameraSettings(period=None), record=False)
    assert list(slow.metrics["outcome"]) == ["stalled", "timed_out"]
    fast = simulate(scene, SmoothController(scene), x0,
                    sim=SimSettings(dt=0.01, horizon=5.0, stall_time=2.0, stall_speed=20.0),
                    camera=CameraSettings(period=None), record=False)
    assert list(fast.metrics["outcome"]) == ["stalled", "stalled"]
    for kw, field in (({"stall_speed": 0.0}, "sim.stall_speed"), ({"stall_time": -1.0}, "sim.stall_time"),
                      ({"stall_time": "x"}, "sim.stall_time")):
        with pytest.raises(ConfigError) as info:
            simulate(scene, SmoothController(scene), x0, sim=SimSettings(horizon=1.0, **kw))
        assert info.value.field == field


@pytest.mark.parametrize("cls", [SmoothController, CBFController])
def test_adversary_near_k_is_stalled(scene, cls):
    """Proposition 1's chattering vehicles count as stalled (mean speed ~ 0), not timed out."""
    rng = np.random.default_rng(0)
    x0 = scene.from_frame(rng.uniform(-45, -15, 40), rng.uniform(-0.5, 0.5, 40))
    res = simulate(scene, cls(scene), x0, sim=SimSettings(dt=0.01, horizon=30.0), camera=CameraSettings(period=0.05),
                   disturbance=Adversarial(0.5), record=False)
    assert (res.metrics["outcome"] == "stalled").mean() >= 0.95


def test_stall_monitor_mean_speed():
    """Half-window means: a vehicle at constant speed v reads v; chattering in place reads ~0."""
    dt, T = 0.01, 2.0
    for v, chatter, stalled in ((0.05, 0.0, True), (0.2, 0.0, False), (0.0, 0.4, True), (0.15, 0.4, False)):
        mon = StallMonitor(1, stall_speed=0.1, stall_time=T, dt=dt)
        n = int(round(6.0 / dt))
        for k in range(n + 1):
            if k % mon.every == 0:
                t = k * dt
                mon.sample(np.array([[v * t + chatter * (-1) ** (k // 5), 0.0]]))
        p_end = mon.buf[(mon.count - 1) % mon.size]
        assert mon.stalled(p_end)[0] == stalled, (v, chatter)


def test_outcome_column_in_metrics_frame(scene):
    res = simulate(scene, HybridController(scene), np.array([[-12.0, 2.0]]), sim=SimSettings(horizon=15.0),
                   camera=CameraSettings(period=0.05))
    df = res.metrics_frame()
    assert {"outcome", "min_clearance", "min_target_distance"} <= set(df.columns)
    assert df.outcome.tolist() == ["reached"]
    assert df.min_target_distance[0] <= 1.0 + 1e-9


# ----------------------------------------------------------------------------------------- the table


def _frame(rng, n, **over):
    df = pd.DataFrame({
        "controller": rng.choice(["hybrid", "smooth"], n),
        "success": rng.random(n) < 0.7,
        "min_clearance": rng.normal(2.0, 1.0, n),
        "final_error": rng.exponential(2.0, n),
        "time_to_target": rng.uniform(3, 10, n),
        "jumps": rng.integers(0, 4, n),
        "min_target_distance": rng.exponential(1.0, n),
    })
    df["collision"] = ~df.success & (rng.random(n) < 0.3)
    df["outcome"] = np.where(df.collision, "collided", np.where(df.success, "reached",
                             np.where(rng.random(n) < 0.5, "stalled", "timed_out")))
    df.loc[~df.success, "time_to_target"] = np.nan
    for k, v in over.items():
        df[k] = v
    return df


@settings(max_examples=20, deadline=None)
@given(seed=st.integers(0, 2**31 - 1), n=st.integers(1, 60))
def test_summarise_agents_matches_direct_computation(seed, n):
    rng = np.random.default_rng(seed)
    df = _frame(rng, n)
    out = summarise_agents(df, "controller", delta_practical=0.8)
    assert sorted(out.controller) == sorted(df.controller.unique())
    for _, row in out.iterrows():
        g = df[df.controller == row.controller]
        assert row.n == len(g)
        assert row.success_rate == pytest.approx(g.success.mean())
        assert row.success_lo - 1e-12 <= row.success_rate <= row.success_hi + 1e-12
        assert -1e-12 <= row.success_lo and row.success_hi <= 1 + 1e-12
        assert row.collision_rate == pytest.approx(g.collision.mean())
        assert sum(row[k] for k in OUTCOMES) == pytest.approx(1.0)
        assert row.reached == pytest.approx((g.outcome == "reached").mean())
        assert row.clearance_median == pytest.approx(np.median(g.min_clearance))
        assert row.clearance_p05 == pytest.approx(np.quantile(g.min_clearance, 0.05))
        assert row.clearance_min == g.min_clearance.min() <= row.clearance_p05
        assert row.final_median == pytest.approx(np.median(g.final_error))
        assert row.final_p90 == pytest.approx(np.quantile(g.final_error, 0.9))
        t = g.time_to_target[g.success]
        assert (np.isnan(row.median_time) and len(t) == 0) or row.median_time == pytest.approx(np.median(t))
        assert row.mean_jumps == pytest.approx(g.jumps.mean())
        ok = ~g.collision & (g.min_target_distance <= 0.8)
        assert row.success_practical == pytest.approx(ok.mean())
        assert row.success_practical_lo - 1e-12 <= row.success_practical <= row.success_practical_hi + 1e-12


def test_summarise_agents_groups_and_without_practical():
    rng = np.random.default_rng(1)
    df = _frame(rng, 200)
    df["sigma"] = rng.choice([0.0, 0.5], 200)
    out = summarise_agents(df, ["controller", "sigma"])
    assert len(out) == 4 and out.n.sum() == 200
    assert "success_practical" not in out.columns
    assert list(out.columns[:3]) == ["controller", "sigma", "n"]


def test_wilson_interval():
    lo, hi = wilson(0, 20)
    assert lo == pytest.approx(0.0, abs=1e-12) and 0.1 < hi < 0.2
    lo, hi = wilson(20, 20)
    assert 0.8 < lo < 0.9 and hi == pytest.approx(1.0)
    lo, hi = wilson(50, 100)  # textbook: [0.404, 0.596]
    assert lo == pytest.approx(0.4038, abs=1e-3) and hi == pytest.approx(0.5962, abs=1e-3)


@given(n=st.integers(1, 2000), share=st.floats(0, 1))
def test_wilson_interval_stays_in_the_unit_interval_around_the_rate(n, share):
    """A table's CI columns are probabilities: never -3e-17 at 0 successes (rounding), never above 1."""
    k = round(share * n)
    lo, hi = wilson(k, n)
    assert 0.0 <= lo <= k / n <= hi <= 1.0


def test_summarise_on_a_simulation(scene):
    x0 = np.array([[-20.0, 0.0], [-12.0, 2.0], [-30.0, 20.0]])
    frames = [simulate(scene, cls(scene), x0, sim=SimSettings(horizon=15.0), camera=CameraSettings(period=0.05)).metrics_frame()
              for cls in (HybridController, SmoothController)]
    out = summarise_agents(pd.concat(frames), "controller")
    row = out.set_index("controller")
    assert row.loc["hybrid", "reached"] == 1.0
    assert row.loc["smooth", "stalled"] == pytest.approx(1 / 3)


# ------------------------------------------------------------------------------- constructor keywords


@pytest.mark.parametrize("cls", [HybridController, SmoothController, CBFController])
def test_controllers_reject_unknown_keywords(scene, cls):
    with pytest.raises(TypeError):
        cls(scene, gain=2.0)
    with pytest.raises(TypeError):
        cls(scene, name="hybrid")


@pytest.mark.parametrize(("cls", "kw"), [(NoDisturbance, {"eps": 0.5}), (Gaussian, {"eps": 0.5}),
                                         (Alternating, {"sigma": 0.5}), (Adversarial, {"name": "x"})])
def test_disturbances_reject_unknown_keywords(cls, kw):
    with pytest.raises(TypeError):
        cls(**kw)


def test_builders_reject_typos_and_a_name_the_target_does_not_take(scene):
    """A node's keys are its target's keywords, `name` too: the controllers' and disturbances' rows are named by their
    class (before: a `name` key was a label the build stripped, restating the class's name in 11 config files)."""
    ctrl = build({"_target_": "pipeline.control.SmoothController", "k": 2.0}, "controller", scene=scene)
    assert isinstance(ctrl, SmoothController) and ctrl.k == 2.0 and ctrl.name == "smooth"
    with pytest.raises(ConfigError, match=r"controller\.name: unknown key"):
        build({"_target_": "pipeline.control.SmoothController", "name": "smooth"}, "controller", scene=scene)
    assert isinstance(build({"_target_": "pipeline.sim.NoDisturbance"}, "disturbance"), NoDisturbance)
    with pytest.raises(ConfigError) as info:
        build({"_target_": "pipeline.control.HybridController", "lamda": 0.05}, "controller",
              scene=scene)
    assert info.value.field == "controller.lamda"
    with pytest.raises(ConfigError) as info:
        build({"_target_": "pipeline.sim.Gaussian", "sigmaa": 0.1}, "disturbance")
    assert info.value.field == "disturbance.sigmaa"


class _Constant(Feedback):
    """Constant velocity (10, 0): straight horizontal lines, at the largest step the integrator allows."""

    name = "constant"

    def _flow(self, m, target):
        return np.tile([10.0, 0.0], (len(m), 1)), np.zeros(len(m), bool)


@pytest.mark.parametrize("model", MODELS)
def test_grazing_chord_is_a_collision(scene, model):
    """A straight path that cuts the obstacle's edge 0.05 deep is a collision even when both ends of every
    step lie outside it; 0.05 outside, the clearance is 0.05."""
    r = scene.obstacle_radius
    x0 = np.array([[-30.0, r - 0.05], [-30.0, r + 0.05], [-30.0, -r + 0.05]])
    res = simulate(scene, _Constant(scene), x0, sim=SimSettings(dt=0.01, horizon=6.0, model=model),
                   camera=CameraSettings(period=None), record=False)
    m = res.metrics
    assert m["collision"].tolist() == [True, False, True]
    assert m["outcome"].tolist() == ["collided", "timed_out", "collided"]
    assert m["min_clearance"][1] == pytest.approx(0.05, abs=1e-3)
    assert (m["min_clearance"][[0, 2]] < 0).all()
    # the collision is located where the line enters the disc
    x_in = -np.sqrt(r**2 - (r - 0.05) ** 2)
    np.testing.assert_allclose(res.p[-1, [0, 2], 0], x_in, atol=0.1 if model == "sampled" else 1e-6)


@settings(max_examples=25, deadline=None)
@given(st.lists(st.tuples(st.floats(-60, 60), st.floats(-40, 40)), min_size=1, max_size=12),
       st.lists(st.tuples(st.floats(-50, 50), st.floats(-30, 30), st.floats(0.5, 6)), min_size=1, max_size=6))
def test_the_monitor_s_distances_to_every_obstacle_are_each_centre_s_bit_for_bit(points, discs):
    """The monitor's squared distances to all obstacle centres at once (one broadcast) are those of each centre
    alone, bit for bit: the collision test and the clearance the tables report do not move by a rounding."""
    from types import SimpleNamespace

    from pipeline.plants import SingleIntegrator
    from pipeline.sim.monitor import ArrivalCollision, _sq

    d = np.array(discs, dtype=float)  # what the monitor reads of a scene (any field, valid for a law or not)
    scene = SimpleNamespace(arrays={"center": d[:, :2], "radius": d[:, 2]}, p_T=np.array([40.0, 0.0]))
    p = np.array(points, dtype=float)
    mon = ArrivalCollision(scene, SingleIntegrator(), len(p), delta=1.0, stop_on_success=True,
                           stall=StallMonitor(len(p), 0.25, 5.0, 0.01))
    each = np.stack([_sq(p, c) for c in scene.arrays["center"]], axis=1)
    assert mon._d2(p).tobytes() == each.tobytes()
