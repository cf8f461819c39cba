"""Maps that know when they can't see (issue 11 §2): the Gaussian head, its calibration and the failure gating."""

from __future__ import annotations

import lightning as L
import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.control import HybridController, Obstacle, Scene
from pipeline.errors import ConfigError
from pipeline.perception.maps import PerceptionMapPredictor
from pipeline.perception.measure import CameraMeasure
from pipeline.perception.network import gaussian_nll
from pipeline.sim import CameraSettings, SimSettings, simulate
from pipeline.train.module import PerceptionMap
from pipeline.train.uncertainty import (
    calibrate,
    clean_gate,
    coverage95,
    false_alarm_upper_bound,
    fit_variance_head,
    flag_metrics,
)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(1, 64), scale=st.floats(1e-3, 1e2))
def test_nll_is_minimised_at_the_log_mean_squared_error(seed, n, scale):
    r2 = torch.tensor(np.random.default_rng(seed).exponential(scale, n), dtype=torch.float64) + 1e-9
    best = torch.log(r2.mean())
    s = best.clone().requires_grad_(True)
    loss = gaussian_nll(s.expand(n), r2)
    loss.backward()
    assert abs(float(s.grad)) < 1e-9
    for d in (-0.3, 0.3):
        assert gaussian_nll((best + d).expand(n), r2) > loss


def _synthetic(n: int, seed: int, sigmas=(0.3, 2.0)):
    """Two kinds of 16x16 images, dark and bright, both labelled (3, -2) plus Gaussian noise of a known
    standard deviation per kind (world units): the best answer is the label's mean and the kind's sigma."""
    rng = np.random.default_rng(seed)
    bright = rng.random(n) < 0.5
    images = np.where(bright[:, None, None, None], 200, 30).astype(np.uint8) * np.ones((n, 16, 16, 3), np.uint8)
    images = (images.astype(np.int16) + rng.integers(-10, 10, images.shape)).clip(0, 255).astype(np.uint8)
    sigma = np.where(bright, sigmas[1], sigmas[0])
    pos = np.array([3.0, -2.0]) + rng.normal(size=(n, 2)) * sigma[:, None]
    return images, pos, bright


def test_gaussian_head_learns_the_known_noise_and_calibrates():
    torch.manual_seed(0)
    L.seed_everything(0, verbose=False)
    images, pos, _ = _synthetic(4096, 0)
    model = PerceptionMap.of(image_shape=[16, 16, 3], arena=[[-10, 10], [-10, 10]], filters=[4], batch_norm=False,
                          dropout=0.0, lr=3e-3, uncertainty="gaussian", coord_channels=False)
    dl = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.from_numpy(images),
                                                                    torch.from_numpy(pos).float()),
                                     batch_size=256, shuffle=True)
    L.Trainer(max_epochs=25, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False).fit(model, dl)
    head_before = [p.clone() for p in model.var_head.parameters()]
    position_before = [p.clone() for p in model.head.parameters()]
    fit = fit_variance_head(model, images, pos, seed=0, log=lambda _: None)
    assert fit["images"] == len(images) and np.isfinite(fit["train_nll"])
    # the fit moves the variance head only
    assert any(not torch.equal(a, b) for a, b in zip(head_before, model.var_head.parameters()))
    assert all(torch.equal(a, b) for a, b in zip(position_before, model.head.parameters()))
    model.eval()
    pm = PerceptionMapPredictor(model)
    val_i, val_p, _ = _synthetic(2000, 1)
    cal = calibrate(model, pm, val_i, val_p)
    test_i, test_p, bright = _synthetic(4000, 2)
    pred, sigma = pm.predict_with_sigma(test_i)
    # the position is the labels' mean, the sigma each kind's noise (within 20%)
    np.testing.assert_allclose(pred.mean(0), [3.0, -2.0], atol=0.25)  # a short fit: within the smaller sigma
    assert np.median(sigma[~bright]) == pytest.approx(0.3, rel=0.2)
    assert np.median(sigma[bright]) == pytest.approx(2.0, rel=0.2)
    assert cal["val_coverage95"] == pytest.approx(0.95, abs=0.01)
    assert coverage95(pred, sigma, test_p) == pytest.approx(0.95, abs=0.02)  # held out: calibration generalises
    # the folded inference network and the training module agree on the sigma, calibration included
    with torch.no_grad():
        ref = model(torch.from_numpy(test_i[:64])).double().numpy()
    np.testing.assert_allclose(sigma[:64], ref[:, 2:], rtol=1e-4)
    # flags: a 1-unit gate separates the two kinds exactly
    f = flag_metrics(pred, sigma, test_p, 1.0, error_px=3.0, gate_px=1.0)
    assert f["flagged"] == pytest.approx(bright.mean(), abs=0.01)
    # the operating point: a gate fitted on the "clean" (dim) validation images at 10% false alarms catches the
    # bright frames' large errors and flags about 10% of the dim test images
    _, val_sigma = pm.predict_with_sigma(val_i)
    _, _, val_bright = _synthetic(2000, 1)
    g = clean_gate(val_sigma[~val_bright], 1.0, 0.1)
    f = flag_metrics(pred, sigma, test_p, 1.0, error_px=3.0, gate_px=1.0, clean_gate_px=g)
    assert f["at_clean_gate"]["detected"] > 0.95
    dim = flag_metrics(pred[~bright], sigma[~bright], test_p[~bright], 1.0, error_px=3.0, gate_px=1.0,
                       clean_gate_px=g)["at_clean_gate"]
    assert dim["flagged"] == pytest.approx(0.1, abs=0.03)


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(20, 500), fa=st.floats(0.01, 0.5), px=st.floats(0.1, 10.0))
def test_clean_gate_flags_the_requested_share_of_clean_images(seed, n, fa, px):
    rng = np.random.default_rng(seed)
    sigma = rng.lognormal(0.0, 1.0, (n, 2))
    g = clean_gate(sigma, px, fa)
    share = float((np.hypot(*(sigma * px).T) > g).mean())
    assert fa - 1.0 / n - 1e-12 <= share <= fa + 1e-12
    # with a `good` mask the share is that of the good frames (the false alarms); the others do not count
    good = rng.random(n) < 0.7
    if good.any():
        g_good = clean_gate(sigma, px, fa, good)
        flagged_good = np.hypot(*(sigma[good] * px).T) > g_good
        assert fa - 1.0 / good.sum() - 1e-12 <= flagged_good.mean() <= fa + 1e-12
    # at_clean_gate is the flag rates at that gate: the same numbers as gate_px = g
    true = rng.normal(0.0, 1.0, (n, 2))
    pred = true + rng.normal(0.0, 1.0, (n, 2)) * sigma
    f = flag_metrics(pred, sigma, true, px, error_px=3.0, gate_px=g, clean_gate_px=g)
    assert {k: f[k] for k in ("flagged", "detected", "false_alarm")} == \
        {k: f["at_clean_gate"][k] for k in ("flagged", "detected", "false_alarm")}


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**31), n=st.integers(20, 3000), fa=st.floats(0.01, 0.5), conf=st.floats(0.6, 0.99))
def test_the_confident_gate_flags_the_largest_share_whose_upper_bound_is_within_target(seed, n, fa, conf):
    """With `confidence`, the gate flags k of n frames: the largest k whose one-sided upper bound is at most the
    target, so never more than the plain quantile flags; at confidence 0.5 the bound is the share itself."""
    rng = np.random.default_rng(seed)
    sigma = rng.lognormal(0.0, 1.0, (n, 2))
    err = np.hypot(*sigma.T)
    g = clean_gate(sigma, 1.0, fa, confidence=conf)
    k = int((err > g).sum())
    assert false_alarm_upper_bound(k, n, conf) <= fa + 1e-12
    assert k == n - 1 or false_alarm_upper_bound(k + 1, n, conf) > fa or k + 1 > fa * n
    assert k <= int((err > clean_gate(sigma, 1.0, fa)).sum())
    assert false_alarm_upper_bound(k, n, 0.5) == pytest.approx(k / n)
    bounds = false_alarm_upper_bound(np.arange(n + 1), n, conf)
    assert np.all(np.diff(bounds) > 0) and np.all(bounds >= np.arange(n + 1) / n - 1e-12)


def test_the_confident_gate_keeps_new_frames_within_the_target_at_its_confidence():
    """The gate is fitted on a sample; on new frames its false-alarm rate (known here: predicted errors uniform on
    [0, 1], so the rate at gate g is 1 - g) exceeds the target in about half of the draws for the plain quantile,
    and in at most 1 - confidence of them (within noise) with the bound."""
    rng = np.random.default_rng(0)
    fa, n, reps = 0.1, 2000, 400
    over = {0.5: 0, 0.95: 0}
    for _ in range(reps):
        u = rng.uniform(0.0, 1.0, n)
        sigma = np.stack([u, np.zeros(n)], axis=1)
        for conf in over:
            over[conf] += (1.0 - clean_gate(sigma, 1.0, fa, confidence=conf)) > fa
    assert over[0.5] / reps > 0.3
    assert over[0.95] / reps < 0.05 + 3 * np.sqrt(0.05 * 0.95 / reps)
    with pytest.raises(ValueError, match="confidence"):
        clean_gate(sigma, 1.0, fa, confidence=1.0)


class _Identity:
    """A 'camera' whose image of p is p itself (the map below reads positions)."""

    def render(self, leader, follower=None, occlusion=None, rng=None, heading=None):
        return np.asarray(leader, float).copy()


class _DoubtfulMap:
    """Right of x = 0 it answers 20 units off and says so (predicted error 50); left, exact (error 0.1)."""

    name, id, has_uncertainty = "doubtful", "0", True

    def predicted_error(self, images):
        right = images[:, 0] > 0
        return images + np.where(right[:, None], [0.0, 20.0], 0.0), np.where(right, 50.0, 0.1)

    def predict(self, images):
        return self.predicted_error(images)[0]


def test_gated_frames_are_failures_the_last_estimate_is_held():
    scene = Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])
    x0 = np.array([[-30.0, 15.0], [-20.0, -18.0], [30.0, 10.0]])
    runs = {}
    for gate in (None, 5.0):
        meas = CameraMeasure(_Identity(), _DoubtfulMap(), gate=gate)
        runs[gate] = (simulate(scene, HybridController(scene), x0,
                               sim=SimSettings(dt=0.01, horizon=6.0, record_every=5, stop_on_success=False),
                               camera=CameraSettings(period=0.05), measure=meas), meas)
    ungated, _ = runs[None]
    gated, meas = runs[5.0]
    off = np.abs(ungated.m[..., 1] - ungated.p[..., 1]) > 10  # the wrong answers reach the controller ungated
    assert off[1:, :2].any()
    assert meas.gated > 0
    # gated: agents 0 and 1 never use an estimate from the right half: their estimate stays where they crossed
    m = gated.m[1:, :2]
    assert (m[..., 0] <= 0.5).all()
    # agent 2 starts on the right: frame 0 is never gated (a vehicle starts with an estimate) ...
    np.testing.assert_allclose(gated.m[0, 2], x0[2] + [0.0, 20.0])
    # ... and afterwards it is held: the controller never sees a newer one
    np.testing.assert_allclose(gated.m[1:, 2], np.broadcast_to(x0[2] + [0.0, 20.0], gated.m[1:, 2].shape))


def test_gate_needs_an_uncertainty_head():
    class NoHead:
        name, id, has_uncertainty = "plain", "1", False

    with pytest.raises(ConfigError, match="camera.gate"):
        CameraMeasure(_Identity(), NoHead(), gate=3.0)


def test_the_head_never_changes_the_position_estimate():
    """The variance head reads detached features: trained side by side from the same seed, the maps with and
    without it give the same positions."""
    images, pos, _ = _synthetic(512, 3)
    preds = []
    for unc in ("none", "gaussian"):
        L.seed_everything(0, verbose=False)
        model = PerceptionMap.of(image_shape=[16, 16, 3], arena=[[-10, 10], [-10, 10]], filters=[4], batch_norm=True,
                              dropout=0.2, lr=3e-3, uncertainty=unc, coord_channels=True)
        dl = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.from_numpy(images),
                                                                        torch.from_numpy(pos).float()),
                                         batch_size=64, shuffle=True, generator=torch.Generator().manual_seed(0))
        L.Trainer(max_epochs=2, accelerator="cpu", logger=False, enable_checkpointing=False,
                  enable_progress_bar=False, enable_model_summary=False).fit(model, dl)
        preds.append(PerceptionMapPredictor(model.eval()).predict(images))
    np.testing.assert_allclose(preds[0], preds[1], atol=1e-5)

