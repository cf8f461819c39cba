"""Perception-map error metrics in pixels, split where the closed loop needs them (issue 11 §3).

- whole set: per-coordinate MAE (the authors' Keras metric), RMSE, Euclidean mean / p95 / max;
- `near_target`: images whose leader is within `r_T` world units of the target `p_T` (where the closed loop
  spends its time), `{mean, p95, max}` of the Euclidean error, as the error-map stage's `summary.json`;
- `visible` / `hidden`: images with less / at least `hidden_alpha` cloud opacity over the leader's pixel (the
  camera's `leader_alpha`); a map cannot see the robot on hidden frames and is judged separately there.
"""

from __future__ import annotations

import numpy as np

HIDDEN_ALPHA = 0.8  # cloud opacity over the robot from which a frame counts as hidden
NEAR_TARGET_RADIUS = 5.0  # r_T, world units


def _dist_px(pred, true, px_per_unit: float) -> tuple[np.ndarray, np.ndarray]:
    err = (np.asarray(pred, np.float64) - np.asarray(true, np.float64)) * px_per_unit
    return err, np.hypot(err[:, 0], err[:, 1])


def error_metrics(pred: np.ndarray, true: np.ndarray, px_per_unit: float) -> dict:
    """MAE (per coordinate), RMSE and Euclidean mean / p95 / max, in pixels."""
    err, dist = _dist_px(pred, true, px_per_unit)
    if not len(err):
        return {"mae_px": None, "rmse_px": None, "mean_dist_px": None, "p95_dist_px": None, "max_dist_px": None,
                "n": 0}
    return {
        "mae_px": float(np.abs(err).mean()),  # per coordinate, as Keras' MAE (the authors' metric)
        "rmse_px": float(np.sqrt((err**2).mean())),
        "mean_dist_px": float(dist.mean()),
        "p95_dist_px": float(np.percentile(dist, 95)),
        "max_dist_px": float(dist.max()),
        "n": len(err),
    }


def near_target_metrics(dist_px: np.ndarray) -> dict:
    """`{mean, p95, max, n}` of Euclidean errors (px); `None` values when the set is empty."""
    if not len(dist_px):
        return {"mean": None, "p95": None, "max": None, "n": 0}
    return {"mean": float(dist_px.mean()), "p95": float(np.percentile(dist_px, 95)), "max": float(dist_px.max()),
            "n": int(len(dist_px))}


def perception_metrics(pred: np.ndarray, true: np.ndarray, px_per_unit: float, *, target=None,
                       leader_alpha: np.ndarray | None = None, near_radius: float = NEAR_TARGET_RADIUS,
                       hidden_alpha: float = HIDDEN_ALPHA) -> dict:
    """`error_metrics` of the whole set, plus `near_target` (when `target` is given) and `visible` / `hidden`
    (when `leader_alpha` is given), each computed on its own subset of the same predictions."""
    true = np.asarray(true, np.float64)
    out = error_metrics(pred, true, px_per_unit)
    _, dist = _dist_px(pred, true, px_per_unit)
    if target is not None:
        near = np.hypot(*(true - np.asarray(target, np.float64)).T) <= near_radius
        out["near_target"] = {**near_target_metrics(dist[near]), "radius": float(near_radius)}
    if leader_alpha is not None:
        hidden = np.asarray(leader_alpha, np.float64) >= hidden_alpha
        pred = np.asarray(pred, np.float64)
        out["visible"] = error_metrics(pred[~hidden], true[~hidden], px_per_unit)
        out["hidden"] = {**error_metrics(pred[hidden], true[hidden], px_per_unit),
                         "share": float(hidden.mean()) if len(hidden) else 0.0, "alpha": float(hidden_alpha)}
    return out


def heading_error_deg(est: np.ndarray, true: np.ndarray) -> np.ndarray:
    """`|θ_est - θ|` wrapped to [0, 180] degrees."""
    d = np.angle(np.exp(1j * (np.asarray(est, float) - np.asarray(true, float))))
    return np.degrees(np.abs(d))


def heading_metrics(est: np.ndarray, true: np.ndarray) -> dict:
    """A pose map's heading error (degrees, wrapped): mean, median, p95, max."""
    e = heading_error_deg(est, true)
    return {"mean_deg": float(e.mean()), "median_deg": float(np.median(e)), "p95_deg": float(np.percentile(e, 95)),
            "max_deg": float(e.max())}
