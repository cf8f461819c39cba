"""The unicycle's perception (issue 19, SPEC §1, §2, §3.7): pose maps, their ε-error maps with the heading error,
the `vehicle` option of every stage that simulates, `camera.heading: camera | imu`, and their bad input."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest

from pipeline import tracking
from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError
from pipeline.plants import SingleIntegrator, Unicycle

ARENA = ((-50.0, 50.0), (-30.0, 30.0))
SCENE = {"_target_": "pipeline.control.Scene", "target": [40.0, 0.0], "obstacles": [{"center": [0.0, 0.0], "radius": 4.0}]}


# ------------------------------------------------------------------------------------- error maps
class PoseCamera:
    """'Images' are the poses themselves: `(x, y, θ)` per image (θ = 0 without a heading)."""

    arena = ARENA
    shape = (60, 100)

    def __init__(self):
        self.headings = []

    def render(self, points, occlusion=None, rng=None, clouds=None, heading=None):
        pts = np.asarray(points, dtype=float)
        th = np.zeros(len(pts)) if heading is None else np.asarray(heading, dtype=float)
        if heading is not None:
            self.headings.append(float(th[0]))
        return np.column_stack([pts, th])


class PoseMap:
    """A pose map with a known error: position bias `beta`, heading bias `b(θ) = 0.2 cos θ` (radians)."""

    pose = True

    def __init__(self, beta=(0.3, -0.4), pose=True, name="posemap", id_="pose000001"):
        self.beta, self.pose, self.name, self.id = np.asarray(beta), pose, name, id_
        self.manifest = {"dataset_id": "stubdata01", "scene": SCENE}

    def predict(self, images):
        x = np.asarray(images, dtype=float)
        pos = x[:, :2] + self.beta
        if not self.pose:
            return pos
        return np.column_stack([pos, x[:, 2] + 0.2 * np.cos(x[:, 2])])

    def camera(self):
        return PoseCamera()


class Samples:
    id, name = "stubdata01", "stub"

    def __init__(self, n=300):
        self._pos = np.random.default_rng(0).uniform([-50, -30], [50, 30], (n, 2))

    def positions(self, split):
        return self._pos

    def images(self, split):  # what the stub map reads: the pose (heading 0)
        return np.column_stack([self._pos, np.zeros(len(self._pos))])


def _em_cfg(tmp_path, *extra):
    return compose("errormap", ["maps=posemap", f"paths.errormaps_dir={tmp_path / 'em'}",
                                f"paths.models_dir={tmp_path / 'models'}", "grid.step=4.0", "formats=[png]",
                                "train_samples=null", "progress=false", "occlusion_levels=[none]", *extra])


def test_error_map_of_a_pose_map_reports_the_heading_error_beside_the_position_error(tmp_path):
    from pipeline.errormap.read import load_error_map, summary_table
    from pipeline.errormap.stage import heading_grid, run

    cam = PoseCamera()
    out = run(_em_cfg(tmp_path, "headings=8"), perception_map=PoseMap(), camera=cam, occlusions={"none": None},
              dataset=Samples())
    s, path = out["summary"], out["path"]
    grid = heading_grid(8)
    assert sorted(set(cam.headings)) == sorted(grid.tolist())  # every point rendered at each of the 8 headings
    assert np.allclose(s["headings_deg"], np.degrees(grid))
    r = s["levels"]["none"]
    assert r["mean"] == pytest.approx(0.5) and r["max"] == pytest.approx(0.5)  # |beta|, at every heading
    err = np.degrees(np.abs(0.2 * np.cos(grid)))  # the heading bias at each heading, the same at every point
    h = r["heading"]
    assert h["fields"] == 8 and h["mean_deg"] == pytest.approx(err.mean())
    assert h["max_deg"] == pytest.approx(err.max()) and h["worst_mean_deg"] == pytest.approx(err.max())
    assert h["p95_deg"] == pytest.approx(np.percentile(np.repeat(err, h["n"] // 8), 95))
    assert out["fields"]["H_none"].shape[0] == 8
    for f in ("heading.csv", "heading_error_map.png", "error_map.png"):
        assert (path / f).is_file(), f
    loaded = load_error_map(path.name, tmp_path / "em")
    assert loaded["levels"]["none"]["heading"]["p95_deg"] == pytest.approx(h["p95_deg"])
    table = summary_table([path.name], tmp_path / "em")
    assert table["heading_mean_deg"].iloc[0] == pytest.approx(err.mean())
    # the heading grid is part of a pose map's error-map id
    other = run(_em_cfg(tmp_path, "headings=4"), perception_map=PoseMap(), camera=PoseCamera(),
                occlusions={"none": None}, dataset=Samples())
    assert other["path"] != path


def test_a_position_map_error_map_ignores_the_heading_grid(tmp_path):
    from pipeline.errormap.stage import run

    runs = [run(_em_cfg(tmp_path, f"headings={n}", "force=true"), perception_map=PoseMap(pose=False, name="posmap"),
                camera=PoseCamera(), occlusions={"none": None}, dataset=Samples()) for n in (4, 8)]
    assert runs[0]["path"] == runs[1]["path"]  # not in its id
    s = runs[0]["summary"]
    assert "heading" not in s["levels"]["none"] and "headings_deg" not in s
    assert not (runs[0]["path"] / "heading.csv").exists() and "H_none" not in runs[0]["fields"]


def test_wrapped_heading_error_in_the_error_field():
    from pipeline.errormap import estimates as core

    pts = np.array([[0.0, 0.0], [1.0, 2.0]])
    render = lambda p, rng: np.column_stack([p, np.full(len(p), 3.1)])  # noqa: E731
    predict = lambda x: np.column_stack([x[:, :2], -3.1 * np.ones(len(x))])  # noqa: E731 - 6.2 rad apart: 0.083 wrapped
    e = core.error_field(predict, render, pts, heading=3.1)
    assert e.shape == (2, 3) and np.allclose(e[:, :2], 0.0)
    assert np.allclose(e[:, 2], 2 * math.pi - 6.2)


# ------------------------------------------------------------------------------------- the vehicle
def test_unicycle_initial_headings():
    class S:
        p_T = np.array([40.0, 0.0])

    p = np.array([[-12.0, 2.0], [40.0, 10.0]])
    assert np.allclose(Unicycle(heading0="target").initial_heading(p, S), [math.atan2(-2.0, 52.0), -math.pi / 2])
    assert np.allclose(Unicycle(heading0=0.5).initial_heading(p, S), 0.5)
    a, b = Unicycle(heading_seed=3).initial_heading(p, S), Unicycle(heading_seed=3).initial_heading(p, S)
    assert np.array_equal(a, b) and not np.array_equal(a, Unicycle(heading_seed=4).initial_heading(p, S))
    assert np.all(np.abs(a) <= math.pi)
    assert SingleIntegrator().initial_heading(p, S) is None
    for kw, field in (({"heading0": "north"}, "vehicle.heading0"), ({"heading0": float("nan")}, "vehicle.heading0"),
                      ({"heading_seed": -1}, "vehicle.heading_seed")):
        with pytest.raises(ConfigError, match=field):
            Unicycle(**kw)


def test_simulate_stage_drives_the_unicycle_and_keeps_the_integrator(tmp_path):
    from pipeline.simulate import run

    common = ["plot=false", "init=random", "init.n=12", "+controller.guard=true", "sim.horizon=15"]
    uni = run(compose("simulate", ["vehicle=unicycle", *common, f"paths.output_dir={tmp_path / 'u'}"]))
    res = uni["result"]
    assert res.heading is not None and res.u.shape[-1] == 2  # (v, ω)
    assert uni["metrics"].success.all() and not uni["metrics"].collision.any()
    th0 = Unicycle().initial_heading(res.x0, None)
    assert np.allclose(res.heading[0], th0)  # vehicle.heading0 random, from vehicle.heading_seed
    # the integrator through the stage equals a direct simulate() without a plant: its numbers do not move
    from pipeline.config import build
    from pipeline.sim import simulate

    cfg = compose("simulate", [*common, f"paths.output_dir={tmp_path / 'i'}"])
    integ = run(cfg)
    scene = build(cfg.scene, "scene")
    ref = simulate(scene, build(cfg.controller, "controller", scene=scene), integ["result"].x0, dt=0.01,
                   horizon=15.0, camera_period=0.05, record_every=5)
    assert np.array_equal(ref.p, integ["result"].p) and integ["result"].heading is None


def _stage(module, *args):
    return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO_ROOT, capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("module,args,field", [
    ("pipeline.simulate", ["vehicle=unicycle", "vehicle.heading0=north"], "vehicle.heading0"),
    ("pipeline.simulate", ["vehicle=unicycle", "vehicle.lookahead=1.5"], "vehicle.lookahead"),
    ("pipeline.simulate", ["vehicle=unicycle", "vehicle.heading_seed=-2"], "vehicle.heading_seed"),
    ("pipeline.simulate", ["camera.heading=gps"], "camera.heading"),
    ("pipeline.simulate", ["camera.heading_noise=-0.1"], "camera.heading_noise"),
    ("pipeline.experiments", ["experiment=noise_failure", "vehicle=unicycle", "vehicle.omega_max=-1"],
     "vehicle.omega_max"),
    ("pipeline.errormap", ["headings=0"], "headings"),
    ("pipeline.data", ["data=unicycle", "data.vehicle.heading0=north"], "data.vehicle.heading0"),
])
def test_bad_new_keys_one_line_exit_2(module, args, field, tmp_path):
    r = _stage(module, *args, f"paths.root_dir={tmp_path}")
    lines = [ln for ln in r.stderr.strip().splitlines() if ln.strip()]
    assert r.returncode == 2, r.stderr
    assert len(lines) == 1 and field in lines[0], r.stderr
    assert not any((tmp_path / d).exists() for d in ("data", "outputs"))  # before any work


def test_camera_settings_heading_keys():
    from pipeline.sim.settings import CameraSettings

    assert CameraSettings(heading="imu", heading_noise=0.05).heading == "imu"
    with pytest.raises(ConfigError, match="camera.heading"):
        CameraSettings(heading="gps")
    with pytest.raises(ConfigError, match="camera.heading_noise"):
        CameraSettings(heading_noise=-1.0)


def test_experiment_cache_key_of_the_integrator_has_no_vehicle_nor_heading_keys(tmp_path):
    from pipeline.experiments.checks import build_scenario
    from pipeline.experiments.context import Context
    from pipeline.experiments.stage import cache_key

    base = [f"paths.outputs_dir={tmp_path}", "perception=oracle", "experiment=noise_failure"]
    keys = {}
    for name, extra in (("default", []), ("noise", ["camera.heading_noise=0.3"]), ("uni", ["vehicle=unicycle"]),
                        ("uni_imu", ["vehicle=unicycle", "camera.heading=imu"])):
        cfg = compose("experiments", [*base, *extra])
        keys[name] = cache_key(cfg, build_scenario(cfg), Context(cfg))
    assert "vehicle" not in keys["default"] and "heading" not in keys["default"]["camera"]
    assert keys["noise"] == keys["default"]  # an integrator reads no heading
    assert keys["uni"]["vehicle"]["_target_"] == "pipeline.plants.Unicycle"
    assert tracking.content_id(keys["uni"]) != tracking.content_id(keys["uni_imu"])


# ------------------------------------------------------------------------------------- pose maps
def _pose_map(**kw):
    import torch

    from pipeline.perception.network import PerceptionMap

    torch.manual_seed(0)
    model = PerceptionMap(outputs="pose", uncertainty="none", **kw)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):  # non-trivial running statistics
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
    return model.eval()


@pytest.mark.parametrize("head", ["pooled", "flat"])
def test_folded_pose_map_matches_the_module(head):
    import torch

    from pipeline.perception.maps import PerceptionMapPredictor

    model = _pose_map(filters=[4, 8, 8], batch_norm=True, coord_channels=True, heading_head=head, heading_hidden=8)
    assert (model.heading_head is not None) == (head == "pooled")
    images = np.random.default_rng(1).integers(0, 256, (40, 60, 100, 3), dtype=np.uint8)
    with torch.inference_mode():
        ref = model(torch.from_numpy(images)).double().numpy()
    out = PerceptionMapPredictor(model, batch_size=16).predict(images)
    assert out.shape == (40, 3) and np.all(np.abs(out[:, 2]) <= math.pi)
    np.testing.assert_allclose(out[:, :2], ref[:, :2], atol=2e-3, rtol=0)
    d = np.angle(np.exp(1j * (out[:, 2] - ref[:, 2])))
    assert np.abs(d).max() < 1e-3


def test_pooled_heading_is_the_same_wherever_the_marker_lies():
    """Whole-cell shifts of the image (8 px: three pooling blocks) leave the max-pooled features' values, so the
    pooled head's heading, unchanged, where the flat head's changes (it reads each cell with its own weights)."""
    import torch

    from pipeline.render import Camera

    cam = Camera(None)  # a blank arena: only the vehicle's marker
    a = cam.render([[-20.0, 4.0]], heading=[0.7])
    b = cam.render([[-20.0 + 16.0, 4.0 - 8.0]], heading=[0.7])
    for head, same in (("pooled", True), ("flat", False)):
        model = _pose_map(filters=[4, 8, 8], batch_norm=False, coord_channels=False, heading_head=head)
        with torch.inference_mode():
            ta, tb = (model(torch.from_numpy(x))[0, 2].item() for x in (a, b))
        assert (abs(ta - tb) < 1e-5) == same, (head, ta, tb)


def test_pose_model_bad_keys():
    from pipeline.perception.network import PerceptionMap

    for kw, field in (({"heading_head": "conv"}, "model.heading_head"), ({"heading_hidden": 0}, "model.heading_hidden"),
                      ({"heading_weight": 0.0}, "model.heading_weight")):
        with pytest.raises(ConfigError, match=field):
            PerceptionMap(outputs="pose", **kw)
