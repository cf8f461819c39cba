"""The unicycle in clutter and the benchmark-like generator (issue 45; docs/dense.md, "The unicycle in clutter"):
the mean of two commands and the speed that slows in a turn, each shown to matter on a benchmark-like field (it
collides without, not with), their rules as properties, and the generator's own covering or its one-line refusal."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.cli import compose
from pipeline.control import HybridController
from pipeline.control.dense import benchmark_scene
from pipeline.control.validity import field_violations
from pipeline.errors import ConfigError
from pipeline.plants import Unicycle, steering_warnings
from pipeline.sim import Adversarial, SimSettings, WorldAlternating, simulate
from pipeline.sim.closed_loop import SampledLoop
from pipeline.sim.composed import loop_parts

STARTS = 7.0 * np.stack([np.cos(np.arange(50) * 2 * np.pi / 50), np.sin(np.arange(50) * 2 * np.pi / 50)], axis=1)
SEED = 2  # a benchmark-like field (12 discs) where each part of the design is needed (measured: tests below)


def _run(disturbance, smoothing=1, turn_lookahead=None):
    """50 starts on the circle of radius 7 facing the goal, the hybrid dense design, |ω| <= 1, d = 0.1, 10 s."""
    scene = benchmark_scene(seed=SEED, inflation=0.1)
    veh = Unicycle(lookahead=0.1, omega_max=1.0, heading0="target", smoothing=smoothing, turn_lookahead=turn_lookahead)
    steer = veh.steering_scene(scene)
    law = HybridController(steer, chi=1.5, lam=0.3, u_max=1.0, push_speed=0.7, cell_hysteresis=0.05,
                           noise_tolerance=0.3, saturation="tangent", push_tangent=True)
    r = simulate(scene, law, STARTS, sim=SimSettings(horizon=10.0), disturbance=disturbance, record=False, plant=veh,
                 heading0=veh.initial_heading(STARTS, scene))
    return int(r.metrics["collision"].sum()), float(r.metrics["success"].mean())


def test_the_mean_of_two_commands_keeps_the_unicycle_off_the_discs_under_the_benchmarks_noise():
    noise = WorldAlternating(m=0.2)
    hits, _ = _run(noise)
    assert hits > 0, "the field no longer shows the failure the design is for"
    assert _run(noise, smoothing=2) == (0, 1.0)
    assert _run(noise, smoothing=2, turn_lookahead=0.5) == (0, 1.0)


def test_slowing_in_a_turn_keeps_it_off_under_the_adversary():
    adversary = Adversarial(eps=0.28)
    hits, _ = _run(adversary, smoothing=2)
    assert hits > 0, "the field no longer shows the failure the slow turn is for"
    hits, success = _run(adversary, smoothing=2, turn_lookahead=0.5)
    assert hits == 0 and success >= 0.9


@pytest.mark.parametrize("k", [1, 2, 3])
def test_smoothing_is_the_mean_of_the_last_commands_and_restarts_with_a_run(k):
    parts = loop_parts(compose("simulate", ["vehicle=unicycle", f"vehicle.smoothing={k}"]))
    loop = SampledLoop(parts.scene, parts.law(compose("simulate", []).controller, "controller"), parts.plant)
    rng = np.random.default_rng(0)
    us = [rng.normal(size=(5, 2)) for _ in range(5)]
    for _ in range(2):  # a second run starts without the first one's commands
        loop.initial(parts.plant.lift(np.tile([-40.0, 5.0], (5, 1)), np.zeros(5)), rng)
        for j, u in enumerate(us):
            window = us[max(0, j - k + 1): j + 1]
            assert np.allclose(loop._smoothed(u), sum(window) / len(window))


_ang = st.floats(-math.pi, math.pi, allow_nan=False)


@settings(max_examples=200, deadline=None)
@given(th=_ang, a=_ang, speed=st.floats(0.0, 2.0), rho=st.floats(0.1, 2.0))
def test_turn_lookahead_slows_only_where_the_turn_rate_clips(th, a, speed, rho):
    d, w_max = 0.1, 1.0
    u = speed * np.array([[math.cos(a), math.sin(a)]])
    c = np.array([[0.0, 0.0, th]])
    plain = Unicycle(lookahead=d, omega_max=w_max).actuate(c, u)[0]
    slow = Unicycle(lookahead=d, omega_max=w_max, turn_lookahead=rho).actuate(c, u)[0]
    lateral = speed * math.sin(a - th)
    assert slow[1] == plain[1]                                  # the turn is the clipped one either way
    assert abs(slow[0]) <= abs(plain[0]) + 1e-12 and np.sign(slow[0]) * np.sign(plain[0]) >= 0
    if abs(lateral) <= w_max * rho:
        assert slow[0] == pytest.approx(plain[0])              # a turn a look-ahead of rho takes: full speed
    else:
        assert slow[0] == pytest.approx(plain[0] * w_max * rho / abs(lateral))


def test_the_options_refuse_what_they_cannot_do():
    with pytest.raises(ConfigError, match="vehicle.turn_lookahead"):
        Unicycle(omega_max=None, turn_lookahead=0.5)
    with pytest.raises(ConfigError, match="vehicle.smoothing"):
        loop_parts(compose("simulate", ["vehicle=unicycle", "vehicle.smoothing=2", "sim.model=continuous"]))


def test_the_design_silences_the_warnings_it_answers():
    law = HybridController(benchmark_scene(seed=0, inflation=0.1).inflated(0.1), u_max=1.0, push_speed=0.7,
                           cell_hysteresis=0.05)
    assert len(steering_warnings(Unicycle(lookahead=0.1, omega_max=1.0), law)) == 2
    assert steering_warnings(Unicycle(lookahead=0.1, omega_max=1.0, smoothing=2, turn_lookahead=0.5), law) == []


# ---- the generator: the benchmark's statistics, each field's own covering, or one line
def test_benchmark_fields_carry_the_largest_covering_their_discs_admit():
    for seed in range(3):
        a, b = benchmark_scene(seed=seed, inflation=0.1), benchmark_scene(seed=seed, inflation=0.1)
        assert a.config() == b.config()                         # seeded
        arr = a.inflated(0.1).arrays
        c, rr = arr["center"], arr["radius"]
        assert 8 <= len(c) <= 12 and np.hypot(*c.T).min() >= 2.0 and np.hypot(*c.T).max() <= 5.5
        gaps = np.hypot(*(c[:, None] - c[None]).transpose(2, 0, 1))[np.triu_indices(len(c), 1)]
        assert gaps.min() >= 2.1
        th = 2 * np.pi * np.arange(100) / 100
        kw = dict(h=0.05, u_max=1.0, T_s=0.05, arena=((-10, 10), (-10, 10)),
                  starts=7.0 * np.stack([np.cos(th), np.sin(th)], 1))
        apex, reach = arr["c"], arr["reach"]
        assert field_violations(c, rr, np.zeros(2), apex=apex, reach=reach, **kw) == []
        assert field_violations(c, rr, np.zeros(2), apex=1.3 * apex, reach=1.3 * reach, **kw), "not near the largest"


def test_a_field_no_covering_admits_is_refused_in_one_line():
    with pytest.raises(ConfigError) as err:
        benchmark_scene(seed=0, spacing=1.2, n_obstacles=(12, 12))
    assert "short by" in err.value.reason and "discs" in err.value.reason and "\n" not in str(err.value)


def test_the_sweep_runs_the_admitted_fields_and_lists_the_rejected(tmp_path):
    from pipeline.experiments.stage import run
    cfg = compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                  "perception=oracle", "debug=tiny", "experiment=dense_sweep_unicycle",
                                  "experiment.n_scenes=8", "scene.spacing=1.75", "scene.seed=1", "experiment.adversary_eps=null",
                                  "experiment.benchmark_m=[0.2]", "publish=true", "scale=1.0",
                                  "experiment.n_agents=4", "experiment.n_drawn=4", "experiment.controllers=[hybrid]"])
    out = run(cfg)
    info = out["results"].info
    assert info["rejected"] and all("short by" in line for line in info["rejected"])
    assert len(info["scenes"]) + len(info["rejected"]) == 8 and info["scenes"]
    hyb = out["results"].tables["summary"].set_index(["condition", "controller"]).xs("hybrid", level="controller")
    assert (hyb["collision_rate"] == 0).all()
    assert (tmp_path / "paper" / "tab_dense_sweep_unicycle.md").exists()


def test_fieldcheck_states_the_unicycle_steering_conditions(capsys):
    from pipeline.fieldcheck import run
    base = ["scene=benchmark", "init=circle", "controller=hybrid_dense", "vehicle=unicycle", "vehicle.lookahead=0.1",
            "vehicle.omega_max=1", "scene.inflation=0.1"]
    bare = run(compose("fieldcheck", base))["steering"]
    assert sum(line.startswith("warning") for line in bare) == 2
    done = run(compose("fieldcheck", [*base, "vehicle.smoothing=2", "vehicle.turn_lookahead=0.5"]))["steering"]
    assert not any(line.startswith("warning") for line in done) and any("within 30 deg" in line for line in done)
    smooth = run(compose("fieldcheck", [*base[:2], "controller=smooth", "controller.u_max=1", *base[3:]]))["steering"]
    assert [line for line in smooth if line.startswith("warning")] == [bare[1]]  # no push-out: not a hybrid law
    assert "Unicycle steering" in capsys.readouterr().out
