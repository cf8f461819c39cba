"""Several obstacles in the experiments (issue 19): starts near every obstacle's K, random fields drawn from the
composed scene, the cells scenario, Proposition 1 behind every obstacle, the guard in the sample-and-hold table,
and the map's scene checked against the simulated one."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from pipeline.cli import compose
from pipeline.control import Scene, in_diamond
from pipeline.control.fields import random_scene
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.sim.starts import BehindObstacles


def _cfg(tmp_path, *extra):
    return compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                   "perception=oracle", "debug=tiny", *extra])


def _cells(scene: Scene, pts: np.ndarray) -> np.ndarray:
    arr = scene.arrays
    rel = pts[:, None, :] - arr["center"][None]
    return (np.hypot(rel[..., 0], rel[..., 1]) - arr["R"][None]).argmin(axis=1)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(seed=st.integers(0, 40), m=st.integers(2, 5), band=st.floats(0.1, 1.5))
def test_behind_obstacles_lie_near_each_K_in_its_cell(seed, m, band):
    scene = random_scene(n_obstacles=m, seed=seed)
    gen = BehindObstacles(n=60, seed=seed, band=band, depth=8.0)
    which = gen.obstacles(scene)
    if not which:
        with pytest.raises(ConfigError, match="init.depth"):
            gen(scene)
        return
    pts = gen(scene)
    assert pts.shape == (60, 2)
    arr = scene.arrays
    cell = _cells(scene, pts)
    assert set(cell) <= set(which)
    for i in set(cell):
        a, b = scene.covering(int(i)).to_frame(pts[cell == i])
        assert (a <= -arr["c"][i] - 1.0 + 1e-9).all() and (a >= -arr["c"][i] - 9.0 - 1e-9).all()  # behind its diamond
        assert (np.abs(b) < band).all()
    assert not in_diamond(scene, pts).any()
    (x0, x1), (y0, y1) = scene.bounds
    assert ((pts[:, 0] > x0) & (pts[:, 0] < x1) & (pts[:, 1] > y0) & (pts[:, 1] < y1)).all()


def test_field_scenes_need_a_random_field(tmp_path):
    from pipeline.experiments.multi.fields import field_scenes

    ctx = Context(_cfg(tmp_path, "experiment=multi_monte_carlo"))
    scenes = field_scenes(ctx, 4, [3, 5], seed=7)
    assert [s.n_obstacles for _, s in scenes] == [3, 5, 3, 5]
    assert len({tuple(np.round(s.arrays["center"][0], 6)) for _, s in scenes}) == 4  # every field its own draw
    with pytest.raises(ConfigError, match="scene=field"):
        field_scenes(Context(_cfg(tmp_path, "experiment=monte_carlo")), 2, [3], seed=0)


def test_cells_partition_the_arena_by_the_nearest_cell(tmp_path):
    from pipeline.experiments.multi.fields import MultiCells

    cfg = _cfg(tmp_path, "experiment=multi_cells")
    ctx = Context(cfg)
    scen = MultiCells(id="multi_cells", title="t", grid_step=2.0)
    res = scen.compute(ctx)
    a = res.arrays
    X, Y = np.meshgrid(a["x"], a["y"])
    pts = np.stack([X.ravel(), Y.ravel()], 1)
    assert (a["cell"].ravel() == _cells(ctx.scene, pts)).all()
    assert 0 < a["band"].mean() < 0.5  # the hysteresis band is a thin set between cells
    assert res.tables["obstacles"]["V1_slack"].gt(0).all()  # the field is valid (V1)
    assert res.tables["metrics"]["success"].all()
    i = a["i"]  # the recorded active obstacle is the nearest cell up to the hysteresis along each run
    d = ctx.controller("hybrid").cell_distance(a["p"].reshape(-1, 2)).reshape(*i.shape, -1)
    active = np.take_along_axis(d, i[..., None].astype(int), axis=-1)[..., 0]
    assert (active <= d.min(axis=-1) + res.info["h"] + 0.6).all()  # + one frame of travel at u_max


def test_proposition1_behind_every_obstacle(tmp_path):
    """The adversary near each K_i stalls the smooth and CBF baselines and not the hybrid controller."""
    from pipeline.experiments.multi.fields import MultiAdversarial

    ctx = Context(_cfg(tmp_path, "experiment=multi_adversarial", "scale=0.1"))
    scen = MultiAdversarial(id="multi_adversarial", title="t", eps=[0.5], n_scenes=10, obstacles=[4])
    t = scen.compute(ctx).tables["summary"].set_index("controller")
    assert t.loc["hybrid", "success_rate"] == 1.0 and t.loc["hybrid", "collision_rate"] == 0.0
    assert t.loc["smooth", "success_rate"] <= 0.1 and t.loc["cbf", "success_rate"] <= 0.1
    assert t.loc["smooth", "stalled"] >= 0.9


def test_guard_shortens_the_sampled_arc_without_pushouts(tmp_path):
    """SPEC §3.3: with the guard the 20 Hz arc from (-12, 2) comes within 10% of the continuous one, 0 push-outs."""
    from pipeline.experiments.paper.theory import SampleAndHold

    ctx = Context(_cfg(tmp_path, "experiment=sample_and_hold"))
    df = SampleAndHold(id="s", title="t", initial_conditions=[[-12.0, 2.0]], limit_dt=0.005).compute(ctx).tables[
        "sample_and_hold"]
    row = df.iloc[0]
    assert row.pushouts_guarded == 0 < row.pushouts_sampled
    assert abs(row.t_guarded - row.t_continuous) <= 0.1 * row.t_continuous < abs(row.t_sampled - row.t_continuous)
    assert row.guard_frames > 0


def test_camera_on_a_field_needs_the_map_of_that_field(tmp_path, monkeypatch):
    from pipeline.experiments.multi.fields import MultiCamera

    ctx = Context(_cfg(tmp_path, "experiment=multi_camera"))
    monkeypatch.setattr(Context, "map_scene", lambda self, kind: Scene())  # a map trained on the default scene
    with pytest.raises(ConfigError, match="maps.field_heavy"):
        MultiCamera(id="multi_camera", title="t").check(ctx)
    monkeypatch.setattr(Context, "map_scene", lambda self, kind: self.scene)
    MultiCamera(id="multi_camera", title="t").check(ctx)


def test_monte_carlo_figure_takes_a_wilson_bound_an_ulp_below_a_rate_of_one(tmp_path):
    """Bug (make multi, 20 fields x 200 starts): every agent reached the target, the Wilson upper bound came out an
    ulp below 1.0 and matplotlib rejected the negative error bar after an hour of simulation."""
    import pandas as pd

    from pipeline.experiments.multi.figures import draw_multi_monte_carlo
    from pipeline.experiments.report import Outputs
    from pipeline.experiments.results import Results

    t = pd.DataFrame({"condition": ["none", "none"], "controller": ["hybrid", "smooth"], "n": [400, 400],
                      "success_rate": [1.0, 0.5], "success_lo": [0.99, 0.45], "success_hi": [1.0 - 1e-16, 0.55]})
    res = Results({"summary": t, "per_scene": t.assign(scene="field00")}, {}, {"scenes": ["field00", "field01"]})
    out = Outputs(tmp_path, "multi_monte_carlo")
    draw_multi_monte_carlo(None, None, res, out)
    assert (tmp_path / "fig19_multi_monte_carlo.png").stat().st_size > 1000
    assert pd.read_csv(tmp_path / "tab_multi_monte_carlo.csv")["success_rate"].tolist() == [1.0, 0.5]


def test_make_multi_pins_every_map_its_experiments_read_by_kind():
    """`make multi` trains `field_heavy_keypoint` (data=field_heavy model=keypoint) and its experiments read it as the
    kind `maps.field_heavy`: the orchestrator pins every kind whose map it built, by the map's name (before: only the
    kinds named like a map were pinned, so multi_camera would have resolved the name again instead of the pinned id)."""
    from pipeline.paper import experiment_pins

    multi = compose("multi", [])
    refs = {name: f"{name}-0123456789" for name in multi.maps}
    ems = {name: f"{name}-9876543210" for name in multi.errormaps}
    exp = compose("experiments", [])
    pins = experiment_pins(exp, refs, ems)
    kinds = {p.split("=")[0] for p in pins}
    used = {f"maps.{m}" for e in multi.experiments for m in _bundle_maps(e)}
    assert used and used <= kinds, (used, pins)
    assert "maps.field_heavy=field_heavy_keypoint-0123456789" in pins
    assert "errormaps.unicycle_pose=unicycle_pose-9876543210" in pins
    assert not any(p.startswith("errormaps.field_heavy") for p in pins)  # the experiments read no error map of it


def _bundle_maps(experiment: str) -> tuple[str, ...]:
    from pipeline.config import build

    cfg = compose("experiments", [f"experiment={experiment}"])
    return tuple(build(cfg.experiment, "experiment").maps)
