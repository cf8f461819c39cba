"""Issue 47, the certified error map (`pipeline.certify`, docs/certify.md): every soundness claim has a check that
can fail. Each test runs the certify stage's own checks of `|l(h(p)) - p| <= ε̄(P)` and asserts they hold, then
loosens one rule of the bound with `monkeypatch` (a mutation) and asserts that the same checks now find a
counterexample.

The checks are the stage's (`pipeline.certify.stage`): the bound per cell (`split.certify_cells`, default `mode`
crown, float32), `split.sampled_errors` (`samples` = 16 positions per cell through the real uint8 renderer and the
deployed network, seed 0: the count of sampled errors outside their cell's bound) and `attack.pgd_check` (the PGD
attack over the position and the images the relaxation admits, `pgd_steps` = 25; on 32 cells instead of 256, for
time; the attack reads no rule of the bound, so what it reached is held against the sound and the mutated bound
alike: `attack_once`), on cells of the default side 0.25.

| rule | map | mutation | caught by |
|---|---|---|---|
| 2x2 max-pool relaxation (`cone._pool`): a member's upper bound only where it dominates | random flat map, amplified | every pool's upper bound its largest-lower-bound member's | sampling, PGD |
| the keypoint head's exact softmax maximum (`keypoint.softmax_mean_max`) | random keypoint map, amplified | the softmax at the box's top corner instead of the maximum over the box | sampling, PGD |
| the renderer's rounding term (`renderer`: `±0.5` level where the coverage is fractional) | a linear map exact on the continuous render | the rounding term dropped | the renderer's pixel check; sampling, with the stage's splitting |

The random maps are `test_certify_bounds`'s (`_amplified`, `_keypoint_map`): their bounds are within a few percent
of the sampled errors, so a rule that under-states them shows; on briefly trained maps the bound is 3-60 times the
sampled error and none of these mutations was caught there.
"""

from __future__ import annotations

import numpy as np
import pytest
import test_certify_bounds as tcb  # its maps and the renderer's check (a module alias: pytest collects nothing twice)
import torch

from pipeline.certify import cone, keypoint, prepare, renderer
from pipeline.certify.attack import pgd_check
from pipeline.certify.deployed import Deployed
from pipeline.certify.settings import CertifySettings
from pipeline.certify.split import certify_cells, sampled_errors
from pipeline.perception.network import FoldedPerceptionNet
from pipeline.render import Camera

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py

DEFAULTS = CertifySettings()  # cell 0.25, mode crown, float32, 16 samples, seed 0, 25 PGD steps
PGD_CELLS = 32


@pytest.fixture(scope="module")
def camera():
    return Camera(tcb.SCENE)


@pytest.fixture(scope="module")
def cells():
    """128 cells of the default side at random places of the arena."""
    rng = np.random.default_rng(1)
    c = np.column_stack([rng.uniform(-45, 45, 128), rng.uniform(-25, 25, 128)])
    h = DEFAULTS.cell / 2
    return np.column_stack([c[:, 0] - h, c[:, 0] + h, c[:, 1] - h, c[:, 1] + h])


def _soundness(net, predict, camera, cells, model=None, **split) -> dict:
    """The certify stage's checks at κ = 0 with its defaults (module docstring): sampled errors outside their
    cell's bound (with the worst as a counterexample) and, given the `PerceptionMap` `model`, the PGD attack's
    directions pushed past it. `split`: the stage's `tolerance`, `max_depth`."""
    dtype = torch.float64 if DEFAULTS.dtype == "float64" else torch.float32
    with torch.no_grad():
        lower, upper, *_ = certify_cells(prepare(net, camera, 0.0, dtype), cells, DEFAULTS.mode, progress=False,
                                         **split)
    _, violations, worst, _ = sampled_errors(predict, camera, cells, lower, upper, DEFAULTS.samples, DEFAULTS.seed,
                                             progress=False)
    out = {"samples": len(cells) * DEFAULTS.samples, "violations": violations, "worst_excess": worst[0],
           "counterexample": worst[1]}
    if model is not None:
        pgd = pgd_check(model, camera, cells, lower, upper, 0.0, PGD_CELLS, DEFAULTS.pgd_steps, DEFAULTS.seed)
        out["pgd"] = {k: pgd[k] for k in ("violations", "worst_excess", "counterexample")}
    return out


@pytest.fixture
def attack_once(monkeypatch):
    """The PGD attack and the search over rendered frames (`attack.pgd_worst`, `attack.render_worst`) read the map,
    the camera and the cells, never the rules of the bound that the PGD-checked mutations loosen (`cone._pool`,
    `keypoint.softmax_mean_max`): each is run once per input and what it reached is held against the sound bound
    and then against the mutated one, instead of the same seeded ascent run again."""
    from pipeline.certify import attack

    def once(fn):
        seen = {}

        def wrapped(model, camera, cells, *args, bar=None, **kwargs):
            key = (id(model), id(camera), np.asarray(cells).tobytes(), args, tuple(sorted(kwargs.items())))
            if key not in seen:
                seen[key] = fn(model, camera, cells, *args, bar=bar, **kwargs) if bar is not None else \
                    fn(model, camera, cells, *args, **kwargs)
            return seen[key]
        return wrapped

    monkeypatch.setattr(attack, "pgd_worst", once(attack.pgd_worst))
    monkeypatch.setattr(attack, "render_worst", once(attack.render_worst))


def _deployed_predict(model):
    net = FoldedPerceptionNet(model)
    return lambda imgs: net(torch.from_numpy(imgs)).detach().numpy()


# ------------------------------------------------------------------------------------- max-pool relaxation
def test_pool_relaxation_is_needed(camera, cells, monkeypatch, attack_once):
    """Held on a random flat map with amplified weights (many unstable ReLUs, pools whose maximum switches member
    over a cell); then a pool's upper bound taken from its largest-lower-bound member even where another member
    can exceed it (the dominance test skipped, forward and backward): the sampled errors and the PGD attack pass
    the bound."""
    model = tcb._amplified(0)
    predict = _deployed_predict(model)
    sound = _soundness(model, predict, camera, cells, model)
    assert sound["violations"] == 0 and sound["pgd"]["violations"] == 0, sound

    pool = cone._pool

    def always_dominant(lo, hi):
        plo, _, member, dominant, umax = pool(lo, hi)
        n, s, _, h, w = lo.shape
        members = hi.reshape(*hi.shape[:-2], h // 2, 2, w // 2, 2).movedim(-3, -2).flatten(-2)
        idx = member[:, None, ..., None].expand(n, s, *member.shape[1:], 1)
        return plo, members.gather(-1, idx)[..., 0], member, torch.ones_like(dominant), umax

    monkeypatch.setattr(cone, "_pool", always_dominant)
    loose = _soundness(model, predict, camera, cells, model)
    assert loose["violations"] > 0 and loose["worst_excess"] > 0.1, loose
    assert loose["pgd"]["violations"] > 0, loose
    print(f"pool dominance skipped: {loose['violations']} of {loose['samples']} sampled errors outside, worst by "
          f"{loose['worst_excess']:.3g}: {loose['counterexample']}; PGD {loose['pgd']}")


# ---------------------------------------------------------------------------------------- keypoint head
def test_keypoint_softmax_maximum_is_needed(camera, cells, monkeypatch, attack_once):
    """Held on a random keypoint map with amplified scores; then the softmax-weighted mean bounded at the score
    box's top corner (every cell at its largest score) instead of its exact maximum over the box: the sampled
    errors and the PGD attack pass the bound."""
    model = tcb._keypoint_map(0)
    predict = _deployed_predict(model)
    sound = _soundness(model, predict, camera, cells, model)
    assert sound["violations"] == 0 and sound["pgd"]["violations"] == 0, sound

    monkeypatch.setattr(keypoint, "softmax_mean_max",
                        lambda s_lo, s_hi, v: (torch.softmax(s_hi.double(), -1) * v.double()).sum(-1))
    loose = _soundness(model, predict, camera, cells, model)
    assert loose["violations"] > 0 and loose["worst_excess"] > 0.1, loose
    assert loose["pgd"]["violations"] > 0, loose
    print(f"softmax at the top corner: {loose['violations']} of {loose['samples']} sampled errors outside, worst by "
          f"{loose['worst_excess']:.3g}: {loose['counterexample']}; PGD {loose['pgd']}")


# ------------------------------------------------------------------------------------------ rounding
def centroid_map(camera, dtype=torch.float32):
    """A linear map (no blocks) that is exact on the continuous render: the robot's coverage of each pixel read off
    one channel where the robot differs from the static image, `α = (x - s) / (c_robot - s)`, and the position the
    coverage's centroid (its mass is `L²` wherever the robot is inside the image). On the uint8 image its only error
    is the rounding. Returns the deployed map and its `predict` on uint8 images."""
    s = np.asarray(camera.background, float).transpose(2, 0, 1)  # (3, H, W)
    d = np.asarray(camera.colors["leader"], float)[:, None, None] - s
    pick = np.arange(3)[:, None, None] == np.abs(d).argmax(0)[None]
    inv = np.where(pick, 1.0 / np.where(pick, d, 1.0), 0.0)
    height, width = s.shape[1:]
    k, size = float(camera.scale), float(camera.robot_size)
    (ax0, _), (_, ay1) = camera.arena
    wx = inv * (np.arange(width) + 0.5)[None, None, :] / (size * size * k)   # u = sum α (col + 1/2) / L²
    wy = -inv * (np.arange(height) + 0.5)[None, :, None] / (size * size * k)  # y = ay1 - v / k
    w = np.stack([wx, wy])
    b = np.array([ax0, ay1]) - (w * s[None]).reshape(2, -1).sum(-1)
    w_t, b_t = torch.as_tensor(w, dtype=dtype), torch.as_tensor(b, dtype=dtype)
    one = torch.ones(2, dtype=dtype)
    net = Deployed([], [], w_t, b_t, 0 * one, one, False, [(height, width)])
    return net, lambda imgs: np.einsum("kchw,nhwc->nk", w, imgs.astype(float)) + b


def test_rounding_term_is_needed(camera, cells, monkeypatch):
    """Held: the renderer's pixel forms contain the uint8 render (`test_certify_bounds`'s check, cells of the
    default side), and the exact-on-the-continuous-render map's bound holds every sampled error, with the stage's
    splitting (`tolerance` 0.05, `max_depth` 3: leaves of 1/32; unsplit, the relaxation's own slack at 0.25 hides
    the rounding). Then the rounding term dropped (the coverage taken as never fractional where the renderer adds
    `±0.5` level): rendered pixels leave their forms, and sampled errors leave their bound. (The PGD attack searches
    the images the relaxation admits, so it cannot see a bound of the renderer that is too small.)"""
    renderer_check = tcb.test_pixel_forms_contain_the_uint8_render.hypothesis.inner_test
    net, predict = centroid_map(camera)
    split = {"tolerance": 0.05, "max_depth": 3}
    renderer_check(camera, 0, DEFAULTS.cell)
    sound = _soundness(net, predict, camera, cells, **split)
    assert sound["violations"] == 0, sound

    product = renderer._product

    def no_rounding(fx, fy):
        lo, hi, amin, amax, frac = product(fx, fy)
        return lo, hi, amin, amax, torch.zeros_like(frac)

    monkeypatch.setattr(renderer, "_product", no_rounding)
    with pytest.raises(AssertionError, match="a rendered pixel"):
        renderer_check(camera, 0, DEFAULTS.cell)
    loose = _soundness(net, predict, camera, cells, **split)
    assert loose["violations"] > 0 and loose["worst_excess"] > 0.01, loose
    print(f"rounding dropped: {loose['violations']} of {loose['samples']} sampled errors outside, worst by "
          f"{loose['worst_excess']:.3g}: {loose['counterexample']}")
