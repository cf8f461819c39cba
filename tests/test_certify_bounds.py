"""The certified error bound (pipeline.certify, SPEC §5.1-5.2): tests that try to break it.

Soundness is checked against the real uint8 renderer and the deployed network (`FoldedPerceptionNet`): the
bounds must contain `l(h(p)) - p` for sampled positions of random cells, on a random network with its first
layer and head amplified (many unstable ReLUs, an output that moves with the robot) and on a small network
trained for a few seconds; a joint PGD over the position and every image the relaxation admits (rounding,
`kappa`) must not get past the bound; a network whose range is known exactly (one linear layer on the
renderer) gets exactly that range plus the rounding term.
"""

import copy
from types import SimpleNamespace

import numpy as np
import pytest
import torch
from budget import examples  # tests/budget.py: more examples under make test-explore
from hypothesis import Phase, given, settings
from hypothesis import strategies as st
from shared import computed_once  # tests/shared.py

from pipeline.certify import certified_error_bound, prepare
from pipeline.certify.deployed import Deployed
from pipeline.certify.renderer import pixel_window
from pipeline.perception.network import FoldedPerceptionNet
from pipeline.render import Camera
from pipeline.train.module import PerceptionMap

SCENE = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))
SLACK = 1e-4  # float32 networks: the deployed net's own rounding (world units)
# no `explain` phase: its line tracing through the torch and numpy code of a failing example ran out of memory
PHASES = (Phase.explicit, Phase.reuse, Phase.generate, Phase.shrink)


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


def _cells(rng, n, side, lo=(-48.0, -28.0), hi=(48.0, 28.0)):
    c = np.column_stack([rng.uniform(lo[0], hi[0], n), rng.uniform(lo[1], hi[1], n)])
    h = np.broadcast_to(np.asarray(side, dtype=float) / 2, (n, 2))
    return c, h, np.column_stack([c[:, 0] - h[:, 0], c[:, 0] + h[:, 0], c[:, 1] - h[:, 1], c[:, 1] + h[:, 1]])


def _samples(rng, c, h, m):
    t = rng.uniform(-1, 1, (len(c), m, 2))
    t[:, :4] = [[-1, -1], [1, 1], [-1, 1], [1, -1]]  # the corners
    return c[:, None] + h[:, None] * t


def _errors(model, camera, p):
    imgs = camera.render(p.reshape(-1, 2))
    with torch.no_grad():
        out = FoldedPerceptionNet(model)(torch.from_numpy(imgs))[:, :2].double().numpy()
    return out.reshape(p.shape) - p


def _amplified(seed, filters=(4, 8, 8), gain=8.0):
    torch.manual_seed(seed)
    m = PerceptionMap.of(filters=filters, uncertainty="none", clamp=False).eval()
    with torch.no_grad():
        for mod in m.modules():
            if isinstance(mod, torch.nn.BatchNorm2d):
                mod.running_mean.uniform_(-0.2, 0.2)
                mod.running_var.uniform_(0.5, 2.0)
                mod.weight.uniform_(0.5, 1.5)
                mod.bias.uniform_(-0.2, 0.2)
        m.features[0].weight.mul_(gain)
        m.head[-1].weight.mul_(gain)
    return m


@pytest.fixture(scope="module")
def trained(camera, tmp_path_factory, worker_id):
    """A small map fitted for a few seconds (100 steps: errors of a few units, median 5.9 against 5.7 after 150;
    ReLUs that switch with the robot); fitted once for the xdist workers of a run (tests/shared.py)."""
    def fit():
        torch.manual_seed(0)
        return _fit(PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", dropout=0.0), camera, 0, 100)

    return computed_once(tmp_path_factory, worker_id, "certify_bounds_trained", fit)


def _fit(m, camera, seed: int, steps: int):
    """`m` fitted for `steps` Adam steps on 768 rendered positions (seeded), in eval mode."""
    return _train(_start(m, camera, seed), steps)


def _start(m, camera, seed: int) -> dict:
    """The state of `_fit` before its first step: the map, its optimiser, the seeded draws and the 768 positions."""
    rng = np.random.default_rng(seed)
    p = np.column_stack([rng.uniform(-47, 47, 768), rng.uniform(-27, 27, 768)])
    x, y = torch.from_numpy(camera.render(p)), torch.as_tensor(p, dtype=torch.float32)
    return {"m": m, "opt": torch.optim.Adam(m.parameters(), lr=3e-3), "rng": rng, "x": x, "y": y, "steps": 0}


def _train(state: dict, steps: int):
    """`state`'s fit continued up to `steps` Adam steps in all (the same steps as one fit of `steps`); the map in
    eval mode."""
    m, opt, rng, x, y = (state[k] for k in ("m", "opt", "rng", "x", "y"))
    m.train()
    for _ in range(steps - state["steps"]):
        idx = torch.as_tensor(rng.integers(0, len(x), 64))
        loss = torch.nn.functional.mse_loss(m.position_outputs(m.prepare(x[idx])), m.targets(y[idx]))
        opt.zero_grad()
        loss.backward()
        opt.step()
    state["steps"] = steps
    return m.eval()


# ----------------------------------------------------------------------------------------- renderer
@settings(max_examples=examples(12), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), side=st.sampled_from([0.01, 0.25, 0.7, 1.5]))
def test_pixel_forms_contain_the_uint8_render(camera, seed, side):
    rng = np.random.default_rng(seed)
    c, h, cells = _cells(rng, 24, (side, side * rng.uniform(0.3, 1.0)), lo=(-51, -31), hi=(51, 31))
    pw = pixel_window(camera, torch.as_tensor(cells))
    t = rng.uniform(-1, 1, (len(c), 32, 2))
    t[:, :4] = [[-1, -1], [1, 1], [-1, 1], [1, -1]]
    imgs = camera.render((c[:, None] + h[:, None] * t).reshape(-1, 2)).reshape(len(c), 32, 60, 100, 3)
    kr, kc = pw.lo.shape[-2:]
    m = 8
    padded = np.zeros((len(c), 32, 60 + 2 * m, 100 + 2 * m, 3))
    padded[:, :, m:-m, m:-m] = imgs
    bg = np.zeros((60 + 2 * m, 100 + 2 * m, 3))
    bg[m:-m, m:-m] = camera.background
    for i in range(len(c)):
        r0, c0 = pw.origin[i].tolist()
        win = padded[i, :, r0 + m:r0 + m + kr, c0 + m:c0 + m + kc].transpose(0, 3, 1, 2)
        lo, hi = pw.lo[i].numpy(), pw.hi[i].numpy()
        ti = t[i][:, :, None, None, None]
        below = float((lo[0] + lo[1] * ti[:, 0] + lo[2] * ti[:, 1] - win).max())
        above = float((win - hi[0] - hi[1] * ti[:, 0] - hi[2] * ti[:, 1]).max())
        assert max(below, above) <= 1e-9, f"cell {cells[i]}: a rendered pixel {max(below, above):.3g} outside"
        outside = np.ones(padded.shape[2:4], dtype=bool)  # every other pixel is the static image
        outside[r0 + m:r0 + m + kr, c0 + m:c0 + m + kc] = False
        same = bool(np.all(padded[i][:, outside] == bg[outside][None]))
        assert same, f"cell {cells[i]}: a pixel outside the window changed"


# ---------------------------------------------------------------------------------------- soundness
def _check(model, camera, cells, c, h, p, mode, dtype):
    with torch.no_grad():
        b = certified_error_bound(prepare(model, camera, 0.0, dtype), torch.as_tensor(cells), mode)
    e = _errors(model, camera, p)
    lo, hi = b.lower.double().numpy()[:, None], b.upper.double().numpy()[:, None]
    below, above = lo - e, e - hi
    worst = np.unravel_index(np.argmax(np.maximum(below, above).max(-1)), below.shape[:2])
    assert below.max() <= SLACK and above.max() <= SLACK, \
        f"counterexample: cell {cells[worst[0]]} p {p[worst]} e {e[worst]} bound {lo[worst[0], 0]} {hi[worst[0], 0]}"
    assert np.all(b.eps.double().numpy() + SLACK >= np.linalg.norm(e, axis=-1).max(1))
    return b, e


@settings(max_examples=examples(8), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), side=st.sampled_from([0.05, 0.25, 0.5]),
       mode=st.sampled_from(["ibp", "forward", "crown"]))
def test_bound_contains_sampled_errors_amplified_net(camera, seed, side, mode):
    rng = np.random.default_rng(seed)
    c, h, cells = _cells(rng, 16, side)
    _check(_amplified(seed), camera, cells, c, h, _samples(rng, c, h, 24), mode, torch.float64)


@settings(max_examples=examples(8), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), side=st.sampled_from([0.05, 0.25, 1.0]),
       mode=st.sampled_from(["forward", "crown"]), dtype=st.sampled_from([torch.float32, torch.float64]))
def test_bound_contains_sampled_errors_trained_net(camera, trained, seed, side, mode, dtype):
    rng = np.random.default_rng(seed)
    c, h, cells = _cells(rng, 16, side, lo=(-50 + side, -30 + side), hi=(50 - side, 30 - side))
    _check(trained, camera, cells, c, h, _samples(rng, c, h, 24), mode, dtype)


def test_tighter_modes_are_tighter(camera, trained):
    rng = np.random.default_rng(3)
    c, h, cells = _cells(rng, 32, 0.25)
    prep = prepare(trained, camera, 0.0, torch.float64)
    with torch.no_grad():
        eps = {m: certified_error_bound(prep, torch.as_tensor(cells), m).eps for m in ("ibp", "forward", "crown")}
    assert torch.all(eps["crown"] <= eps["forward"] + 1e-9)
    assert eps["crown"].median() < eps["ibp"].median()


# ----------------------------------------------------------------------------------------- exact case
def _coverage(u, idx, size):
    """Overlap of [u - size/2, u + size/2] with [idx, idx + 1] (the renderer's exact area), numpy."""
    return np.clip(np.minimum(idx + 1, u + size / 2) - np.maximum(idx, u - size / 2), 0.0, 1.0)


@settings(max_examples=examples(10), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000))
def test_single_linear_layer_on_the_renderer_is_exact(camera, seed):
    """One linear layer on the image (no blocks, no clamp), cells that are segments in x between the coverage's
    breakpoints: `e` is affine on each cell, so the bound must be its exact range plus the rounding term
    (`0.5 |w|` over the pixels whose coverage is fractional on the cell, scaled to world units)."""
    rng = np.random.default_rng(seed)
    n = 12
    w = torch.as_tensor(rng.normal(0, 1e-3, (2, 3, 60, 100)))
    b = torch.as_tensor(rng.normal(0, 0.1, 2))
    half, center = torch.tensor([50.0, 30.0], dtype=torch.float64), torch.tensor([0.0, 0.0], dtype=torch.float64)
    net = Deployed([], [], w, b, center, half, False, [(60, 100)])
    k = rng.integers(5, 95, n)  # u in (k + 0.5, k + 1.5): no breakpoint of any column's coverage (L = 3)
    a = rng.uniform(0.01, 0.5, n)
    width = rng.uniform(0.01, 0.98 - a)
    x0 = k + 0.5 + a - 50.0
    y = rng.uniform(-27, 27, n)
    cells = np.column_stack([x0, x0 + width, y, y])
    bound = certified_error_bound(prepare(net, camera), torch.as_tensor(cells), "crown")
    bg = camera.background.astype(float)
    col = camera.colors["leader"]
    rows, cols = np.arange(60), np.arange(100)
    for i in range(n):
        ends = []
        for x in (cells[i, 0], cells[i, 1]):
            u, v = camera.world_to_pixel([[x, y[i]]])[0]
            alpha = _coverage(v, rows, 3.0)[:, None] * _coverage(u, cols, 3.0)[None, :]
            img = bg + alpha[..., None] * (col - bg)
            z = (w.numpy() * img.transpose(2, 0, 1)[None]).reshape(2, -1).sum(-1) + b.numpy()
            ends.append(z * half.numpy() + center.numpy() - np.array([x, y[i]]))
            if x == cells[i, 0]:
                a_lo = alpha
            else:
                a_hi = alpha
        frac = (np.maximum(a_lo, a_hi) > 0) & ~(np.minimum(a_lo, a_hi) >= 1)
        moving = np.any(bg != col, axis=-1)
        r = 0.5 * (np.abs(w.numpy()) * (frac & moving)[None, None]).reshape(2, -1).sum(-1) * half.numpy()
        ends = np.array(ends)
        np.testing.assert_allclose(bound.lower[i].numpy(), ends.min(0) - r, atol=1e-9)
        np.testing.assert_allclose(bound.upper[i].numpy(), ends.max(0) + r, atol=1e-9)


# ----------------------------------------------------------------------------------------------- PGD
def _pgd_worst(model, camera, cells, kappa):
    """Largest / smallest `e_j` the joint PGD over the position and the admissible image reaches per cell
    (`pipeline.certify.attack`, the certify stage's attack)."""
    from pipeline.certify.attack import pgd_worst

    return pgd_worst(model, camera, cells, kappa, steps=25, seed=0)


@pytest.mark.parametrize("kappa", [0.0, 3.0])
def test_pgd_inside_the_cells_set_stays_below_the_bound(camera, trained, kappa):
    rng = np.random.default_rng(11)
    _, _, cells = _cells(rng, 12, 0.25, lo=(-45, -25), hi=(45, 25))
    with torch.no_grad():
        b = certified_error_bound(prepare(trained, camera, kappa, torch.float64), torch.as_tensor(cells), "crown")
    worst = _pgd_worst(trained, camera, cells, kappa)
    limit = torch.cat([b.upper, -b.lower], 1)
    assert torch.all(worst <= limit + SLACK), (worst - limit).max()
    # the attack is not idle: it gets within reach of the bound somewhere
    assert (worst / limit.abs().clamp(min=1e-6)).max() > 0.2


# -------------------------------------------------------------------------------- relaxations alone
def _random_forms(rng, shape, spread):
    """Random lower / upper forms `(N, 3, *shape)` with `lo(t) <= hi(t)` on the box."""
    lo = torch.as_tensor(rng.normal(0, spread, (shape[0], 3, *shape[1:])))
    gap = torch.as_tensor(rng.normal(0, spread, lo.shape))
    width = gap[:, 1:].abs().sum(1) + torch.as_tensor(rng.exponential(spread, (shape[0], *shape[1:])))
    hi = lo + gap
    hi[:, 0] = lo[:, 0] + width  # hi - lo = width + gap_t . t >= 0 everywhere on the box
    return lo, hi


def _at(form, t):
    return form[:, 0] + form[:, 1] * t[:, 0].view(-1, *[1] * (form.dim() - 2)) \
        + form[:, 2] * t[:, 1].view(-1, *[1] * (form.dim() - 2))


@settings(max_examples=examples(20), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), spread=st.sampled_from([0.1, 1.0, 10.0]))
def test_pool_and_relu_relaxations_hold_pointwise(seed, spread):
    from pipeline.certify.cone import _pool, _relu

    rng = np.random.default_rng(seed)
    lo, hi = _random_forms(rng, (64, 2, 4, 4), spread)
    plo, phi, *_ = _pool(lo, hi)
    rlo, rhi, *_ = _relu(lo, hi, ibp=False)
    for _ in range(20):
        t = torch.as_tensor(rng.uniform(-1, 1, (64, 2)))
        t[:4] = torch.tensor([[-1.0, -1.0], [1.0, -1.0], [-1.0, 1.0], [1.0, 1.0]])
        x = _at(lo, t) + torch.as_tensor(rng.uniform(0, 1, (64, 2, 4, 4))) * (_at(hi, t) - _at(lo, t))
        pooled = torch.nn.functional.max_pool2d(x, 2)
        assert torch.all(_at(plo, t) <= pooled + 1e-9) and torch.all(pooled <= _at(phi, t) + 1e-9)
        assert torch.all(_at(rlo, t) <= x.relu() + 1e-9) and torch.all(x.relu() <= _at(rhi, t) + 1e-9)


# ------------------------------------------------------------------------------------------ splitting
def test_adaptive_splitting_tightens_and_stays_sound(camera, trained):
    from pipeline.certify.split import certify_cells, eps_of, sampled_errors

    rng = np.random.default_rng(5)
    _, _, cells = _cells(rng, 8, 0.5, lo=(-40, -20), hi=(40, 20))
    prep = prepare(trained, camera, 0.0, torch.float64)
    lo0, hi0, d0, n0, h0 = certify_cells(prep, cells, progress=False)
    eps0 = eps_of(lo0, hi0)
    assert np.all(d0 == 0) and np.all(n0 == 1) and np.all(np.isnan(h0))  # no heading for a position map
    tol = float(np.median(eps0))  # cells above the median split once, the others stay whole
    lo1, hi1, d1, n1, _ = certify_cells(prep, cells, tolerance=tol, max_depth=1, progress=False)
    eps1 = eps_of(lo1, hi1)
    assert np.array_equal(d1, (eps0 > tol).astype(int)) and np.array_equal(n1, np.where(eps0 > tol, 4, 1))
    assert np.all(eps1[eps0 <= tol] == eps0[eps0 <= tol])
    assert np.median(eps1[eps0 > tol]) < np.median(eps0[eps0 > tol])
    predict = lambda imgs: FoldedPerceptionNet(trained)(torch.from_numpy(imgs)).detach().numpy()  # noqa: E731
    emp, violations, worst, _ = sampled_errors(predict, camera, cells, lo1, hi1, 32, 0, progress=False)
    assert violations == 0 and worst[0] <= 0, worst
    assert np.all(eps1 + SLACK >= emp)


# ------------------------------------------------------------------------------------------- keypoint head
def test_softmax_mean_max_is_the_maximum_over_the_box():
    """The threshold solution is the exact maximum: no sampled score vector gets above it, and a vertex reaches it."""
    from pipeline.certify.keypoint import softmax_mean_max

    rng = np.random.default_rng(0)
    n, m = 6, 7
    lo = torch.as_tensor(rng.normal(0, 2, (n, m)))
    hi = lo + torch.as_tensor(rng.uniform(0, 3, (n, m)))
    v = torch.as_tensor(rng.normal(0, 1, (n, m)))
    best = softmax_mean_max(lo, hi, v)
    corners = torch.as_tensor(np.array(np.meshgrid(*[[0, 1]] * m)).reshape(m, -1).T, dtype=torch.float64)
    s = lo[:, None] + corners[None] * (hi - lo)[:, None]  # every vertex of every box
    vals = (torch.softmax(s, -1) * v[:, None]).sum(-1)
    torch.testing.assert_close(best, vals.amax(-1))
    inside = lo[:, None] + torch.rand(n, 500, m, dtype=torch.float64) * (hi - lo)[:, None]
    assert bool(((torch.softmax(inside, -1) * v[:, None]).sum(-1) <= best[:, None] + 1e-12).all())


def _keypoint_map(seed: int, trained_on=None, camera=None):
    torch.manual_seed(seed)
    m = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", dropout=0.0, position_head="keypoint", clamp=False)
    if trained_on is None:
        with torch.no_grad():
            m.features[0].weight.mul_(4.0)
            m.head.score.weight.mul_(4.0)
        return m.eval()
    return copy.deepcopy(_fitted_keypoint_map(seed, trained_on, camera))


_FITS: dict = {}  # (seed, camera) -> {steps: the state of `_fit` after them}; emptied after the module


@pytest.fixture(scope="module", autouse=True)
def _forget_fits():
    yield
    _FITS.clear()


def _fitted_keypoint_map(seed: int, steps: int, camera):
    """The keypoint map of `seed` fitted for `steps` (deterministic: the same weights for the same arguments), its fit
    run once per process and resumed from the longest shorter one: hypothesis examples that draw the same `seed % 7`
    reuse it, and `trained_keypoint` (seed 1, 150 steps) continues the examples' 60 steps of seed 1."""
    fits = _FITS.setdefault((seed, id(camera)), {})
    if steps not in fits:
        shorter = [k for k in fits if k < steps]
        if shorter:
            state = copy.deepcopy(fits[max(shorter)])  # the map and its optimiser together: one copy
        else:
            torch.manual_seed(seed)
            state = _start(PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", dropout=0.0,
                                            position_head="keypoint", clamp=False), camera, seed)
        _train(state, steps)
        fits[steps] = state
    return fits[steps]["m"]


@settings(max_examples=examples(10), deadline=None, phases=PHASES)
@given(seed=st.integers(0, 10_000), side=st.sampled_from([0.05, 0.25, 1.0]), mode=st.sampled_from(["ibp", "forward", "crown"]),
       trained_steps=st.sampled_from([None, 60]))
def test_bound_contains_sampled_errors_keypoint_head(camera, seed, side, mode, trained_steps):
    """The keypoint head's bound holds on random and briefly trained maps (float64: the check of the bound itself)."""
    rng = np.random.default_rng(seed)
    c, h, cells = _cells(rng, 16, side, lo=(-50 + side, -30 + side), hi=(50 - side, 30 - side))
    _check(_keypoint_map(seed % 7, trained_steps, camera), camera, cells, c, h, _samples(rng, c, h, 24), mode,
           torch.float64)


@pytest.fixture(scope="module")
def trained_keypoint(camera, tmp_path_factory, worker_id):
    return computed_once(tmp_path_factory, worker_id, "certify_bounds_trained_keypoint",
                         lambda: _keypoint_map(1, 150, camera))


@pytest.mark.parametrize("kappa", [0.0, 3.0])
def test_pgd_cannot_pass_the_keypoint_bound_and_crown_is_tighter(camera, trained_keypoint, kappa):
    """A joint PGD over the position and the admissible image stays below the keypoint head's bound; the backward
    passes (`crown`) never loosen the forward bound and tighten it on most cells."""
    rng = np.random.default_rng(5)
    _, _, cells = _cells(rng, 12, 0.25, lo=(-45, -25), hi=(45, 25))
    prep = prepare(trained_keypoint, camera, kappa, torch.float64)
    with torch.no_grad():
        fwd, b = (certified_error_bound(prep, torch.as_tensor(cells), m) for m in ("forward", "crown"))
    assert torch.all(b.upper <= fwd.upper + 1e-9) and torch.all(b.lower >= fwd.lower - 1e-9)
    assert (b.eps < fwd.eps - 1e-6).float().mean() > 0.5
    worst = _pgd_worst(trained_keypoint, camera, cells, kappa)
    limit = torch.cat([b.upper, -b.lower], 1)
    assert torch.all(worst <= limit + SLACK), (worst - limit).max()
    assert (worst / limit.abs().clamp(min=1e-6)).max() > 0.1  # the attack is not idle
