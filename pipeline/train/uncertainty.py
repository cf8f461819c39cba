"""Maps that know when they can't see (issue 11 §2): calibration of the predicted sigma, and its use as a flag.

A map trained with `model.uncertainty: gaussian` predicts, per image, a standard deviation for each coordinate.
- **Fit** (`fit_variance_head`, after the position network is trained): the variance head learns, by Gaussian
  negative log-likelihood, the squared error of the *trained* network on the training split, in eval mode
  (BatchNorm's running statistics, no dropout): the error the closed loop will see. Trained side by side with
  the position instead, it learned the error of a moving, dropout-noised network, which hides what makes a
  frame hard: on heavy clouds it caught 66% of the frames with > 3 px error at the clean-image gate; fitted
  afterwards (and reading a thumbnail of the image, `PerceptionMap.variance_inputs`) 92.5% (docs/train.md).
- **Calibration** (`calibrate`, on the validation split after training): the share of validation images whose
  error falls inside the predicted 95% ellipse (`sum((e_i / s_i)^2) <= chi2_2(0.95)`) is measured with the raw
  sigmas, then one scale factor `c` is fitted so that exactly 95% do (`c^2 = q95(mahalanobis^2) / chi2_2(0.95)`)
  and stored in the model (`sigma_scale`). The test split then measures the calibrated coverage honestly.
- **Flagging** (`flag_metrics`): a frame is flagged when the predicted error `sqrt(sx^2 + sy^2)` exceeds
  `gate_px`; reported are the share flagged, the share of frames with a real error above `error_px` that are
  flagged (detection) and the share of the others that are flagged (false alarms). In the closed loop a flagged
  frame is a camera failure (`camera.gate`): the last estimate is held.
- **Operating point** (`clean_gate`): the gate at which a given share of the *clean* images' good frames (whose
  real error is at most `error_px`) is flagged: the false-alarm rate on clean images. A clean frame with a
  large error is a frame worth flagging, not a false alarm. The gate is a tail quantile of a sample, so its
  rate on new frames misses the share by the sampling error; with `confidence` it flags the largest share
  whose one-sided upper bound (Wilson) is within the target, so that the rate on new frames is within it with
  that confidence. The train stage fits it on the validation positions and fresh positions from the recipe's
  own distribution, all rendered without clouds (`pipeline.train.evaluate.fit_clean_gate`); the test levels then
  report their detection at that gate (`at_clean_gate`), i.e. the ROC point "detect the bad frames at <= x%
  false alarms on clean images" measured without looking at the test split.
"""

from __future__ import annotations

import time
from statistics import NormalDist

import numpy as np
import torch

from pipeline.perception.network import CHI2_2_95, LOGVAR_RANGE, gaussian_nll

_FEATURE_BATCH = 1024  # images per forward pass while collecting the features


@torch.no_grad()
def _features_and_errors(model, images, positions, device) -> tuple[torch.Tensor, torch.Tensor]:
    """The variance head's eval-mode inputs `(N, F)` (features and thumbnail) and the squared normalised position
    errors `(N, 2)`, on the CPU."""
    n = len(images)
    feats = sq = None
    for i in range(0, n, _FEATURE_BATCH):
        x = torch.from_numpy(np.array(images[i:i + _FEATURE_BATCH])).to(device)  # a copy: memmaps are read-only
        xp = model.prepare(x)
        g, f = model.encode(xp)
        target = (torch.as_tensor(np.asarray(positions[i:i + _FEATURE_BATCH]), dtype=torch.float32, device=device)
                  - model.center) / model.half_range
        inputs = model.variance_inputs(xp, f)
        if feats is None:  # preallocated: the inputs of a large split are held once, not twice
            feats, sq = torch.empty(n, inputs.shape[1]), torch.empty(n, 2)
        feats[i:i + len(f)] = inputs.cpu()
        sq[i:i + len(f)] = ((model.head_outputs(g, f)[:, :2] - target) ** 2).cpu()  # a pose map's: position first
    return feats, sq


def fit_variance_head(model, images, positions, *, seed: int, device="cpu", log=print) -> dict:
    """Fit `model.var_head` (Gaussian NLL of the trained network's own errors) on `images`/`positions` (the
    training split), with the model's `uncertainty_epochs`, `uncertainty_lr` (one-cycle) and
    `uncertainty_batch_size`; the position network is not touched. Deterministic for a seed. The features are
    held in memory: `N x F x 4` bytes (48k images of the default map: 1 GB). Returns a summary for metrics.json."""
    hp = model.hparams
    t0 = time.perf_counter()
    model.eval().to(device)
    feats, sq = _features_and_errors(model, images, positions, device)
    n, bs, epochs = len(feats), int(hp.uncertainty_batch_size), int(hp.uncertainty_epochs)
    steps = max(1, n // bs)
    head = model.var_head.to(device).requires_grad_(True)
    opt = torch.optim.Adam(head.parameters(), lr=float(hp.uncertainty_lr))
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=float(hp.uncertainty_lr),
                                                total_steps=max(2, epochs * steps), pct_start=0.15)
    gen = torch.Generator().manual_seed(int(seed))
    log(f"[train] fitting the uncertainty head on {n} training images ({epochs} epochs)")
    nll = float("nan")
    for _ in range(epochs):
        perm, total = torch.randperm(n, generator=gen), 0.0
        for k in range(steps):
            idx = perm[k * bs:(k + 1) * bs] if n >= bs else perm
            logvar = head(feats[idx].to(device)).clamp(*LOGVAR_RANGE)
            loss = gaussian_nll(logvar, sq[idx].to(device))
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            sched.step()
            total += float(loss.detach())
        nll = total / steps
    head.requires_grad_(False)
    return {"images": n, "epochs": epochs, "train_nll": nll, "seconds": round(time.perf_counter() - t0, 1)}


def mahalanobis2(pred: np.ndarray, sigma: np.ndarray, true: np.ndarray) -> np.ndarray:
    """Squared Mahalanobis distance of the errors under independent per-coordinate Gaussians."""
    z = (np.asarray(pred, np.float64) - np.asarray(true, np.float64)) / np.maximum(np.asarray(sigma, np.float64), 1e-12)
    return (z * z).sum(axis=1)


def coverage95(pred: np.ndarray, sigma: np.ndarray, true: np.ndarray) -> float:
    """Share of errors inside the predicted 95% ellipse (0.95 when calibrated)."""
    return float((mahalanobis2(pred, sigma, true) <= CHI2_2_95).mean())


def calibrate(model, predictor, images, true: np.ndarray) -> dict:
    """Fit the model's `sigma_scale` on a held-out split (the validation split); returns the raw and calibrated
    coverage there and the scale. `predictor` must run `model` (its network is rebuilt after the change)."""
    model.sigma_scale.fill_(1.0)
    predictor.refresh()
    pred, sigma = predictor.predict_with_sigma(images)
    pred = pred[:, :2]  # a pose map: the sigma is the position's
    raw = coverage95(pred, sigma, true)
    scale = float(np.sqrt(np.quantile(mahalanobis2(pred, sigma, true), 0.95) / CHI2_2_95))
    scale = min(max(scale, 1e-3), 1e3)
    with torch.no_grad():
        model.sigma_scale.fill_(scale)
    predictor.refresh()
    return {"val_coverage95_raw": raw, "sigma_scale": scale,
            "val_coverage95": coverage95(pred, sigma * scale, true), "n": int(len(true))}


def false_alarm_upper_bound(flagged: int | np.ndarray, n: int, confidence: float) -> np.ndarray:
    """One-sided upper confidence bound on a false-alarm rate from `flagged` of `n` frames: the Wilson score
    bound at `confidence` (0.5: the share itself). Vectorised over `flagged`."""
    k = np.asarray(flagged, np.float64)
    z = NormalDist().inv_cdf(confidence) if confidence > 0.5 else 0.0
    p, z2 = k / n, z * z
    return (p + z2 / (2 * n) + z * np.sqrt(p * (1 - p) / n + z2 / (4 * n * n))) / (1 + z2 / n)


def clean_gate(sigma_clean: np.ndarray, px_per_unit: float, false_alarm: float, good: np.ndarray | None = None,
               confidence: float = 0.5) -> float:
    """The gate (px of predicted error) that flags a share `false_alarm` of the clean images whose predicted
    sigmas are `sigma_clean` (at most that share; exactly, up to one image, without ties). With `good` (a mask:
    the frames whose real error is at most `error_px`), the share is taken among those frames only: the
    false alarms.

    The gate is estimated from a sample, so the rate it gives on new frames misses `false_alarm` by the sampling
    error of a tail quantile. With `confidence` > 0.5 the gate flags the largest share whose one-sided upper
    confidence bound (:func:`false_alarm_upper_bound`) is at most `false_alarm`: the false-alarm rate on new
    frames from the same distribution is then at most `false_alarm` with that confidence (0.5: the share itself,
    the plain quantile)."""
    pred_err = np.hypot(*(np.asarray(sigma_clean, np.float64) * px_per_unit).T)
    if good is not None:
        pred_err = pred_err[np.asarray(good, bool)]
    n = len(pred_err)
    if not n:
        raise ValueError("clean_gate needs at least one frame")
    if not 0.5 <= confidence < 1:
        raise ValueError(f"clean_gate: confidence must be in [0.5, 1), got {confidence!r}")
    k = int(np.floor(false_alarm * n + 1e-9))  # images it may flag: those strictly above the gate
    if confidence > 0.5:  # the largest k whose upper bound stays within false_alarm (the bound grows with k)
        ks = np.arange(k + 1)
        k = int(ks[false_alarm_upper_bound(ks, n, confidence) <= false_alarm + 1e-12].max(initial=0))
    return float(np.sort(pred_err)[n - k - 1])


def _rates(flagged: np.ndarray, bad: np.ndarray) -> dict:
    return {"flagged": float(flagged.mean()) if len(flagged) else None,
            "detected": float(flagged[bad].mean()) if bad.any() else None,  # flagged among frames with error > error_px
            "false_alarm": float(flagged[~bad].mean()) if (~bad).any() else None}  # flagged among the others


def flag_metrics(pred: np.ndarray, sigma: np.ndarray, true: np.ndarray, px_per_unit: float, *,
                 error_px: float, gate_px: float, clean_gate_px: float | None = None) -> dict:
    """Coverage of the 95% ellipse, and how well `predicted error > gate_px` flags `real error > error_px`
    (and, given `clean_gate_px` from :func:`clean_gate`, the same rates at that gate under `at_clean_gate`)."""
    err = np.hypot(*((np.asarray(pred) - np.asarray(true)) * px_per_unit).T)
    pred_err = np.hypot(*(np.asarray(sigma) * px_per_unit).T)
    flagged = pred_err > gate_px
    bad = err > error_px
    extra = {} if clean_gate_px is None else {
        "at_clean_gate": {"gate_px": float(clean_gate_px), **_rates(pred_err > clean_gate_px, bad)}}
    return {
        "coverage95": coverage95(pred, sigma, true),
        "predicted_error_median_px": float(np.median(pred_err)) if len(err) else None,
        **_rates(flagged, bad),
        "bad_share": float(bad.mean()) if len(err) else None,
        "mae_unflagged_px": float(np.abs((np.asarray(pred) - np.asarray(true))[~flagged] * px_per_unit).mean())
        if (~flagged).any() else None,
        "error_px": float(error_px), "gate_px": float(gate_px), **extra,
    }
