"""The gate under clouds (pipeline.certify.gate, issue 44): tests that try to break it.

The gate's statistic is what the loop compares (`PerceptionMapPredictor.predicted_error`: the hypot of the variance
head's calibrated sigmas); its bounds are checked against frames rendered by the real camera under a fixed layout and
read by the deployed network (`FoldedPerceptionNet`), on make paper's occluded map (`tests/fixtures/
occluded_keypoint.pt`, production size, a gaussian variance head).
"""


import numpy as np
import pytest
import torch
from omegaconf import open_dict

from pipeline.certify import prepare
from pipeline.certify.clouds import eps_delta, layout_bounds, layout_maps
from pipeline.certify.gate import (
    CERTIFIED,
    FLAGGED,
    UNDECIDED,
    eps_delta_gated,
    gate_range,
    layout_gate,
    pool_matrix,
    shares,
    var_head,
    verdicts,
)
from pipeline.errors import ConfigError
from pipeline.render.occlusion import CloudSample, Occlusion, load_occlusion
from pipeline.train.module import PerceptionMap

REL = 1e-4  # float32: the deployed network's own rounding, relative to the predicted error
GATE = 0.5626522205725629  # the map's clean-image gate (its manifest's calibration.clean_gate_px; 1 px = 1 unit)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _band_cells(rng, n, side=0.25):
    c = np.column_stack([rng.uniform(-30.0, -11.5, n), rng.uniform(-2.0, 2.0, n)])
    return np.column_stack([c[:, 0] - side / 2, c[:, 0] + side / 2, c[:, 1] - side / 2, c[:, 1] + side / 2])


def _positions(rng, cells, m):
    t = rng.uniform(0, 1, (len(cells), m, 2))
    t[:, :4] = [[0, 0], [1, 1], [0, 1], [1, 0]]  # the corners
    return np.stack([cells[:, None, 0] + t[..., 0] * (cells[:, None, 1] - cells[:, None, 0]),
                     cells[:, None, 2] + t[..., 1] * (cells[:, None, 3] - cells[:, None, 2])], -1)


def _predicted(net, camera, p, occ=None, clouds=None):
    """The loop's gate statistic `(C, m)` at positions `p (C, m, 2)` (every frame with the layout `clouds[0]`)."""
    cl = None if clouds is None else clouds[np.zeros(p.shape[0] * p.shape[1], dtype=int)]
    imgs = camera.render(p.reshape(-1, 2), occlusion=occ, clouds=cl)
    with torch.no_grad():
        out = net(torch.from_numpy(imgs)).double().numpy()
    return np.hypot(out[:, 2], out[:, 3]).reshape(p.shape[:2]), imgs


def test_pooling_matrix_is_adaptive_average_pooling():
    x = torch.rand(1, 3, 60, 100, dtype=torch.float64)
    for th, tw in ((15, 25), (7, 9), (60, 100)):
        r, c = pool_matrix(60, th)[:, 24:-24], pool_matrix(100, tw)[:, 24:-24]
        ref = torch.nn.functional.adaptive_avg_pool2d(x, (th, tw))[0]
        assert torch.allclose(torch.einsum("ik,ckl,jl->cij", r, x[0], c), ref, atol=1e-12)
    with pytest.raises(ValueError, match="no uncertainty head"):  # the app names clouds.gate for such a map
        var_head(PerceptionMap.of(filters=(4, 8, 8), uncertainty="none"))


# ------------------------------------------------------------------------ (a) soundness on real clouded renders
def test_gate_bounds_contain_the_predicted_error_of_real_clouded_renders(production):
    model, net, camera = production
    rng = np.random.default_rng(44)
    cells = _band_cells(rng, 8)
    prep = prepare(model, camera, 0.0, torch.float32)
    for occ in (load_occlusion("heavy"), load_occlusion("medium")):
        clouds = occ.sample(3, rng, camera.shape)
        lay = layout_maps(occ, clouds, camera.background)
        for mode in ("crown", "ibp"):
            lower, upper = layout_gate(model, prep, cells, lay, mode)
            assert np.all(lower <= upper) and np.all(lower > 0)
            p = _positions(rng, cells, 24)
            for j in range(len(lay)):
                err, _ = _predicted(net, camera, p, occ, clouds[j:j + 1])
                excess = np.maximum(lower[:, j, None] - err, err - upper[:, j, None]) / upper[:, j, None]
                assert excess.max() <= REL, f"{occ.name} {mode} layout {j}: predicted error past its bound"
    # no layout: the clean images
    with torch.no_grad():
        lo, hi = (t.numpy() for t in gate_range(var_head(model), prep, cells, "crown"))
    err, _ = _predicted(net, camera, _positions(rng, cells, 24))
    assert np.all(lo[:, None] * (1 - REL) <= err) and np.all(err <= hi[:, None] * (1 + REL))


def test_gate_bounds_are_tight_on_a_tiny_cell(production):
    """Not vacuous: on a 1e-3 cell the bounds pinch the predicted error (the formula is the loop's)."""
    model, net, camera = production
    rng = np.random.default_rng(45)
    cells = _band_cells(rng, 6, side=1e-3)
    with torch.no_grad():
        lo, hi = (t.numpy() for t in gate_range(var_head(model), prepare(model, camera), cells, "crown"))
    err, _ = _predicted(net, camera, _positions(rng, cells, 4))
    assert np.all(hi - lo <= 0.25 * err.mean(1)), (lo, hi, err)


# ------------------------------------------------------------------------------- (b) a layout hiding the robot
def test_a_layout_hiding_the_robot_is_flagged_or_undecided_never_certified(production):
    model, net, camera = production
    wall = Occlusion(name="wall", probability=1.0, blobs=(1, 1), radius=(29.0, 29.0), opacity=(1.0, 1.0),
                     aspect=(1.0, 1.0), softness=0.05, bank=1, seed=0)
    full = (wall.fields(camera.shape)[0][0, :60, :100] == 255).astype(float)
    box = np.zeros((60, 100))
    box[20:41, 35:66] = 1
    hits = np.fft.ifft2(np.fft.fft2(full) * np.conj(np.fft.fft2(box))).real
    dy, dx = np.unravel_index(np.argmax(hits), hits.shape)
    clouds = CloudSample(np.array([True]), np.array([0]), np.array([dy]), np.array([dx]))
    lay = layout_maps(wall, clouds, camera.background)
    assert lay.alpha[0, 20:41, 35:66].min() == 255
    rng = np.random.default_rng(7)
    c = np.column_stack([rng.uniform(-12.0, 12.0, 16), rng.uniform(-7.0, 7.0, 16)])
    cells = np.column_stack([c[:, 0] - 0.25, c[:, 0] + 0.25, c[:, 1] - 0.25, c[:, 1] + 0.25])
    p = _positions(rng, cells, 6)
    err, imgs = _predicted(net, camera, p, wall, clouds)
    assert np.all(imgs == imgs[:1])  # the robot is invisible: one image, one predicted error
    prep = prepare(model, camera, 0.0, torch.float32)
    eps, _, _ = layout_bounds(prep, cells, lay, "crown")
    lower, upper = layout_gate(model, prep, cells, lay, "crown")
    value = float(err[0, 0])
    assert np.all(lower[:, 0] <= value * (1 + REL)) and np.all(value <= upper[:, 0] * (1 + REL))
    assert np.all(upper - lower <= 1e-3 * value)  # the image is known exactly: so is the statistic
    at = 0.3  # below the cell's half-diagonal (0.35): no one constant guess is within it over the cell
    for g, expect in ((0.5 * value, FLAGGED), (2.0 * value, UNDECIDED)):
        v = verdicts(eps, lower, at, g)
        assert np.all(v != CERTIFIED) and np.all(v == expect), (g, value)
    many = lambda a: np.tile(a, (1, 50))  # noqa: E731 (50 draws of this one layout: enough for delta 10%)
    assert np.all(eps_delta_gated(many(eps), many(lower), 0.5 * value, 0.1, 0.9) == 0)  # all dropped: no error
    assert np.all(eps_delta_gated(many(eps), many(lower), 2.0 * value, 0.1, 0.9) == eps[:, 0])
    assert value > GATE  # the map's own clean gate flags this layout everywhere


# ------------------------------------------------------------------------------------- the verdicts' counting
def test_eps_delta_gated_counts_only_what_is_neither_certified_nor_flagged():
    rng = np.random.default_rng(0)
    eps, glo = rng.uniform(0, 4, (5, 299)), rng.uniform(0, 1, (5, 299))
    assert np.array_equal(eps_delta_gated(eps, glo, np.inf), eps_delta(eps))  # a gate nothing passes: as before
    eg = eps_delta_gated(eps, glo, 0.5)
    assert np.all(eg <= eps_delta(eps))
    kept = glo <= 0.5
    assert np.array_equal(eg, np.where(kept, eps, 0).max(1))  # N = 299, delta 1%: k* = 0, the largest kept
    sh = shares(eps, glo, 2.0, 0.5)
    v = verdicts(eps, glo, 2.0, 0.5)
    assert np.allclose(sh["flagged_share"] + sh["undecided_share"] + (v == CERTIFIED).mean(1), 1.0)
    assert np.array_equal(sh["undecided_share"] == 0, ((eps > 2.0) & kept).sum(1) == 0)


# --------------------------------------------- (c) gate null is today's app, (d) a bad gate is one line naming it
def test_the_clouds_app_with_and_without_a_gate(tiny_maps, tmp_path):
    from pipeline.certify.clouds_cli import check
    from pipeline.certify.clouds_run import run
    from pipeline.cli import compose

    root, ids = tiny_maps
    base = [f"paths.models_dir={root / 'models'}", f"clouds.maps={ids['occluded']}",
            f"paths.certified_dir={tmp_path / 'certified'}", "clouds.progress=false"]
    for bad in ("clouds.gate=-1", "clouds.gate=0", "clouds.gate=abc", "clouds.gate=true", "clouds.gate=[1]"):
        with pytest.raises(ConfigError, match=r"^clouds\.gate") as err:
            check(compose("certify_clouds", [*base, bad]))
        assert "\n" not in str(err.value)
    tables, summaries = [], []
    for gate in ("null", "0.5"):
        out = tmp_path / gate
        cfg = compose("certify_clouds", [*base, "clouds.limit=2", "clouds.layouts=3", "clouds.samples=1",
                                         "clouds.fresh=4", f"clouds.gate={gate}", f"hydra.run.dir={out}"])
        with open_dict(cfg):
            cfg.paths.output_dir = str(out)
        summaries.append(run(cfg))
        tables.append(np.loadtxt(summaries[-1]["path"] / "table.csv", delimiter=",", skiprows=1))
    plain, gated = summaries
    assert tables[0].shape == (2, 9) and tables[1].shape == (2, 12)
    assert np.array_equal(tables[0], tables[1][:, :9], equal_nan=True)  # the gate changes nothing it did not add
    assert "gated" not in plain and "gate" not in plain["settings"]  # null: today's outputs, key for key
    assert gated["gated"]["sampled"]["violations"] == 0
    assert np.all(tables[1][:, 9] <= tables[1][:, 4])
    assert np.allclose(tables[1][:, 10] + tables[1][:, 11] + tables[1][:, 6], 1.0)


def test_clouds_gate_clean_is_the_maps_own_gate_and_names_the_key_without_one(tiny_maps, tmp_path):
    """`clouds.gate=clean` reads the gate the train stage fitted (the loop's operating point), so a certificate is not
    run against a gate copied by hand from another map; the number enters the id as if it had been passed."""
    from pipeline import tracking
    from pipeline.certify.clouds_cli import check, clean_gate
    from pipeline.cli import compose

    root, ids = tiny_maps
    base = [f"paths.models_dir={root / 'models'}", f"paths.certified_dir={tmp_path / 'certified'}"]
    gate = tracking.read_manifest(root / "models" / ids["occluded"])["metrics"]["calibration"]["clean_gate"]["gate_px"]
    s = check(compose("certify_clouds", [*base, f"clouds.maps={ids['occluded']}", "clouds.gate=clean"]))["settings"]
    given = check(compose("certify_clouds", [*base, f"clouds.maps={ids['occluded']}", f"clouds.gate={gate!r}"]))
    assert s.gate == gate and s.recipe() == given["settings"].recipe()
    flat = tmp_path / "flat_map-0123456789"  # a map without an uncertainty head has no clean gate in its manifest
    flat.mkdir()
    (flat / "manifest.json").write_text('{"id": "0123456789", "metrics": {"test_split": {"mae_px": 0.1}}}')
    with pytest.raises(ConfigError, match=r"^clouds\.gate: clean: perception map flat_map-0123456789 has no clean"):
        clean_gate(flat)


def test_the_clouds_progress_moves_within_a_chunk(tiny_maps, tmp_path, monkeypatch, capsys):
    """A heavy chunk is minutes of bounds (64 cells x 299 layouts): the bar moves per layout, bounds and gate, not
    once per chunk (a run of 3 chunks printed nothing for ten minutes)."""
    import re

    from pipeline import progress as pr
    from pipeline.certify.clouds_run import run
    from pipeline.cli import compose

    monkeypatch.setattr(pr, "LINE_INTERVAL", 0.0)
    monkeypatch.setattr(pr, "DELAY", 0.0)
    root, ids = tiny_maps
    cfg = compose("certify_clouds", [f"paths.models_dir={root / 'models'}", f"clouds.maps={ids['occluded']}",
                                     f"paths.certified_dir={tmp_path / 'certified'}", "clouds.limit=2",
                                     "clouds.layouts=4", "clouds.samples=1", "clouds.fresh=2", "clouds.gate=0.5",
                                     f"hydra.run.dir={tmp_path}"])
    with open_dict(cfg):
        cfg.paths.output_dir = str(tmp_path)
    run(cfg)
    done = [int(n) for n in re.findall(r"x 4 layouts: (\d+)/2 cell", capsys.readouterr().err)]
    assert 1 in done and done[-1] == 2, done  # one chunk of 2 cells: a cell's worth of layout passes shows
