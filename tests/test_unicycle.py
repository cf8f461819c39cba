"""The unicycle experiments (issue 19, SPEC §3.7): fields valid for the inflated discs, the `unicycle` bundle with a
pose map read from the camera, the imu ablation and the single integrator beside it, the `unicycle_field` bundle
through the stage, and the bad input of their keys."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from shared import run_cli  # tests/shared.py
from test_pose import MomentsMap, _map_folder

from pipeline.cli import compose
from pipeline.control.fields import random_scene
from pipeline.control.validity import field_violations
from pipeline.experiments.context import Context


@settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 30), m=st.integers(3, 5), d=st.sampled_from([0.25, 0.5]))
def test_a_field_drawn_with_an_inflation_is_valid_for_the_inflated_discs(seed, m, d):
    """`random_scene(inflation=d)`: the unicycle's steering scene (every disc grown by d) passes V1–V3 and keeps the
    starts clear; the real discs are the drawn ones."""
    keep = [[-40.0, 0.0], [-12.0, 2.0], [-37.0, -17.0]]
    scene = random_scene(n_obstacles=m, seed=seed, keep_free=keep, inflation=d)
    grown = scene.inflated(d).arrays
    assert np.allclose(grown["radius"], scene.arrays["radius"] + d)
    left = field_violations(grown["center"], grown["radius"], scene.p_T, apex=grown["c"], reach=grown["reach"],
                            h=1.0, u_max=10.0, T_s=0.05, arena=scene.bounds, starts=keep)
    assert left == [], left[0].line


def test_the_plain_field_fails_v3_once_inflated_and_field_unicycle_passes(tmp_path):
    """docs/multi.md: the `field` preset is not valid for the unicycle's inflated discs; `field_unicycle` is."""
    from pipeline.errors import ConfigError

    for scene, ok in (("field", False), ("field_unicycle", True)):
        cfg = compose("experiments", [f"paths.outputs_dir={tmp_path}", "perception=oracle", "vehicle=unicycle",
                                      f"scene={scene}", "controller.guard=true"])
        ctx = Context(cfg)
        ctrl = ctx.controller("hybrid")
        if ok:
            ctrl.check_loop(ctx.frame_period)
        else:
            with pytest.raises(ConfigError, match="V3"):
                ctrl.check_loop(ctx.frame_period)


def test_unicycle_bundle_with_a_pose_map_from_the_camera(tmp_path, monkeypatch):
    """The bundle end to end on the default scene with a pose map that reads the image (image moments): every
    condition reaches the target without a collision; the camera's heading is the map's (an error > 0), the imu's
    the true one plus its noise; the integrator runs the same starts; the drawing writes the table and a GIF."""
    from PIL import Image

    from pipeline.experiments.checks import build_scenario
    from pipeline.experiments.multi.unicycle_figures import draw_unicycle
    from pipeline.experiments.report import Outputs

    folder = _map_folder(tmp_path / "models", "moments", "pose")
    cfg = compose("experiments", [f"paths.outputs_dir={tmp_path}", f"paths.models_dir={folder.parent}",
                                  "experiment=unicycle", f"maps.unicycle_pose={folder.name}", "experiment.n_agents=4",
                                  "experiment.imu_noise=0.2", "sim.horizon=15", "scale=0.1"])
    maps = {}
    ctx = Context(cfg, load_map=lambda f, **kw: maps.setdefault("pm", MomentsMap(ctx.camera("unicycle_pose"))))
    monkeypatch.setattr(Context, "error_map", lambda self, kind: None)  # the stub map has no error map
    scen = build_scenario(cfg)
    res = scen.compute(ctx)
    t = res.tables["summary"].set_index(["condition", "vehicle"])
    assert len(t) == 4 and (t["n"] == 6).all()  # the paper's two starts and 4 random ones
    assert (t["success_rate"] == 1.0).all() and (t["collision_rate"] == 0.0).all(), t
    assert (t["clearance_min"] > 0).all()
    uni = t.xs("unicycle", level="vehicle")
    assert maps["pm"].frames > 10  # the camera conditions read the images
    h = uni["mean_heading_error_deg"]
    assert h["true_state"] < h["camera"] < 5.0  # the map's heading, not the true one
    assert h["imu"] > h["true_state"] + 3.0  # N(0, 0.2 rad): about 9 degrees
    assert t.loc[("true_state", "integrator"), "median_time_ratio"] == 1.0
    assert 1.0 <= uni.loc["true_state", "median_time_ratio"] < 1.5  # the unicycle turns first
    assert (uni["mean_omega_saturation"] > 0).all() and (uni["mean_omega_saturation"] < 0.5).all()
    out = Outputs(tmp_path / "paper", scen.id)
    draw_unicycle(scen, ctx, res, out)
    table = np.genfromtxt(tmp_path / "paper" / "tab_unicycle.csv", delimiter=",", names=True, dtype=None,
                          encoding=None)
    assert np.allclose(table["success_rate"], 1.0) and len(table) == 4
    with Image.open(tmp_path / "paper" / "anim21_unicycle.gif") as gif:
        assert gif.n_frames > 4


def test_unicycle_field_bundle_through_the_stage(tmp_path):
    """`python -m pipeline.experiments experiment=unicycle_field` (perfect map, debug=tiny): the field drawn for the
    inflated discs, every start reaches the target, the axle point stays off every real disc."""
    import pandas as pd

    from pipeline.experiments.stage import run

    run(compose("experiments", [f"paths.root_dir={tmp_path}", "experiment=unicycle_field", "perception=oracle",
                                "debug=tiny", "experiment.gif=false"]))
    folder = next((tmp_path / "outputs" / "experiments").glob("unicycle_field-*"))
    t = pd.read_csv(folder / "summary.csv")
    assert set(t["vehicle"]) == {"unicycle", "integrator"}
    assert (t["success_rate"] == 1.0).all() and (t["collision_rate"] == 0.0).all()
    m = pd.read_csv(folder / "metrics.csv")
    assert (m["min_clearance"] > 0).all()
    sat = m.groupby("vehicle")["saturated_frames"].sum()
    assert sat["unicycle"] > 0 == sat["integrator"]  # |ω| saturates when a random heading turns first


@pytest.mark.parametrize("args,field", [
    (["experiment=unicycle", "experiment.imu_noise=-1"], "experiment.imu_noise"),
    (["experiment=unicycle", "experiment.conditions=[gps]"], "experiment.conditions"),
    (["experiment=unicycle", "vehicle=integrator"], "vehicle"),
    (["experiment=unicycle", "scene=field"], "scene.obstacles"),  # V3 once the discs are inflated
    (["experiment=unicycle_field", "scene.inflation=-0.5"], "scene.inflation"),
])
def test_unicycle_bad_input_one_line_exit_2(args, field, tmp_path):
    r = run_cli("pipeline.experiments", *args, "perception=oracle", f"paths.root_dir={tmp_path}")  # tests/shared.py
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and field in lines[0], r.stderr
    assert not (tmp_path / "outputs").exists()  # before any work


def test_the_bundles_push_out_speed_keeps_the_unicycle_off_a_period_2_orbit_at_a_face():
    """docs/multi.md "push-out speed": a frame-flipping error of 0.5 (the alternating disturbance) puts the perceived
    look-ahead point inside a diamond every other frame. Pushed out at the full u_max = 10 the unicycle turns at
    20 rad/s (past omega_max = 4 pi): it reverses and turns 0.63 rad, the next frame's flow turns it back, and it
    stays at the face (0 of the starts arrive); at the bundles' push speed (below omega_max d / 2) every start
    arrives. The bundles must keep that value."""
    from pipeline.control import HybridController, Scene
    from pipeline.plants import Unicycle
    from pipeline.sim.disturbances import Alternating
    from pipeline.sim.simulator import SimSettings, simulate

    cfg = compose("experiments", ["experiment=unicycle", "perception=oracle"])
    push = float(cfg.controller.push_speed)
    uni = Unicycle(heading0="random")
    assert push <= uni.omega_max * uni.lookahead / 2
    scene = Scene()
    rng = np.random.default_rng(0)
    x0 = np.column_stack([rng.uniform(-25, -8, 12), rng.uniform(-12, 12, 12)])
    arrived = {}
    for speed in (10.0, push):
        ctrl = HybridController(uni.steering_scene(scene), push_speed=speed, guard=True)
        res = simulate(scene, ctrl, x0, sim=SimSettings(horizon=20.0), plant=uni,
                       heading0=uni.initial_heading(x0, scene), disturbance=Alternating(eps=0.5), record=False)
        arrived[speed] = res.metrics["success"].mean()
    assert arrived[10.0] <= 0.25 and arrived[push] == 1.0, arrived
