"""The controllers as hybrid data (flow_map, jump_map, flow_set, jump_set; paper Eqs. (gradient_flows1)-(jump_set1))."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_control_geometry import scenes
from test_control_potentials import box_points, default_scene, sampled_step

from pipeline.control import CBFController, HybridController, SmoothController, in_diamond, potential
from pipeline.sim import CameraSettings, SimSettings, simulate

SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def _copy(xd: dict) -> dict:
    return {k: np.array(v) for k, v in xd.items()}


def _assert_same(xd: dict, ref: dict) -> None:
    assert set(xd) == set(ref)
    for k in ref:
        np.testing.assert_array_equal(xd[k], ref[k])


@SETTINGS
@given(scene=scenes(kinds=("squared", "authors_code")), seed=st.integers(0, 2**31 - 1),
       chi=st.floats(1.05, 2.0), frac=st.floats(0.05, 0.95))
def test_hybrid_data_properties(scene, seed, chi, frac):
    """C ∪ D covers the covering O = O_1 ∪ O_2; after a jump the state is in C \\ D (hysteresis: no Zeno);
    the sampled step is `jump where D, then flow_map of the new mode`; the data are pure."""
    lam = frac * (chi - 1)
    ctrl = HybridController(scene, k=0.8, chi=chi, lam=lam, u_max=10.0, guard=False)  # the literal rule
    a, b, m = box_points(scene, seed, 1500)
    q = np.random.default_rng(seed).choice(np.array([1, 2], dtype=np.int8), len(m))
    xd = {"i": np.zeros(len(m), dtype=np.int64), "q": q}
    ref = _copy(xd)
    outside = ~in_diamond(scene, m)
    C, D = ctrl.flow_set(m, xd), ctrl.jump_set(m, xd)
    assert (C | D)[outside].all()
    # D by the paper's inequality, with SPEC §3.3's rules for V_q = inf and V_q = 0
    V = {j: potential(scene, j, m) for j in (1, 2)}
    Vq, Vo = np.where(q == 1, V[1], V[2]), np.where(q == 1, V[2], V[1])
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(D, (Vq > 0) & np.isfinite(Vo) & (Vq >= (chi - lam) * Vo))
    xd_plus = ctrl.jump_map(m, xd)
    np.testing.assert_array_equal(xd_plus["q"], 3 - q)
    np.testing.assert_array_equal(xd_plus["i"], xd["i"])  # one obstacle: no cell jump
    after = {k: v[D] for k, v in xd_plus.items()}
    assert ctrl.flow_set(m[D], after).all()
    assert not ctrl.jump_set(m[D], after).any()
    # the sampled step agrees with the named functions, which have no side effects
    u, xd_new, jumped, pushed = sampled_step(ctrl, m, xd)
    np.testing.assert_array_equal(xd_new["q"], np.where(D, xd_plus["q"], q))
    np.testing.assert_array_equal(u, ctrl.flow_map(m, xd_new))
    np.testing.assert_array_equal(jumped, D)
    # a push-out is counted where the state is outside C ∪ D (before the jump, and after it)
    np.testing.assert_array_equal(pushed, ~C & ~D)
    np.testing.assert_array_equal(pushed, ~ctrl.flow_set(m, xd_new) & ~ctrl.jump_set(m, xd_new))
    _assert_same(xd, ref)  # the maps and the frame did not change their input
    np.testing.assert_array_equal(ctrl.jump_set(m, xd), D)  # nor any state of the controller
    np.testing.assert_array_equal(ctrl.flow_set(m, xd), C)


@SETTINGS
@given(scene=scenes(kinds=("squared",)), seed=st.integers(0, 2**31 - 1))
def test_smooth_laws_have_a_flow_map_only(scene, seed):
    """Empty jump set, identity jump map; the flow set is where the law itself (not its push-out) applies:
    everywhere for the CBF filter, outside the margin disc `|m - c| <= 2r` (V_s = inf) for the smooth law."""
    _, _, m = box_points(scene, seed, 500)
    q = np.ones(len(m), dtype=np.int8)
    in_margin = np.hypot(*(m - scene.p_0).T) <= 2 * scene.obstacle_radius
    for cls in (SmoothController, CBFController):
        ctrl = cls(scene)
        xd = ctrl.initial_state(m)
        np.testing.assert_array_equal(xd["q"], q)
        C = ctrl.flow_set(m, xd)
        np.testing.assert_array_equal(C, ~in_margin if cls is SmoothController else np.ones(len(m), bool))
        assert not ctrl.jump_set(m, xd).any()
        np.testing.assert_array_equal(ctrl.jump_map(m, xd)["q"], q)
        u = ctrl.flow_map(m, xd)
        assert np.isfinite(u).all() and (np.hypot(*u.T) <= 10.0 * (1 + 1e-12)).all()
        u_loop, xd_new, jumped, pushed = sampled_step(ctrl, m, xd)
        np.testing.assert_array_equal(u_loop, u)
        np.testing.assert_array_equal(xd_new["q"], q)
        assert not jumped.any()
        np.testing.assert_array_equal(pushed, ~C)


def test_sampled_loop_counts_pushouts_exactly_outside_c_and_d():
    """`simulate` (the sampled loop, hybrid controller, M = 1) counts a push-out at a frame exactly where the
    state is outside C ∪ D (flow_set and jump_set both false: the diamond, at M = 1), and jumps where it is in
    D: replayed frame by frame with the pure maps on the measurements the camera gave."""
    scene = default_scene()
    ctrl = HybridController(scene)
    n, frames, c = 60, 40, scene.c
    rng = np.random.default_rng(3)
    a = rng.uniform(-2.5 * c, 2.5 * c, (frames, n))
    b = rng.uniform(-2.5 * c, 2.5 * c, (frames, n))
    dia = rng.random((frames, n)) < 0.3  # a third of the frames perceived inside the diamond
    t, s = rng.uniform(-1, 1, (frames, n)), rng.choice([-1.0, 1.0], (frames, n))
    a = np.where(dia, t * c * 0.98, a)
    b = np.where(dia, s * (1 - np.abs(t)) * c * rng.uniform(0, 0.98, (frames, n)), b)
    seq = scene.from_frame(a, b)  # (frames, n, 2): the measurement of each frame, whatever the true state

    def measure(p, idx, frame, rng_):
        return seq[frame][idx].copy()

    x0 = np.column_stack([np.full(n, -45.0), np.linspace(-25.0, 25.0, n)])  # far from the obstacle and target
    res = simulate(scene, ctrl, x0, sim=SimSettings(dt=0.01, horizon=0.4, record_every=1),
                   camera=CameraSettings(period=0.01), measure=measure)
    assert (res.metrics["termination"] == "horizon").all()
    xd = ctrl.initial_state(seq[0])
    pushouts, jumps = np.zeros(n, dtype=int), np.zeros(n, dtype=int)
    for k in range(frames):
        m = seq[k]
        C, D = ctrl.flow_set(m, xd), ctrl.jump_set(m, xd)
        out = ~C & ~D
        np.testing.assert_array_equal(out, in_diamond(scene, m))  # at M = 1, outside C ∪ D is the diamond
        pushouts += out
        jumps += D
        xd = {key: np.where(D, v, xd[key]) for key, v in ctrl.jump_map(m, xd).items()}
        np.testing.assert_array_equal(res.q[k + 1], xd["q"])  # recorded after frame k's step
    np.testing.assert_array_equal(res.metrics["pushouts"], pushouts)
    np.testing.assert_array_equal(res.metrics["jumps"], jumps)
    assert (pushouts > 0).all() and (pushouts < frames).all() and jumps.sum() > 0
