"""The falsifier through the camera (issue 28: `κ_hi`, pipeline.bracket.camera_falsifier) and its stage settings.

A differentiable stand-in for the perception map (the centroid of the bright pixels, in world units, as in
tests/test_attacks.py) and the real Camera keep the loops fast; the stage runs once with a tiny trained map.
"""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest
import torch
from torch import nn

from pipeline.bracket.camera_falsifier import (
    CAMERA_ADVERSARIES,
    CameraLoop,
    CameraSearch,
    falsify_camera,
    pgd,
    run_camera,
)
from pipeline.bracket.loop import REACHED, RUNNING, FrameLoop
from pipeline.config import compose
from pipeline.control import HybridController, Scene, SmoothController
from pipeline.errors import ConfigError
from pipeline.render import Camera

SCENE = Scene(target=[40.0, 0.0], obstacles=[{"center": [0.0, 0.0], "radius": 4.0}])
NEAR_K = np.array([[-20.0, 0.05], [-30.0, -0.1]])  # beside K, the axis behind the obstacle: the clean loop arrives


class Centroid(nn.Module):
    """Intensity-weighted centroid of the pixels brighter than `thr` (grey level), as world coordinates of the
    default 100 x 60 arena (1 px = 1 unit, row 0 at y = +30): the white vehicle. Differentiable in the image."""

    def __init__(self, thr: float = 150.0):
        super().__init__()
        self.thr = thr

    def forward(self, x):
        g = x.mean(-1)
        w = torch.relu(g - self.thr)
        h, wd = g.shape[1:]
        cols = torch.arange(wd, dtype=x.dtype) + 0.5
        rows = torch.arange(h, dtype=x.dtype) + 0.5
        tot = w.sum((1, 2)) + 1e-6
        return torch.stack([(w.sum(1) * cols).sum(1) / tot - 50.0, 30.0 - (w.sum(2) * rows).sum(1) / tot], 1)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


def camera_loop(law, camera, horizon=20.0):
    loop = FrameLoop(SCENE, law(SCENE), horizon=horizon, delta=5.0)
    return CameraLoop(loop, Centroid(), camera, CameraSearch(steps=3, n_dirs=8))


def test_pgd_with_one_budget_is_the_pixel_attack(camera):
    from pipeline.perception.attacks import pixel_attack

    rng = np.random.default_rng(3)
    p = np.column_stack([rng.uniform(-40, 30, 6), rng.uniform(-22, 22, 6)])
    d = np.tile([0.0, -1.0], (6, 1))
    imgs = camera.render(p)
    clean, att = pgd(Centroid(), imgs, d, np.full(6, 6.0), 3)
    ref = pixel_attack(Centroid(), imgs, d, kappa=6.0, steps=3)
    np.testing.assert_array_equal(clean, ref.clean)  # one PGD (issue 47): the falsifier's is the pixel attack
    np.testing.assert_array_equal(att, ref.attacked)
    assert (ref.along > 0).all()


def test_pgd_budgets_per_run_are_batch_invariant(camera):
    """One batch with a budget per image is each image attacked alone; κ < 1 moves nothing; it never helps."""
    p = np.array([[-20.0, 0.5], [-10.0, 8.0], [5.0, -12.0], [20.0, 3.0], [-35.0, -20.0]])
    d = np.array([[0.0, -1.0], [1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.6, 0.8]])
    kappa = np.array([0.0, 0.9, 2.0, 6.0, 12.0])
    imgs = camera.render(p)
    clean, att = pgd(Centroid(), imgs, d, kappa, 3)
    c2, a2 = pgd(Centroid(), imgs, d, kappa, 3, batch_size=2)
    np.testing.assert_array_equal(c2, clean)
    np.testing.assert_array_equal(a2, att)
    for i in range(len(p)):
        c1, a1 = pgd(Centroid(), imgs[i : i + 1], d[i : i + 1], kappa[i : i + 1], 3)
        np.testing.assert_allclose(clean[i], c1[0], atol=1e-9)
        np.testing.assert_allclose(att[i], a1[0], atol=1e-9)
    np.testing.assert_array_equal(att[:2], clean[:2])
    along = np.einsum("ij,ij->i", att - clean, d)
    assert (along >= 0).all() and (along[2:] > 0).all()
    assert along[4] > along[2]  # a larger budget moves the estimate further here


def test_kappa_zero_is_the_clean_loop(camera):
    """κ = 0: every adversary delivers the clean image, and the loop is the map's own estimate frame by frame."""
    cl = camera_loop(SmoothController, camera, horizon=6.0)
    paths = [run_camera(cl, NEAR_K, np.zeros(2), kind)["path"] for kind in CAMERA_ADVERSARIES]
    np.testing.assert_array_equal(paths[0], paths[1])
    net, loop = Centroid(), cl.loop

    def error(p):
        with torch.no_grad():
            return net(torch.from_numpy(camera.render(p)).float()).double().numpy() - p

    st = loop.start(NEAR_K, error(NEAR_K))
    ref = [st["p"]]
    while st["frame"] < loop.n_frames and (st["outcome"] == RUNNING).any():
        st = loop.step(st, error(st["p"]))
        ref.append(st["p"])
    np.testing.assert_allclose(paths[0], np.stack(ref), atol=1e-9)


def test_smooth_law_is_falsified_through_the_camera_near_K_and_the_hybrid_is_not(camera):
    """Proposition 1 through the camera: from beside `K` the clean loop arrives, a pixel budget found by the
    bisection stalls the smooth law (its counterexample replays), one level less fails under no adversary; the
    hybrid law arrives from the same starts under every budget up to `kappa_max`."""
    kappa_max = 16
    smooth = camera_loop(SmoothController, camera)
    assert (run_camera(smooth, NEAR_K, np.zeros(2), "fixed")["outcome"] == REACHED).all()
    br = falsify_camera(smooth, NEAR_K, kappa_max)
    assert np.isfinite(br.kappa_hi).all() and (br.kappa_hi >= 1).all() and (br.kappa_hi <= kappa_max).all()
    assert np.isfinite(br.path).all()
    assert (np.hypot(*(br.path[-1] - SCENE.p_T).T) > 5.0).all()  # the counterexamples never arrive
    assert (np.hypot(*(br.path - SCENE.p_0).reshape(-1, 2).T) >= 4.0).all()
    # the replays run the starts in one batch (a budget per run; runs are independent: batch invariance above)
    for kind in set(br.adversary.tolist()):
        rows = br.adversary == kind
        again = run_camera(smooth, NEAR_K[rows], br.kappa_hi[rows], str(kind))
        assert (again["outcome"] != REACHED).all()
        np.testing.assert_allclose(again["path"][-1], br.path[-1, rows])
    for kind in CAMERA_ADVERSARIES:  # the bisection's last passing level: κ_hi - 1
        assert (run_camera(smooth, NEAR_K, br.kappa_hi - 1, kind)["outcome"] == REACHED).all()
    assert br.tried[1] == ([float(kappa_max)], len(NEAR_K))  # the top of the range, tried first, fails from both
    hybrid = falsify_camera(camera_loop(HybridController, camera), NEAR_K, kappa_max)
    assert np.isinf(hybrid.kappa_hi).all() and np.isnan(hybrid.path).all()


def test_a_start_the_clean_loop_breaks_has_kappa_hi_zero(camera):
    """On `K` itself the smooth law stalls with no attack at all: `κ_hi = 0`, adversary `none`."""
    br = falsify_camera(camera_loop(SmoothController, camera, horizon=10.0), np.array([[-25.0, 0.0]]), 8)
    assert br.kappa_hi[0] == 0 and br.adversary[0] == "none" and br.tried[0] == ([0.0], 1)
    assert len(br.tried) == 1  # nothing else to try


# ------------------------------------------------------------------------------------------ the stage
@pytest.mark.parametrize("override,field", [
    ("bracket.camera_map=no_such_map-0000000000", "bracket.camera_map"),
    ("bracket.kappa_max=0", "bracket.kappa_max"),
    ("bracket.kappa_max=256", "bracket.kappa_max"),
    ("bracket.kappa_max=2.5", "bracket.kappa_max"),
    ("bracket.pgd_steps=0", "bracket.pgd_steps"),
    ("bracket.camera_adversaries=[receding]", "bracket.camera_adversaries"),
    ("bracket.camera_adversaries=[]", "bracket.camera_adversaries"),
    ("bracket.camera_adversaries=[fixed,fixed]", "bracket.camera_adversaries"),
    ("bracket.camera_device=tpu", "bracket.camera_device"),
])
def test_bad_camera_input_is_one_config_error(tmp_path, override, field):
    from pipeline.bracket.stage import check
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("bracket", [override, f"paths.models_dir={tmp_path}", f"hydra.run.dir={tmp_path}"], check)
    assert err.value.field.startswith(field) and "\n" not in str(err.value), str(err.value)


def test_bad_camera_map_exits_2_in_one_line(tmp_path):
    """The command, run in this process (`run_cli`: it ends before any work): one line naming the key, exit 2."""
    from shared import run_cli

    proc = run_cli("pipeline.bracket", "bracket.camera_map=no_such_map-0000000000", f"paths.models_dir={tmp_path}",
                   f"hydra.run.dir={tmp_path / 'cli'}")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith("error: bracket.camera_map:"), \
        proc.stderr[-2000:]


TINY = ["bracket.cell=4.0", "bracket.start_cell=20", "bracket.eps=[0.1]", "bracket.n_bisect=0", "bracket.n_dirs=4",
        "bracket.tail=4", "bracket.lookahead=4", "bracket.commit=4", "sim.horizon=4", "bracket.controllers=[smooth]",
        "bracket.kappa_max=2", "bracket.pgd_steps=1", "bracket.polytope_split=0"]


def test_camera_map_of_another_scene_is_rejected(tmp_path, tiny_maps):
    from pipeline.bracket.stage import check
    from pipeline.preflight import preflight

    root, ids = tiny_maps
    args = [f"bracket.camera_map={ids['clean']}", f"paths.models_dir={root / 'models'}", "scene.target=[30.0,0.0]",
            f"hydra.run.dir={tmp_path}"]
    with pytest.raises(ConfigError) as err:
        preflight("bracket", args, check)
    assert err.value.field == "bracket.camera_map" and "another scene" in str(err.value)


def test_tiny_bracket_through_the_camera(tmp_path, tiny_maps):
    """The stage with a (tiny, barely trained) camera map: a `kappa_hi` column on the integer levels, the table's
    camera columns, the camera counterexamples; the map's id is part of the output's id."""
    from pipeline.bracket.stage import run

    root, ids = tiny_maps
    args = [*TINY, f"paths.models_dir={root / 'models'}", f"paths.outputs_dir={tmp_path}",
            f"paths.output_dir={tmp_path / 'run'}"]
    plain = run(compose("bracket", args))
    out = run(compose("bracket", [*args, f"bracket.camera_map={ids['clean']}"]))
    assert out["path"] != plain["path"] and "kappa_hi" not in plain["bracket"]
    df = pd.read_csv(out["path"] / "bracket.csv")
    assert set(df.kappa_hi.unique()) <= {0.0, 1.0, 2.0, np.inf}
    pd.testing.assert_series_equal(df.eps_hi, plain["bracket"].eps_hi)  # the state falsifier is unchanged
    assert "κ_hi" in (out["path"] / "table.md").read_text()
    paths = np.load(out["path"] / "counterexamples.npz")
    rows = np.isfinite(df.kappa_hi.to_numpy()) & (df.camera_adversary != "start in obstacle").to_numpy()
    assert paths["smooth_camera"].shape[1] == len(df) and np.isfinite(paths["smooth_camera"][:, rows]).all()
