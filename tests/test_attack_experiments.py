"""Issue 20: the attacks as disturbances through the camera (config nodes, the context's attacked camera), the
attack scenarios at debug=tiny with trained (tiny) maps, and the margin map over the geometry."""

from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from shared import run_cli  # tests/shared.py

from pipeline.cli import compose
from pipeline.errors import ConfigError


def _cfg(tmp_path, *extra):
    return compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                   *extra])


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


# ------------------------------------------------------------------------------------------- config
BAD = [
    (["experiment=camera_attack", "disturbances.pixel_attack.kappa=300"], "disturbances.pixel_attack.kappa"),
    (["experiment=camera_attack", "disturbances.pixel_attack.kappa=-1"], "disturbances.pixel_attack.kappa"),
    (["experiment=camera_attack", "+disturbances.pixel_attack.kapa=3"], "disturbances.pixel_attack.kapa"),
    (["experiment=camera_attack", "disturbances.pixel_attack.step_size=0"], "disturbances.pixel_attack.step_size"),
    (["experiment=camera_attack", "experiment.kappas=[-1.0]"], "experiment.kappas"),
    (["experiment=camera_attack", "experiment.kappas=[]"], "experiment.kappas"),
    (["experiment=camera_attack", "experiment.attack=adversarial"], "experiment.attack"),
    (["experiment=camera_attack", "experiment.gated=[cbf2]"], "experiment.gated[0]"),
    (["experiment=camera_attack", "experiment.band=0"], "experiment.band"),
    (["experiment=worst_cloud", "disturbances.worst_cloud.candidates=0"], "disturbances.worst_cloud.candidates"),
    (["experiment=worst_cloud", "experiment.levels=[fog]"], "experiment.levels"),
    (["experiment=worst_cloud", "experiment.levels=[heavy,heavy]"], "experiment.levels"),
    (["experiment=worst_cloud", "disturbances.worst_cloud.level=fog"], "disturbances.worst_cloud.level"),
    (["experiment=worst_cloud", "experiment.record=light"], "experiment.record"),
    (["experiment=worst_cloud", "+experiment.occlusion=heavy"], "experiment.occlusion"),
    (["experiment=geometry_margin", "experiment.rho=[0.5,2.0]"], "experiment.rho"),
    (["experiment=geometry_margin", "experiment.apex_ratio=[1.2]"], "experiment.apex_ratio"),
]


@pytest.mark.parametrize("overrides,field", BAD, ids=[" ".join(o) for o, _ in BAD])
def test_bad_attack_keys_are_one_config_error(tmp_path, overrides, field):
    from pipeline.experiments.checks import check
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("experiments", [*overrides, "perception=oracle", f"paths.outputs_dir={tmp_path}"], check)
    assert err.value.field == field and "\n" not in str(err.value), str(err.value)


def test_bad_attack_input_on_the_command_line_is_one_line_exit_2(tmp_path):
    # the same entry in this process (tests/shared.py); each stage's fresh-interpreter case: test_config_truth.py
    for module, args, field in [
            ("pipeline.experiments", ["experiment=camera_attack", "disturbances.pixel_attack.kappa=300",
                                      "perception=oracle"], "disturbances.pixel_attack.kappa"),
            ("pipeline.simulate", ["disturbance=pixel_attack", "plot=false"], "disturbance")]:
        proc = run_cli(module, *args, f"paths.root_dir={tmp_path / 'o'}", f"hydra.run.dir={tmp_path / 'run'}")
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}"), proc.stderr
        assert not (tmp_path / "o" / "experiments").exists()


def test_the_attack_nodes_build_what_the_context_plugs_in(tmp_path):
    from pipeline.experiments.context import Context
    from pipeline.perception.adversary import AttackedCamera, PixelAttack, WorstCloud

    ctx = Context(_cfg(tmp_path, "experiment=camera_attack", "perception=oracle", "disturbances.pixel_attack.steps=3"))
    att = ctx.attack("pixel_attack", kappa=2.0)
    assert isinstance(att, PixelAttack) and (att.kappa, att.steps) == (2.0, 3)
    cloud = ctx.attack("worst_cloud", level="medium")
    assert isinstance(cloud, WorstCloud) and cloud.level == "medium" and cloud.candidates == 8
    with pytest.raises(ConfigError, match="experiment.attack"):
        ctx.attack("gaussian")
    hook = ctx.camera_measure("clean", attack=cloud)  # the oracle reads no image: the true state, no error
    assert isinstance(hook, AttackedCamera) and hook.occlusion.name == "medium"
    p = np.array([[-20.0, 0.3], [-30.0, -0.2]])
    np.testing.assert_array_equal(hook(p, np.arange(2), 0, np.random.default_rng(0)), p)
    assert hook.mean_norm == 0.0 and hook.table()["agent"].tolist() == [0, 1]


# ------------------------------------------------------------------------------ the induced error
class Centroid(torch.nn.Module):
    """The bright (leader) pixels' centroid in world units of the default arena: a differentiable stand-in map."""

    def forward(self, x):
        g = torch.relu(x.mean(-1) - 150.0)
        h, w = g.shape[1:]
        tot = g.sum((1, 2)) + 1e-6
        u = (g.sum(1) * (torch.arange(w, dtype=x.dtype) + 0.5)).sum(1) / tot
        v = (g.sum(2) * (torch.arange(h, dtype=x.dtype) + 0.5)).sum(1) / tot
        return torch.stack([u - 50.0, 30.0 - v], 1)


def test_the_attack_pushes_the_estimate_across_the_line_behind_the_obstacle():
    """Through the config's attack node and the real camera: the induced error points along -sign(b(p)) e_b, the
    direction of SPEC §3.5's state attack, for every agent on either side of K (and in a scene turned by 90°)."""
    from pipeline.control import Scene
    from pipeline.perception.adversary import PixelAttack, proposition1_direction
    from pipeline.render import Camera
    from pipeline.sim import Adversarial

    for target in ([40.0, 0.0], [0.0, 25.0]):
        scene = Scene(target=target)
        net = Centroid()
        pm = SimpleNamespace(net=net, device="cpu", has_uncertainty=False,
                             predict=lambda im, net=net: net(torch.from_numpy(np.asarray(im)).float()).double().numpy())
        hook = PixelAttack(kappa=8, steps=3).measure(Camera(scene), pm, proposition1_direction(scene))
        rng = np.random.default_rng(0)
        a, b = rng.uniform(-25, -12, 16), np.tile([0.4, -0.4], 8)
        p = scene.covering(0).from_frame(a, b)
        clean = pm.predict(Camera(scene).render(p))
        est = hook(p, np.arange(16), 1, rng)
        induced = est - clean
        d = Adversarial(eps=1.0)(p, 0, rng, scene)  # -sign(b) e_b
        along = np.einsum("ij,ij->i", induced, d)
        assert np.all(along > 0.02), along  # a stand-in map: a small shift, but every one along d
        np.testing.assert_allclose(hook.table()["along"], along, atol=1e-4)
        assert np.all(np.sign(np.einsum("ij,j->i", induced, scene.e_b)) == -np.sign(b))


def test_direction_with_several_obstacles_is_the_state_attack():
    from pipeline.control import Obstacle, Scene
    from pipeline.perception.adversary import proposition1_direction
    from pipeline.sim import Adversarial

    scene = Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=3.0),
                                                 Obstacle(center=[-30.0, 10.0], radius=3.0)])
    p = np.random.default_rng(1).uniform([-45, -25], [35, 25], (50, 2))
    np.testing.assert_array_equal(proposition1_direction(scene)(p), Adversarial(1.0)(p, 0, None, scene))


# -------------------------------------------------------------------------- scenarios, tiny maps


def _tiny(tmp_path, tiny_maps, exp, *extra):
    root, ids = tiny_maps
    return _cfg(tmp_path, f"experiment={exp}", "debug=tiny", f"paths.models_dir={root / 'models'}",
                f"maps.clean={ids['clean']}", f"maps.occluded={ids['occluded']}", "experiment.horizon=1.0", *extra)


def _written(out, name: str):
    return next(f for f in out["files"] if f.name == name)


def test_camera_attack_at_debug_tiny(tmp_path, tiny_maps):
    from pipeline.experiments.stage import run

    out = run(_tiny(tmp_path, tiny_maps, "camera_attack", "experiment.kappas=[0.0,8.0]", "experiment.gated=[hybrid]"))
    s = out["results"].tables["summary"]
    gate = out["results"].info["gate"]
    runs = 3 + (1 if gate is not None else 0)  # hybrid, smooth, cbf (+ the gated hybrid with an uncertainty head)
    assert len(s) == 2 * runs and set(s["budget"]) == {0.0, 8.0}
    assert (s["n"] == 2).all() and ((s["success_lo"] <= s["success_rate"]) & (s["success_rate"] <= s["success_hi"])).all()
    clean, attacked = s[s.budget == 0.0], s[s.budget == 8.0]
    assert (clean["induced_norm_run"] == 0).all()  # no budget, no induced error
    assert (attacked["induced_along_start"] > 0).all()  # the attack moves the estimate along -sign(b) e_b
    m = out["results"].tables["metrics"]
    assert len(m) == 2 * len(s)  # one row per agent and run
    assert _written(out, "fig14_camera_attack.png").stat().st_size > 1000


def test_worst_cloud_at_debug_tiny_with_animation(tmp_path, tiny_maps):
    from pipeline.experiments.stage import run

    out = run(_tiny(tmp_path, tiny_maps, "worst_cloud", "experiment.levels=[none,heavy]", "experiment.gated=[]",
                    "disturbances.worst_cloud.candidates=3"))
    res = out["results"]
    s = res.tables["summary"].set_index(["budget", "controller"])
    assert (s.loc["none", "induced_norm_run"] < 1e-6).all()  # no clouds: the clear image (float32, other batches)
    assert (s.loc["heavy", "induced_along_start"] >= 0).all()  # the worst of 3 is never better than the clear frame
    # the recorded runs keep one chosen cloud per attacked image, re-rendered for the animation
    rows, clouds = res.arrays["rec_smooth_rows"], res.arrays["rec_smooth_clouds"]
    assert len(rows) == len(clouds) > 0 and clouds[:, 0].all()  # `always`: every chosen layout has clouds
    gif = _written(out, "anim15_worst_cloud.gif")
    assert gif.stat().st_size > 10_000
    from PIL import Image

    with Image.open(gif) as im:  # debug=tiny's scale draws 8 frames as the paper's other animations do (40 at scale 1)
        assert im.n_frames == 8


# ------------------------------------------------------------------------------- geometry margin
def test_geometry_margin_grid_skips_invalid_cells_and_varies(tmp_path):
    """The grid is the product of the three lists; a cell whose barrier reaches the target is skipped with the
    scene's reason; the apex moves the margin (the bisection of HysteresisMargin, checked on one cell directly)."""
    from pipeline.experiments.attacks.margin import GeometryMargin
    from pipeline.experiments.context import Context
    from pipeline.experiments.scenario import practical_success

    ctx = Context(_cfg(tmp_path, "experiment=geometry_margin", "perception=oracle"))
    scen = GeometryMargin(id="g", title="g", apex_ratio=[2.0, 3.5], rho=[0.5], barrier_scale=[4.0, 40.0],
                          n_agents=10, tol=0.5, a_range=[-40.0, -20.0])
    res = scen.compute(ctx)
    df = res.tables["margin"]
    assert len(df) == 4 and list(df["apex_ratio"]) == [2.0, 2.0, 3.5, 3.5]
    bad = df[df.barrier_scale == 40.0]
    assert not bad["valid"].any() and bad["eps_margin"].isna().all() and bad["note"].str.contains("scene.target").all()
    good = df[df.valid].set_index("apex_ratio")
    assert good.loc[3.5, "eps_margin"] > good.loc[2.0, "eps_margin"] + scen.tol  # the margin varies with c / r
    row = good.loc[2.0]
    from pipeline.experiments.attacks.margin import cell_scene

    scene = cell_scene(ctx.scene_cfg, apex_ratio=2.0, rho=0.5, scale=4.0)
    for eps, robust in ((row.eps_margin, True), (row.eps_fails, False)):
        sim = ctx.simulate(ctx.controller("hybrid", scene=scene), res.arrays["x0"], scene=scene, record=False,
                           disturbance=ctx.disturbance("adversarial", eps=eps), model=scen.time_model)
        assert (practical_success(sim, ctx.delta, eps).mean() >= scen.success) == robust, eps
