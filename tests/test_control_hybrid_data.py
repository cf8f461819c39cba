"""The controllers as hybrid data (flow_map, jump_map, flow_set, jump_set; paper Eqs. (gradient_flows1)-(jump_set1))."""

from __future__ import annotations

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_control_geometry import scenes
from test_control_potentials import box_points

from pipeline.control import CBFController, HybridController, SmoothController, in_diamond, potential

SETTINGS = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.too_slow])


@SETTINGS
@given(scene=scenes(kinds=("squared", "authors_code")), seed=st.integers(0, 2**31 - 1),
       chi=st.floats(1.05, 2.0), frac=st.floats(0.05, 0.95))
def test_hybrid_data_properties(scene, seed, chi, frac):
    """C ∪ D covers the covering O = O_1 ∪ O_2; after a jump the state is in C \\ D (hysteresis: no Zeno);
    the sampled step is `jump where D, then flow_map of the new mode`; the data are pure."""
    lam = frac * (chi - 1)
    ctrl = HybridController(scene, k=0.8, chi=chi, lam=lam, u_max=10.0)
    a, b, m = box_points(scene, seed, 1500)
    q = np.random.default_rng(seed).choice(np.array([1, 2], dtype=np.int8), len(m))
    outside = ~in_diamond(scene, m)
    C, D = ctrl.flow_set(m, q), ctrl.jump_set(m, q)
    assert (C | D)[outside].all()
    # D by the paper's inequality, with SPEC §3.3's rules for V_q = inf and V_q = 0
    V = {j: potential(scene, j, m) for j in (1, 2)}
    Vq, Vo = np.where(q == 1, V[1], V[2]), np.where(q == 1, V[2], V[1])
    with np.errstate(invalid="ignore"):
        np.testing.assert_array_equal(D, (Vq > 0) & np.isfinite(Vo) & (Vq >= (chi - lam) * Vo))
    q_plus = ctrl.jump_map(q)
    np.testing.assert_array_equal(q_plus, 3 - q)
    after = ctrl.flow_set(m[D], q_plus[D])
    assert after.all()
    assert not ctrl.jump_set(m[D], q_plus[D]).any()
    # the sampled step agrees with the named functions, which have no side effects
    ctrl.reset(m)
    ctrl.q = q.copy()
    u = ctrl(m)
    np.testing.assert_array_equal(ctrl.q, np.where(D, q_plus, q))
    np.testing.assert_array_equal(u, ctrl.flow_map(m, ctrl.q))
    np.testing.assert_array_equal(ctrl.jumps, D.astype(int))
    u2, pushed = ctrl.flow_map(m, ctrl.q, with_pushout=True)
    np.testing.assert_array_equal(u2, u)
    np.testing.assert_array_equal(pushed.astype(int), ctrl.pushouts)
    assert (ctrl.jumps == D.astype(int)).all()  # flow_map/jump_set did not count anything


@SETTINGS
@given(scene=scenes(kinds=("squared",)), seed=st.integers(0, 2**31 - 1))
def test_smooth_laws_have_a_flow_map_only(scene, seed):
    _, _, m = box_points(scene, seed, 500)
    q = np.ones(len(m), dtype=np.int8)
    for cls in (SmoothController, CBFController):
        ctrl = cls(scene)
        assert ctrl.flow_set(m, q).all() and not ctrl.jump_set(m, q).any()
        np.testing.assert_array_equal(ctrl.jump_map(q), q)
        u = ctrl.flow_map(m, q)
        assert np.isfinite(u).all() and (np.hypot(*u.T) <= 10.0 * (1 + 1e-12)).all()
        np.testing.assert_array_equal(ctrl(m), u)
