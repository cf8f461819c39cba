"""The certified bound of a pose map (pipeline.certify, SPEC §5.1-5.2): cells of poses `(x, y, θ)`, the unicycle's
triangle marker inside the bound, the heading error. Tests that try to break it: the marker's pixel forms against
the uint8 renderer, the position and heading bounds against sampled poses through the deployed network, the heading
error's range against every corner of the box where it is known exactly, and the parts not covered refused."""

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from budget import examples  # tests/budget.py: more examples under make test-explore
from hypothesis import Phase, given, settings
from hypothesis import strategies as st

from pipeline.certify import certified_error_bound, prepare
from pipeline.certify.heading import heading_error
from pipeline.certify.renderer import pixel_window
from pipeline.certify.split import certify_cells, pose_cells, sampled_errors
from pipeline.errors import ConfigError
from pipeline.perception.network import FoldedPerceptionNet
from pipeline.render import Camera
from pipeline.train.module import PerceptionMap

SCENE = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))
PHASES = (Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink)
SLACK = 1e-4  # float32 networks: the deployed net's own rounding


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


def _pose_cells(rng, n, side, width):
    c = np.column_stack([rng.uniform(-46, 46, n), rng.uniform(-26, 26, n), rng.uniform(-math.pi, math.pi, n)])
    h = np.array([side / 2, side / 2, width / 2])
    return c, h, np.column_stack([c[:, 0] - h[0], c[:, 0] + h[0], c[:, 1] - h[1], c[:, 1] + h[1], c[:, 2] - h[2],
                                  c[:, 2] + h[2]])


def _samples(rng, c, h, m):
    t = rng.uniform(-1, 1, (len(c), m, 3))
    t[:, :8] = np.stack(np.meshgrid([-1, 1], [-1, 1], [-1, 1], indexing="ij"), -1).reshape(8, 3)  # the corners
    return t, c[:, None] + h * t


def _pose_map(seed, gain=4.0):
    torch.manual_seed(seed)
    m = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", clamp=False, position_head="keypoint", outputs="pose",
                      heading_head="attention").eval()
    with torch.no_grad():
        m.features[0].weight.mul_(gain)  # many ReLUs that switch with the marker
    return m


@settings(max_examples=examples(8), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), side=st.sampled_from([0.01, 0.25, 1.0]), width=st.sampled_from([0.01, 0.2, 1.0]),
       symbolic=st.booleans())
def test_marker_forms_contain_the_uint8_render(camera, seed, side, width, symbolic):
    rng = np.random.default_rng(seed)
    c, h, cells = _pose_cells(rng, 12, side, width)
    pw = pixel_window(camera, torch.as_tensor(cells), symbolic=symbolic)
    t, pose = _samples(rng, c, h, 24)
    imgs = camera.render(pose[..., :2].reshape(-1, 2), heading=pose[..., 2].ravel()).reshape(12, 24, 60, 100, 3)
    kr, kc = pw.lo.shape[-2:]
    m = 24
    padded = np.zeros((12, 24, 60 + 2 * m, 100 + 2 * m, 3))
    padded[:, :, m:-m, m:-m] = imgs
    bg = np.zeros((60 + 2 * m, 100 + 2 * m, 3))
    bg[m:-m, m:-m] = camera.background
    for i in range(len(c)):
        r0, c0 = pw.origin[i].tolist()
        win = padded[i, :, r0 + m:r0 + m + kr, c0 + m:c0 + m + kc].transpose(0, 3, 1, 2)
        lo, hi = pw.lo[i].numpy(), pw.hi[i].numpy()
        low, high = (f[0] + np.einsum("schw,ms->mchw", f[1:], t[i][:, :f.shape[0] - 1]) for f in (lo, hi))
        assert float(np.max(low - win)) <= 1e-9 and float(np.max(win - high)) <= 1e-9, f"cell {cells[i]}"
        outside = np.ones(padded.shape[2:4], dtype=bool)
        outside[r0 + m:r0 + m + kr, c0 + m:c0 + m + kc] = False
        assert np.all(padded[i][:, outside] == bg[outside][None]), f"cell {cells[i]}: a pixel outside changed"


@pytest.mark.parametrize("mode", ["ibp", "forward", "crown"])
@pytest.mark.parametrize("side, width", [(0.25, 0.2), (1.0, 1.0)])
def test_pose_bound_contains_sampled_errors(camera, mode, side, width):
    rng = np.random.default_rng(7)
    model = _pose_map(3)
    c, h, cells = _pose_cells(rng, 10, side, width)
    with torch.no_grad():
        b = certified_error_bound(prepare(model, camera), torch.as_tensor(cells), mode)
    t, pose = _samples(rng, c, h, 48)
    with torch.no_grad():
        out = FoldedPerceptionNet(model)(torch.from_numpy(camera.render(pose[..., :2].reshape(-1, 2),
                                                                        heading=pose[..., 2].ravel())))
    out = out.double().numpy().reshape(10, 48, 3)
    e = out[..., :2] - pose[..., :2]
    lo, hi = b.lower.numpy()[:, None], b.upper.numpy()[:, None]
    assert np.all(e >= lo - SLACK) and np.all(e <= hi + SLACK), f"{mode}: a sampled position error outside"
    he = np.abs(np.remainder(out[..., 2] - pose[..., 2] + math.pi, 2 * math.pi) - math.pi)
    assert np.all(he <= b.heading.numpy()[:, None] + 1e-5), f"{mode}: a sampled heading error above its bound"
    assert np.all(b.heading.numpy() <= math.pi + 1e-12)


@settings(max_examples=examples(60), deadline=None, phases=PHASES)
@given(cx=st.floats(-3, 3), cy=st.floats(-3, 3), wx=st.floats(0, 1.5), wy=st.floats(0, 1.5),
       th=st.floats(-math.pi, math.pi), w=st.floats(0, 0.6))
def test_heading_error_is_the_exact_range(cx, cy, wx, wy, th, w):
    """The heading error's bound is attained at a corner of the `(cos, sin)` box and an end of the heading interval
    (the box off the origin, the error below π), and no point inside exceeds it."""
    lo, hi = np.array([[cx, cy]]), np.array([[cx + wx, cy + wy]])
    f64 = lambda v: torch.tensor(v, dtype=torch.float64)  # noqa: E731
    bound = float(heading_error(f64(lo), f64(hi), f64([th - w]), f64([th + w])))
    wrap = lambda a: np.abs(np.remainder(a + math.pi, 2 * math.pi) - math.pi)  # noqa: E731
    holds_origin = cx <= 0 <= cx + wx and cy <= 0 <= cy + wy
    if holds_origin:
        assert bound == pytest.approx(math.pi)
        return
    rng = np.random.default_rng(0)
    pts = lo + rng.uniform(size=(4000, 2)) * (hi - lo)
    thetas = th + rng.uniform(-w, w, 4000)
    assert wrap(np.arctan2(pts[:, 1], pts[:, 0]) - thetas).max() <= bound + 1e-9
    corners = np.array([[a, b] for a in (cx, cx + wx) for b in (cy, cy + wy)])
    ends = np.array([th - w, th + w])
    exact = wrap(np.arctan2(corners[:, 1], corners[:, 0])[:, None] - ends[None]).max()
    if bound < math.pi - 1e-9:
        assert bound == pytest.approx(exact, abs=1e-9)


def test_pose_cells_split_with_their_heading_and_sample_inside(camera):
    """The stage's pose cells: `headings` intervals covering [-π, π]; splitting halves the heading as well; the
    sampled check compares every pose with its own cell's bounds (a bound lowered on purpose is caught)."""
    cells = pose_cells(np.array([[40.0, 41.0, -1.0, 0.0]]), 4)
    assert cells.shape == (4, 6) and cells[0, 4] == pytest.approx(-math.pi) and cells[-1, 5] == pytest.approx(math.pi)
    np.testing.assert_allclose(cells[1:, 4], cells[:-1, 5])
    model = _pose_map(5, gain=1.0)
    prep = prepare(model, camera)
    lower, upper, depth, leaves, heading = certify_cells(prep, cells, "forward", tolerance=0.0, max_depth=1,
                                                         progress=False)
    assert np.all(depth == 1) and np.all(leaves == 8) and np.all(np.isfinite(heading))
    predict = lambda imgs: FoldedPerceptionNet(model)(torch.from_numpy(imgs)).double().numpy()  # noqa: E731
    emp, violations, _, head_emp = sampled_errors(predict, camera, cells, lower, upper, 16, 0, progress=False,
                                                  heading=heading)
    assert violations == 0 and np.all(head_emp <= heading + 1e-5) and np.all(emp > 0)
    _, caught, worst, _ = sampled_errors(predict, camera, cells, lower, upper, 16, 0, progress=False,
                                         heading=head_emp * 0.5)
    assert caught > 0 and "heading" in worst[1]


def test_parts_the_bound_does_not_cover_are_refused(camera):
    with pytest.raises(ConfigError, match="attention heading head"):
        prepare(PerceptionMap.of(outputs="pose", uncertainty="none", filters=(4, 8, 8)).eval(), camera)  # pooled heading
    with pytest.raises(ValueError, match="heading interval"):
        certified_error_bound(prepare(_pose_map(1), camera), torch.zeros(2, 4), "ibp")
