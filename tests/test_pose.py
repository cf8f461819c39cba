"""The unicycle's perception (issue 19, SPEC §1, §2, §3.7): pose maps, their ε-error maps with the heading error,
the `vehicle` option of every stage that simulates, `camera.heading: camera | imu`, and their bad input."""

from __future__ import annotations

import math
import subprocess
import sys

import numpy as np
import pytest
from shared import run_cli, without_figures  # tests/shared.py

from pipeline import tracking
from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError
from pipeline.lineage import expected_errormap_id, expected_map_manifest
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


def test_error_map_of_a_pose_map_reports_the_heading_error_beside_the_position_error(tmp_path, monkeypatch):
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
    without_figures(monkeypatch, "errormap")
    other = run(_em_cfg(tmp_path, "headings=4"), perception_map=PoseMap(), camera=PoseCamera(),
                occlusions={"none": None}, dataset=Samples())
    assert other["path"] != path


def test_a_position_map_error_map_ignores_the_heading_grid(tmp_path, monkeypatch):
    from pipeline.errormap.stage import run

    without_figures(monkeypatch, "errormap")
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

    common = ["plot=false", "init=random", "init.n=12", "controller.guard=true", "sim.horizon=15"]
    uni = run(compose("simulate", ["vehicle=unicycle", *common, f"paths.output_dir={tmp_path / 'u'}"]))
    res = uni["result"]
    assert res.heading is not None and res.u.shape[-1] == 2  # (v, ω)
    assert uni["metrics"].success.all() and not uni["metrics"].collision.any()
    th0 = Unicycle().initial_heading(res.x0, None)
    assert np.allclose(res.heading[0], th0)  # vehicle.heading0 random, from vehicle.heading_seed
    # the integrator through the stage equals a direct simulate() without a plant: its numbers do not move
    from pipeline.config import build
    from pipeline.sim import CameraSettings, SimSettings, simulate

    cfg = compose("simulate", [*common, f"paths.output_dir={tmp_path / 'i'}"])
    integ = run(cfg)
    scene = build(cfg.scene, "scene")
    ref = simulate(scene, build(cfg.controller, "controller", scene=scene), integ["result"].x0,
                   sim=SimSettings(dt=0.01, horizon=15.0, record_every=5), camera=CameraSettings(period=0.05))
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
    r = run_cli(module, *args, f"paths.root_dir={tmp_path}")  # the entry in this process (tests/shared.py)
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

    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    model = PerceptionMap.of(outputs="pose", uncertainty="none", **kw)
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
    from pipeline.train.module import PerceptionMap

    for kw, field in (({"heading_head": "conv"}, "model.heading_head"), ({"heading_hidden": 0}, "model.heading_hidden"),
                      ({"heading_weight": 0.0}, "model.heading_weight")):
        with pytest.raises(ConfigError, match=field):
            PerceptionMap.of(outputs="pose", **kw)


# ---------------------------------------------------------------- the unicycle in the experiments Context
class MomentsMap:
    """A pose map that reads the image: the leader's intensity centroid (the marker's area centroid is the position,
    SPEC §1) and the marker's principal axis, pointed by the sign of its third moment (the apex is the long tail)."""

    pose, has_uncertainty, name, id, manifest = True, False, "moments", "0123456789", {}

    def __init__(self, camera):
        self.cam, self.bg = camera, camera.background[..., 2].astype(float)
        self.frames = 0

    def predict(self, images):
        self.frames += 1
        w = np.clip((np.asarray(images)[..., 2] - self.bg) / (255.0 - self.bg), 0.0, 1.0)  # the white marker
        h, wd = w.shape[1:]
        u, v = np.arange(wd) + 0.5, np.arange(h) + 0.5
        m = w.sum((1, 2))
        cu, cv = (w * u).sum((1, 2)) / m, (w * v[:, None]).sum((1, 2)) / m
        dx, dy = u[None, None] - cu[:, None, None], cv[:, None, None] - v[None, :, None]  # world axes
        sxx, syy, sxy = ((w * a * b).sum((1, 2)) / m for a, b in ((dx, dx), (dy, dy), (dx, dy)))
        axis = 0.5 * np.arctan2(2 * sxy, sxx - syy)
        along = dx * np.cos(axis)[:, None, None] + dy * np.sin(axis)[:, None, None]
        axis = np.where((w * along**3).sum((1, 2)) > 0, axis, axis + np.pi)
        return np.column_stack([self.cam.pixel_to_world(np.column_stack([cu, cv])), np.angle(np.exp(1j * axis))])


def _map_folder(root, name, outputs):
    """A tracked perception-map folder as the train stage writes its manifest (the model's outputs, scene, render)."""
    cfg = compose("train", [])
    meta = {"kind": "perception_map", "model": {"outputs": outputs}, "scene": tracking.to_plain(cfg.scene),
            "render": tracking.to_plain(cfg.render), "image_shape": [60, 100, 3], "arena": [[-50, 50], [-30, 30]]}
    with tracking.tracked_output(root, name, "0123456789", meta) as tmp:
        (tmp / "model.pt").write_text("stub")
    return root / f"{name}-0123456789"


def _uni_context(tmp_path, folder, *extra):
    from pipeline.experiments.context import Context

    cfg = compose("experiments", [f"paths.outputs_dir={tmp_path}", f"paths.models_dir={folder.parent}",
                                  "experiment=noise_failure", "vehicle=unicycle", f"maps.clean={folder.name}",
                                  "controller.guard=true", "sim.horizon=15", *extra])
    maps = {}

    def load_map(f, models_dir=None, device=None):
        ctx_cam = ctx.camera("clean")
        maps.setdefault("pm", MomentsMap(ctx_cam))
        return maps["pm"]

    ctx = Context(cfg, load_map=load_map)
    return ctx


def test_unicycle_with_a_pose_map_from_the_camera_reaches_the_target(tmp_path):
    folder = _map_folder(tmp_path / "models", "moments", "pose")
    ctx = _uni_context(tmp_path, folder)
    x0 = np.array([[-12.0, 2.0], [-37.0, -17.0], [-30.0, 20.0], [10.0, -20.0]])
    res = ctx.simulate(ctx.controller("hybrid"), x0, measure=ctx.camera_measure("clean"))
    m = res.metrics
    assert m["success"].all() and not m["collision"].any(), m
    assert ctx.perception_map("clean").frames > 10  # the heading came from the images
    live = np.isfinite(res.heading_measured) & np.isfinite(res.heading)
    err = np.degrees(np.abs(np.angle(np.exp(1j * (res.heading_measured - res.heading)))))[live]
    assert 0 < err.mean() < 5.0  # read from the image, not copied
    # the controller steers the look-ahead point around the inflated disc, the axle point stays out of the real one
    assert ctx.controller("hybrid").scene.obstacles[0].radius == pytest.approx(4.0 + 0.5)
    assert np.all(m["min_clearance"] > 0)


def test_imu_heading_is_the_true_heading_plus_noise(tmp_path):
    folder = _map_folder(tmp_path / "models", "moments", "pose")
    ctx = _uni_context(tmp_path, folder, "camera.heading=imu", "camera.heading_noise=0.1")
    measure = ctx.camera_measure("clean")
    rng = np.random.default_rng(0)
    c = np.column_stack([rng.uniform([-45, -25], [45, 25], (2000, 2)), rng.uniform(-np.pi, np.pi, 2000)])
    est = measure(c, np.arange(len(c)), 1, rng)
    assert np.abs(est[:, :2] - c[:, :2]).max() < 0.1  # the position: the map's, from the image
    d = np.angle(np.exp(1j * (est[:, 2] - c[:, 2])))
    assert d.std() == pytest.approx(0.1, rel=0.08) and abs(d.mean()) < 0.01  # N(0, 0.1): not the map's heading
    res = ctx.simulate(ctx.controller("hybrid"), np.array([[-12.0, 2.0], [-37.0, -17.0]]), measure=measure)
    assert res.metrics["success"].all()


def test_heading_from_the_camera_needs_a_pose_map_before_any_work(tmp_path):
    from pipeline.experiments.checks import check

    folder = _map_folder(tmp_path / "models", "clean", "position")
    base = [f"paths.outputs_dir={tmp_path}", f"paths.models_dir={folder.parent}", "experiment=noise_failure",
            f"maps.clean={folder.name}"]
    check(compose("experiments", base))  # the integrator reads no heading
    with pytest.raises(ConfigError, match="camera.heading"):
        check(compose("experiments", [*base, "vehicle=unicycle"]))
    check(compose("experiments", [*base, "vehicle=unicycle", "camera.heading=imu"]))


def test_a_tiny_pose_map_through_data_train_errormap_and_the_context(tmp_path, monkeypatch):
    """The plumbing with a real (tiny, untrained) pose map: the unicycle recipe's dataset, the train stage's pose
    metrics, the error map's heading error, and the map's heading in the camera-in-the-loop measurement."""
    from pipeline.data.stage import run as data_run
    from pipeline.errormap.stage import run as errormap_run
    from pipeline.experiments.context import Context
    from pipeline.perception.maps import load_perception_map
    from pipeline.train.stage import run as train_run

    paths = [f"paths.datasets_dir={tmp_path / 'datasets'}", f"paths.models_dir={tmp_path / 'models'}"]
    small = ["data=unicycle", "data.splits.train=256", "data.splits.val=64", "data.splits.test=64",
             "data.sampling.closed_loop.starts=8", "data.sampling.closed_loop.horizon=5.0"]
    assert data_run(compose("data", [*small, *paths]))["counts"]["train"] == 256
    train_cfg = compose("train", [*small, *paths, "model=pose", "trainer=debug", "eval_levels=[none]"])
    expected = expected_map_manifest(train_cfg)  # before training: what make paper pins the map's readers with
    out = train_run(train_cfg)
    metrics = out["metrics"]
    assert set(metrics["test_split"]["heading"]) == {"mean_deg", "median_deg", "p95_deg", "max_deg"}
    folder = tmp_path / "models" / f"{out['name']}-{out['id']}"
    pm = load_perception_map(folder, device="cpu")
    assert pm.pose
    em_args = [f"paths.errormaps_dir={tmp_path / 'em'}", *paths, "grid.step=10.0", "headings=2",
               "occlusion_levels=[none]", "formats=[png]", "train_samples=64", "progress=false", "device=cpu"]
    without_figures(monkeypatch, "errormap")  # the plumbing, not the figures
    em = errormap_run(compose("errormap", [f"maps={folder}", *em_args]))
    manifest = tracking.read_manifest(folder)
    assert {k: expected[k] for k in ("name", "id", "scene", "arena")} == \
        {k: manifest[k] for k in ("name", "id", "scene", "arena")}
    assert em["path"].name == "-".join(expected_errormap_id(expected, em_args)) == \
        "-".join(expected_errormap_id(folder, em_args))  # a pose map's error map: the id reads the model's outputs
    h = em["summary"]["levels"]["none"]["heading"]
    assert h["fields"] == 2 and 0 <= h["mean_deg"] <= 180
    cfg = compose("experiments", [f"paths.outputs_dir={tmp_path / 'out'}", *paths, "experiment=noise_failure",
                                  "vehicle=unicycle", f"maps.clean={folder.name}", "sim.horizon=0.5", "device=cpu"])
    ctx = Context(cfg, load_map=load_perception_map)
    res = ctx.simulate(ctx.controller("hybrid"), np.array([[-12.0, 2.0], [-37.0, -17.0]]),
                       measure=ctx.camera_measure("clean"), record_every=1)
    m0 = ctx.perception_map("clean").predict(ctx.camera("clean").render(res.p[0], heading=res.heading[0]))
    assert np.allclose(res.heading_measured[0], m0[:, 2])  # the first frame's heading is the map's
    from pipeline.certify.stage import run as certify_run  # the certified error map of the pose map

    without_figures(monkeypatch, "certify")  # the plumbing (table.md stays)
    cert = certify_run(compose("certify", ["debug=tiny", f"maps={folder}", *paths, "region=[[40.0,44.0],[-2.0,2.0]]",
                                           f"paths.certified_dir={tmp_path / 'certified'}", "kappas=[0.0]",
                                           "headings=2", "progress=false"]))
    r = cert["summary"]["kappas"]["0"]
    assert cert["summary"]["model"]["outputs"] == "pose" and cert["summary"]["headings"] == 2
    assert r["soundness"]["violations"] == 0 and r["soundness"]["samples"] == 4 * 2 * cert["summary"]["n_cells"]
    cells = np.load(cert["path"] / "cells.npz")
    op = cells["operational"]
    assert np.all(cells["heading_0"][op] >= cells["heading_emp_0"][op]) and np.all(cells["eps_0"][op] >= cells["emp_0"][op])
    assert r["heading_bar_deg"]["max"] <= 180 + 1e-9 and "Heading" in (cert["path"] / "table.md").read_text()
