"""Maps that know when they can't see (issue 11 §2): calibration of the predicted sigma, and its use as a flag.

A map trained with `model.uncertainty: gaussian` predicts, per image, a standard deviation for each coordinate.
- **Calibration** (`calibrate`, on the validation split after training): the share of validation images whose
  error falls inside the predicted 95% ellipse (`sum((e_i / s_i)^2) <= chi2_2(0.95)`) is measured with the raw
  sigmas, then one scale factor `c` is fitted so that exactly 95% do (`c^2 = q95(mahalanobis^2) / chi2_2(0.95)`)
  and stored in the model (`sigma_scale`). The test split then measures the calibrated coverage honestly.
- **Flagging** (`flag_metrics`): a frame is flagged when the predicted error `sqrt(sx^2 + sy^2)` exceeds
  `gate_px`; reported are the share flagged, the share of frames with a real error above `error_px` that are
  flagged (detection) and the share of the others that are flagged (false alarms). In the closed loop a flagged
  frame is a camera failure (`camera.gate`): the last estimate is held.
- **Operating point** (`clean_gate`): the gate at which a given share of *clean* images (the validation
  positions re-rendered without clouds) is flagged, fitted on the validation split like the sigma scale; the
  test levels then report their detection at that gate (`at_clean_gate`), i.e. the ROC point "detect the bad
  frames at <= x% false alarms on clean images" measured without looking at the test split.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.train.model import CHI2_2_95


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
    raw = coverage95(pred, sigma, true)
    scale = float(np.sqrt(np.quantile(mahalanobis2(pred, sigma, true), 0.95) / CHI2_2_95))
    scale = min(max(scale, 1e-3), 1e3)
    with torch.no_grad():
        model.sigma_scale.fill_(scale)
    predictor.refresh()
    return {"val_coverage95_raw": raw, "sigma_scale": scale,
            "val_coverage95": coverage95(pred, sigma * scale, true), "n": int(len(true))}


def clean_gate(sigma_clean: np.ndarray, px_per_unit: float, false_alarm: float) -> float:
    """The gate (px of predicted error) that flags a share `false_alarm` of the clean images whose predicted
    sigmas are `sigma_clean` (at most that share; exactly, up to one image, without ties)."""
    pred_err = np.hypot(*(np.asarray(sigma_clean, np.float64) * px_per_unit).T)
    k = int(np.floor(false_alarm * len(pred_err) + 1e-9))  # images it may flag: those strictly above the gate
    return float(np.sort(pred_err)[len(pred_err) - k - 1])


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
