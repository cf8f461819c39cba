"""Perception certified under clouds (pipeline.certify.clouds, issue 44): tests that try to break it.

Soundness is checked through the loop's own path: `Camera.render(occlusion=..., clouds=...)` (the real
`Occlusion.apply`) and the deployed network; the probability part on synthetic draws whose law is known exactly and
on the level's own layout process.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from omegaconf import open_dict

from pipeline.certify import certified_error_bound, prepare
from pipeline.certify.clouds import (
    apply_table,
    cloud_window,
    cp_upper,
    draw_seed,
    eps_delta,
    layout_bounds,
    layout_maps,
    layout_prep,
    max_exceedances,
)
from pipeline.certify.renderer import pixel_window
from pipeline.errors import ConfigError, DatasetError
from pipeline.perception.network import FoldedPerceptionNet
from pipeline.render import Camera
from pipeline.render.occlusion import CloudSample, Occlusion, load_occlusion
from pipeline.train.module import PerceptionMap

SCENE = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))
SLACK = 1e-4  # float32 networks: the deployed net's own rounding (world units)

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


@pytest.fixture(scope="module")
def heavy():
    return load_occlusion("heavy")


def _amplified(seed, keypoint=False, gain=6.0):
    torch.manual_seed(seed)
    m = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", clamp=False,
                         position_head="keypoint" if keypoint else "flat").eval()
    with torch.no_grad():
        m.features[0].weight.mul_(gain)
        if not keypoint:
            m.head[-1].weight.mul_(gain)
    return m


@pytest.fixture(scope="module")
def trained(camera, heavy):
    """A small flat map fitted for a few seconds on clouded images."""
    torch.manual_seed(0)
    m = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", dropout=0.0)
    rng = np.random.default_rng(0)
    p = np.column_stack([rng.uniform(-47, 47, 512), rng.uniform(-27, 27, 512)])
    x, y = torch.from_numpy(camera.render(p, occlusion=heavy, rng=rng)), torch.as_tensor(p, dtype=torch.float32)
    opt = torch.optim.Adam(m.parameters(), lr=3e-3)
    for _ in range(100):
        idx = torch.as_tensor(rng.integers(0, len(p), 64))
        loss = torch.nn.functional.mse_loss(m.position_outputs(m.prepare(x[idx])), m.targets(y[idx]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    return m.eval()


def _cells(rng, n, side, lo=(-47.0, -27.0), hi=(47.0, 27.0)):
    c = np.column_stack([rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n)])
    return c, np.column_stack([c[:, 0] - side / 2, c[:, 0] + side / 2, c[:, 1] - side / 2, c[:, 1] + side / 2])


def _positions(rng, cells, m):
    t = rng.uniform(0, 1, (len(cells), m, 2))
    t[:, :4] = [[0, 0], [1, 1], [0, 1], [1, 0]]  # the corners
    return np.stack([cells[:, None, 0] + t[..., 0] * (cells[:, None, 1] - cells[:, None, 0]),
                     cells[:, None, 2] + t[..., 1] * (cells[:, None, 3] - cells[:, None, 2])], -1)


def _errors(model, camera, occ, clouds, p):
    """Errors `(C, m, 2)` of positions `p (C, m, 2)`, every frame rendered with the layout `clouds[0]`."""
    cl = clouds[np.zeros(p.shape[0] * p.shape[1], dtype=int)]
    imgs = camera.render(p.reshape(-1, 2), occlusion=occ, clouds=cl)
    with torch.no_grad():
        out = FoldedPerceptionNet(model)(torch.from_numpy(imgs))[:, :2].double().numpy()
    return out.reshape(p.shape) - p


# -------------------------------------------------------------------------------------------- the apply
def test_apply_is_the_affine_blend_with_half_a_level(camera, heavy):
    t = apply_table()
    exact = np.arange(256)[:, None] * (255 - np.arange(256)[None]) / 255
    assert np.abs(t - exact).max() <= 0.5  # exhaustive over every (level, opacity)
    assert np.array_equal(t[:, 0], np.arange(256)) and np.all(t[:, 255] == 0)
    rng = np.random.default_rng(1)
    clouds = heavy.sample(6, rng, camera.shape)
    lay = layout_maps(heavy, clouds, camera.background)
    img = rng.integers(0, 256, (6, *camera.shape, 3), dtype=np.uint8)
    out = img.copy()
    heavy.apply(out, clouds)
    model = t[img.astype(int), lay.alpha[..., None].astype(int)] + lay.tint
    assert np.array_equal(out, model)  # the per-pixel model of the bound is what apply does, bit for bit
    assert lay.alpha.max() > 200 and not lay.clear.any()


def test_pixel_forms_contain_the_clouded_render(camera, heavy):
    rng = np.random.default_rng(2)
    table = torch.as_tensor(apply_table())
    for side in (0.25, 1.0):
        _, cells = _cells(rng, 12, side, lo=(-50.5, -30.5), hi=(50.5, 30.5))
        clouds = heavy.sample(3, rng, camera.shape)
        lay = layout_maps(heavy, clouds, camera.background)
        pw0 = pixel_window(camera, torch.as_tensor(cells))
        p = _positions(rng, cells, 16)
        kr, kc = pw0.lo.shape[-2:]
        for j in range(len(lay)):
            a, b = torch.as_tensor(lay.alpha[j]), torch.as_tensor(lay.tint[j])
            pw = cloud_window(pw0, a.expand(len(cells), *a.shape), b.expand(len(cells), *b.shape), table)
            imgs = camera.render(p.reshape(-1, 2), occlusion=heavy, clouds=clouds[np.full(p.size // 2, j)])
            imgs = imgs.reshape(len(cells), -1, *camera.shape, 3).astype(float)
            m = 8
            padded = np.zeros((*imgs.shape[:2], 60 + 2 * m, 100 + 2 * m, 3))
            padded[:, :, m:-m, m:-m] = imgs
            static = np.zeros((60 + 2 * m, 100 + 2 * m, 3))
            static[m:-m, m:-m] = lay.static[j]
            t = (p - cells[:, None, [0, 2]]) / (cells[:, None, [1, 3]] - cells[:, None, [0, 2]]) * 2 - 1
            for i in range(len(cells)):
                r0, c0 = pw.origin[i].tolist()
                win = padded[i, :, r0 + m:r0 + m + kr, c0 + m:c0 + m + kc].transpose(0, 3, 1, 2)
                lo, hi = pw.lo[i].numpy(), pw.hi[i].numpy()
                ti = t[i][:, :, None, None, None]
                below = (lo[0] + lo[1] * ti[:, 0] + lo[2] * ti[:, 1] - win).max()
                above = (win - hi[0] - hi[1] * ti[:, 0] - hi[2] * ti[:, 1]).max()
                assert max(below, above) <= 1e-9, f"cell {cells[i]}, layout {j}: a pixel outside its bound"
                outside = np.ones(padded.shape[2:4], dtype=bool)
                outside[r0 + m:r0 + m + kr, c0 + m:c0 + m + kc] = False
                assert np.all(padded[i][:, outside] == static[outside][None]), "a pixel outside the window changed"


# -------------------------------------------------------------------------------------- (a) soundness
@pytest.mark.parametrize("which", ["trained", "amplified_keypoint", "amplified_flat"])
def test_layout_bound_contains_errors_of_real_clouded_renders(camera, heavy, trained, which):
    model = {"trained": trained, "amplified_keypoint": _amplified(3, keypoint=True),
             "amplified_flat": _amplified(4)}[which]
    rng = np.random.default_rng(5)
    _, cells = _cells(rng, 8, 0.5)
    medium = load_occlusion("medium")
    for occ in (heavy, medium):
        clouds = occ.sample(4, rng, camera.shape)
        lay = layout_maps(occ, clouds, camera.background)
        for mode in ("crown", "ibp"):
            _, lower, upper = layout_bounds(prepare(model, camera, 0.0, torch.float64), cells, lay, mode)
            p = _positions(rng, cells, 12)
            for j in range(len(lay)):
                e = _errors(model, camera, occ, clouds[j:j + 1], p)
                excess = np.maximum(lower[:, j, None] - e, e - upper[:, j, None]).max()
                assert excess <= SLACK, f"{which} {occ.name} {mode}: layout {j} error {excess:.3g} past its bound"


# -------------------------------------------------------------------------------- (b) a hidden robot
def test_a_layout_hiding_the_robot_is_not_certified_tight(camera, trained):
    wall = Occlusion(name="wall", probability=1.0, blobs=(1, 1), radius=(29.0, 29.0), opacity=(1.0, 1.0),
                     aspect=(1.0, 1.0), softness=0.05, bank=1, seed=0)
    full = (wall.fields(camera.shape)[0][0, :60, :100] == 255).astype(float)
    box = np.zeros((60, 100))
    box[20:41, 35:66] = 1
    hits = np.fft.ifft2(np.fft.fft2(full) * np.conj(np.fft.fft2(box))).real  # (dy, dx): opaque pixels in the box
    dy, dx = np.unravel_index(np.argmax(hits), hits.shape)
    clouds = CloudSample(np.array([True]), np.array([0]), np.array([dy]), np.array([dx]))
    lay = layout_maps(wall, clouds, camera.background)
    assert lay.alpha[0, 20:41, 35:66].min() == 255  # the middle of the image is fully hidden
    rng = np.random.default_rng(7)
    _, cells = _cells(rng, 40, 0.5, lo=(-12.0, -7.0), hi=(12.0, 7.0))
    p = _positions(rng, cells, 8)
    imgs = camera.render(p.reshape(-1, 2), occlusion=wall, clouds=clouds[np.zeros(p.size // 2, dtype=int)])
    assert np.all(imgs == imgs[:1])  # the robot is invisible: one image for every position
    eps, _, _ = layout_bounds(prepare(trained, camera, 0.0, torch.float64), cells, lay, "crown")
    e = np.linalg.norm(_errors(trained, camera, wall, clouds, p), axis=-1).max(1)
    assert np.all(eps[:, 0] + SLACK >= e)
    # the map's one guess is right at most near one place: every cell farther than 2 units from it stays uncertified
    with torch.no_grad():
        z = FoldedPerceptionNet(trained)(torch.from_numpy(imgs[:1]))[0, :2].double().numpy()
    far = np.hypot(np.maximum(0, np.maximum(cells[:, 0] - z[0], z[0] - cells[:, 1])),
                   np.maximum(0, np.maximum(cells[:, 2] - z[1], z[1] - cells[:, 3]))) > 2.0
    assert far.sum() >= 30 and np.all(eps[far, 0] > 2.0)


# ------------------------------------------------------------------------------------- (c) the CP bound
def test_clopper_pearson_bound():
    assert cp_upper(0, 299, 0.95) == pytest.approx(1 - 0.05 ** (1 / 299), rel=1e-12)
    assert cp_upper(299, 299, 0.95) == 1.0
    assert max_exceedances(298, 0.01, 0.95) == -1 and max_exceedances(299, 0.01, 0.95) == 0
    assert np.all(np.diff(cp_upper(np.arange(50), 50, 0.9)) > 0)
    assert np.all(np.isinf(eps_delta(np.zeros((2, 100)), 0.01, 0.95)))  # too few layouts: nothing claimed
    try:
        from scipy.stats import beta
    except ImportError:
        return
    k = np.arange(300)
    np.testing.assert_allclose(cp_upper(k, 300, 0.95), beta.ppf(0.95, k + 1, 300 - k), rtol=1e-10, atol=1e-13)


def test_eps_delta_holds_its_probability_on_a_known_law():
    """Bounds drawn from U(0, 1): Pr(X > e) = 1 - e exactly; over repeated draws of N layouts the claim
    "Pr(X > eps_delta) <= delta" must fail in at most 1 - confidence of them (up to sampling)."""
    rng = np.random.default_rng(0)
    for n, delta, conf in ((299, 0.01, 0.95), (1000, 0.01, 0.95), (500, 0.05, 0.9)):
        trials = 4000
        e = eps_delta(rng.uniform(size=(trials, n)), delta, conf)
        fail = float(((1 - e) > delta).mean())
        assert fail <= (1 - conf) + 3 * np.sqrt(conf * (1 - conf) / trials), (n, delta, conf, fail)
        assert fail >= (1 - conf) / 3  # and not vacuous: the bound is exact, not loose


def test_eps_delta_on_the_level_s_own_layouts(camera, heavy):
    """A deterministic bound of a layout (the cloud's opacity over a patch): eps_delta from 299 layouts of the
    heavy level, then the empirical rate above it over 20 000 fresh layouts sits under delta."""
    def patch(occ, cl):  # the layout's opacity over a 10 x 10 patch, as apply reads the bank (clear: 0)
        win = np.lib.stride_tricks.sliding_window_view(occ.fields(camera.shape)[0], (10, 10), axis=(1, 2))
        return np.where(cl.mask, win[cl.field, (cl.dy + 25) % 60, (cl.dx + 45) % 100].mean((1, 2)), 0.0)

    lay = layout_maps(heavy, heavy.sample(8, np.random.default_rng(10), camera.shape), camera.background)
    assert np.allclose(patch(heavy, lay.clouds), lay.alpha[:, 25:35, 45:55].mean((1, 2)))  # the same layouts
    for occ in (heavy, load_occlusion("medium")):
        bound = patch(occ, occ.sample(299, np.random.default_rng(11), camera.shape))
        ed = eps_delta(bound[None], 0.01, 0.95)[0]
        fresh = np.concatenate([patch(occ, occ.sample(2000, np.random.default_rng([12, i]), camera.shape))
                                for i in range(10)])
        rate = float((fresh > ed).mean())
        assert rate <= 0.01 + 3 * np.sqrt(0.01 * 0.99 / len(fresh)), (occ.name, ed, rate)


# -------------------------------------------------------------------------------- (d) a clear layout
@pytest.mark.parametrize("keypoint", [False, True])
def test_an_all_transparent_layout_is_the_clean_bound_exactly(camera, keypoint):
    model = _amplified(8, keypoint=keypoint)
    faint = Occlusion(name="faint", probability=1.0, blobs=(3, 3), radius=(8.0, 9.0), opacity=(0.001, 0.001),
                      bank=4, seed=1)
    rng = np.random.default_rng(9)
    clouds = faint.sample(2, rng, camera.shape)
    lay = layout_maps(faint, clouds, camera.background)
    assert faint.active and lay.alpha.max() == 0 and not lay.clear.any()
    _, cells = _cells(rng, 10, 0.25)
    prep = prepare(model, camera, 0.0, torch.float32)
    for mode in ("crown", "forward", "ibp"):
        with torch.no_grad():
            clean = certified_error_bound(prep, torch.as_tensor(cells), mode)
            under = certified_error_bound(layout_prep(prep, lay, 0), torch.as_tensor(cells), mode)
        assert torch.equal(clean.lower, under.lower) and torch.equal(clean.upper, under.upper), mode
    clear = layout_maps(faint, CloudSample(np.array([False]), np.array([0]), np.array([0]), np.array([0])),
                        camera.background)
    assert clear.clear[0] and layout_prep(prep, clear, 0) is prep


# ---- the Hydra app: bad settings are one line (exit 2) before any work; a tiny run writes its table and summary
def test_the_clouds_app_checks_its_settings_and_runs_tiny(tiny_maps, tmp_path):
    from pipeline.bracket.maps import (
        error_map,  # the bracket reads the output as its ε̄ (pipeline.bracket.clouds)
    )
    from pipeline.certify.clouds_cli import check
    from pipeline.certify.clouds_run import run
    from pipeline.cli import compose

    root, ids = tiny_maps
    base = [f"paths.models_dir={root / 'models'}", f"clouds.maps={ids['occluded']}",
            f"paths.certified_dir={tmp_path / 'certified'}", "clouds.progress=false"]
    for bad, field in (("clouds.delta=1.5", "clouds.delta"), ("clouds.layouts=0", "clouds.layouts"),
                       ("clouds.occlusion=foggy", "clouds.occlusion"), ("clouds.mode=exact", "clouds.mode")):
        with pytest.raises(ConfigError, match=rf"^{field}"):
            check(compose("certify_clouds", [*base, bad]))
    with pytest.raises(DatasetError, match="unknown perception map 'nope'"):
        check(compose("certify_clouds", [*base, "clouds.maps=nope"]))
    tiny = ["clouds.limit=2", "clouds.layouts=3", "clouds.delta=0.7", "clouds.samples=1", "clouds.fresh=4"]
    cfg = compose("certify_clouds", [*base, *tiny, f"hydra.run.dir={tmp_path}"])
    with open_dict(cfg):
        cfg.paths.output_dir = str(tmp_path)
    summary = run(cfg)
    assert summary["cells"] == 2 and summary["layouts"] == 3 and summary["sampled"]["violations"] == 0
    table = np.loadtxt(summary["path"] / "table.csv", delimiter=",", skiprows=1)
    assert table.shape == (2, 9) and (table[:, 4] > 0).all() and np.isfinite(table[:, 4]).all()  # k* = 0 of 3
    emap = error_map(SimpleNamespace(paths=SimpleNamespace(certified_dir=str(tmp_path / "certified"))),
                     SimpleNamespace(error_map=summary["path"].name, error_map_kappa=0.0))
    np.testing.assert_array_equal(emap.cells, table[:, :5])
    assert (emap.clouds.delta, emap.clouds.layouts, emap.clouds.cells) == (summary["delta"], 3, 2)
    assert emap.clouds.map_id == ids["occluded"].rsplit("-", 1)[-1]
    # each chunk of cells draws its own layouts (clouds.draw=per_chunk): with chunks of one cell, the first cell keeps
    # its draw (chunk 0's) and the second gets chunk 1's, other layouts, so another bound
    one = run(compose("certify_clouds", [*base, *tiny, "clouds.chunk=1", f"hydra.run.dir={tmp_path}"]))
    split = np.loadtxt(one["path"] / "table.csv", delimiter=",", skiprows=1)
    np.testing.assert_allclose(split[0, 4], table[0, 4], rtol=1e-5)
    assert abs(split[1, 4] - table[1, 4]) > 1e-4 * table[1, 4], (split[1, 4], table[1, 4])


def test_per_chunk_draws_are_independent_and_pool_to_the_expected_rate():
    """`draw_seed`: a shared draw is one event for every chunk (the pooled rate above eps_delta is that draw's,
    whatever the number of chunks); per-chunk draws are independent, so the pooled rate over many chunks sits at
    its expectation `1 / (N + 1)` for bounds drawn from U(0, 1) (Pr(X > e) = 1 - e; eps_delta the max of N)."""
    n, chunks = 299, 400
    def draw(seed):  # one draw of N layouts' bounds
        return np.random.default_rng(seed).uniform(size=n)

    def rates(how, seed):  # per chunk Pr(X > eps_delta) (eps_delta on a batch: its rows are the chunks' draws)
        return 1 - eps_delta(np.stack([draw(draw_seed(seed, how, c)) for c in range(chunks)]))

    assert draw_seed(5, "shared", 3) == draw_seed(5, "shared", 0) == 5
    assert draw_seed(5, "per_chunk", 3) != draw_seed(5, "per_chunk", 0)
    expected, sd = 1 / (n + 1), 1 / (n + 1) / np.sqrt(chunks)  # the max of N uniforms: 1 - max ~ Beta(1, N)
    for seed in range(5):
        shared, own = rates("shared", seed), rates("per_chunk", seed)
        assert np.ptp(shared) == 0  # one draw, every chunk the same
        assert np.ptp(own) > 0 and abs(own.mean() - expected) < 4 * sd, (seed, own.mean(), expected)
    # the shared draw's pooled rate is one Beta(1, N) sample: over seeds it spreads as one chunk's own rate does
    pooled = 1 - eps_delta(np.stack([draw(draw_seed(seed, "shared", 0)) for seed in range(200)]))
    assert pooled.std() > 10 * sd
