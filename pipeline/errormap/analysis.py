"""The numbers of an ε-error map (SPEC §2, Assumption 1, Lemma 1): from one cloud level's error field
`E(p) = l(h(p)) - p` on the grid, its statistics over the operational set, the Lipschitz estimate, the coverage
set of Assumption 1 (the points within `r_cov` of a training sample whose bound holds), the error model of Dean
et al. and the error against the distance to the data. Pure numpy (the estimates live in
:mod:`pipeline.errormap.estimates`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from pipeline.control import Scene, in_diamond
from pipeline.errormap import estimates as core
from pipeline.errormap.settings import ErrorMapSettings


def operational_margin(margin, camera) -> float:
    """`auto`: half the robot's side in world units (where the robot is fully in view, as the datasets
    sample positions), else the number given."""
    if margin != "auto":
        return float(margin)
    size, scale = getattr(camera, "robot_size", None), getattr(camera, "scale", None)
    return float(size) / 2 / float(scale) if size and scale else 0.0


def operational_set(points: np.ndarray, scene: Scene, arena, margin: float = 0.0) -> np.ndarray:
    """The operational set on the grid: the arena shrunk by `margin`, minus the diamond `W_1 ∩ W_2`."""
    (x0, x1), (y0, y1) = arena
    inside = ((points[:, 0] >= x0 + margin) & (points[:, 0] <= x1 - margin)
              & (points[:, 1] >= y0 + margin) & (points[:, 1] <= y1 - margin))
    return inside & ~in_diamond(scene, points)


def dean_center(center, scene: Scene) -> np.ndarray:
    if center == "origin":
        return np.zeros(2)
    if center == "target":
        return np.asarray(scene.p_T, dtype=float)
    return np.asarray(center, dtype=float)


def analyse_level(E: np.ndarray, points: np.ndarray, shape: tuple[int, int], operational: np.ndarray,
                  samples: np.ndarray, sample_err: np.ndarray, near: np.ndarray, scene: Scene,
                  settings: ErrorMapSettings) -> dict:
    """All numbers of one occlusion level from its error field `E (K, N, 2)` (K draws per point).

    Statistics pool the K draws; the worst draw per point, `e(p) = max_k |E_k(p)|`, is what Assumption 1
    bounds, so it is the heat map, the Lipschitz bound check and the error-vs-distance quantity.
    """
    k = E.shape[0]
    mag = np.linalg.norm(E, axis=-1)  # (K, N)
    worst = mag.max(axis=0)
    op_stats = core.error_stats(mag[:, operational])
    arena_stats = core.error_stats(mag)
    # where the closed loop spends its time: within r_T of the target (operational points only)
    r_t = float(settings.near_target_radius)
    near_t = operational & (np.hypot(*(points - scene.p_T).T) <= r_t)
    near_stats = core.error_stats(mag[:, near_t]) if near_t.any() else {}
    step = float(settings.grid.step)
    grid_f = E.reshape(k, *shape, 2)
    lip_op = core.lipschitz_estimate(grid_f, step, operational.reshape(shape))
    lip_all = core.lipschitz_estimate(grid_f, step)
    L = lip_op["max"] if settings.coverage.lipschitz == "max" else lip_op["p99"]
    r_cov = settings.coverage.r_cov
    eps_min = core.coverage_eps_min(points, samples, sample_err, L, r_cov)
    eps_op = eps_min[operational]
    reachable = near[operational] <= (np.inf if r_cov is None else r_cov)
    eps_values = settings.coverage.eps
    eps_values = core.eps_sweep(eps_op) if eps_values is None else np.asarray(eps_values, dtype=float)
    eps_values = np.unique(np.concatenate([eps_values, np.asarray(settings.coverage.eps_marks or [])]))
    center = dean_center(settings.dean.center, scene)
    op_idx = np.flatnonzero(operational)
    dean = core.dean_fit(E[:, op_idx].reshape(-1, 2), np.tile(points[op_idx], (k, 1)), center,
                         settings.dean.eps_C)
    edges = _distance_edges(near[operational], int(settings.distance_bins))
    binned = core.binned_stats(near[operational], worst[operational], edges)
    # Lemma 1 on the grid: where a sample lies within r_cov, does |E(p)| <= eps_min(p) hold?
    has_bound = np.isfinite(eps_op)
    bound_ok = worst[operational][has_bound] <= eps_op[has_bound] * (1 + 1e-9) + 1e-12
    return {
        **op_stats,
        "arena": arena_stats,
        "near_target": {**{k: near_stats.get(k) for k in ("mean", "p95", "max")}, "radius": r_t,
                        "n_points": int(near_t.sum())},
        "L_max": lip_op["max"], "L_p99": lip_op["p99"], "L": L, "L_pairs": lip_op["n_pairs"],
        "L_arena_max": lip_all["max"], "L_arena_p99": lip_all["p99"],
        "eps_cover": core.smallest_coverage_eps(eps_op, 1.0),
        "eps_cover_95": core.smallest_coverage_eps(eps_op, 0.95),
        "eps_cover_50": core.smallest_coverage_eps(eps_op, 0.5),
        "eps_uniform": float(worst[operational].max()) if operational.any() else math.nan,
        "reachable": float(reachable.mean()) if reachable.size else math.nan,
        "bound_holds": float(bound_ok.mean()) if bound_ok.size else math.nan,
        "coverage": {"eps": eps_values, "fraction": core.coverage_curve(eps_op, eps_values)},
        "dean": dean,
        "error_vs_distance": binned,
        "_eps_min": eps_min,
        "_slope": lip_op["slope"],
    }


def _heading_stats(deg: np.ndarray) -> dict:
    deg = np.asarray(deg, dtype=float).ravel()
    if deg.size == 0:
        return {"n": 0, "mean_deg": math.nan, "median_deg": math.nan, "p95_deg": math.nan, "max_deg": math.nan}
    return {"n": int(deg.size), "mean_deg": float(deg.mean()), "median_deg": float(np.median(deg)),
            "p95_deg": float(np.percentile(deg, 95)), "max_deg": float(deg.max())}


def analyse_heading(H: np.ndarray, points: np.ndarray, operational: np.ndarray, scene: Scene,
                    settings: ErrorMapSettings) -> dict:
    """A pose map's heading error beside the position error (SPEC §2): `H (K, N)` the wrapped errors (radians) of
    the K fields (draws x headings); `|Δθ|` in degrees pooled over them, over the operational set (the headline),
    the arena, and within `near_target_radius` of the target; `worst_*`: of the worst heading per point."""
    deg = np.degrees(np.abs(np.asarray(H, dtype=float)))  # (K, N)
    r_t = float(settings.near_target_radius)
    near_t = operational & (np.hypot(*(points - scene.p_T).T) <= r_t)
    worst = deg.max(axis=0)[operational]
    return {**_heading_stats(deg[:, operational]), "fields": int(len(deg)),
            "arena": _heading_stats(deg),
            "near_target": {**_heading_stats(deg[:, near_t]), "radius": r_t},
            "worst_mean_deg": float(worst.mean()) if worst.size else math.nan,
            "worst_p95_deg": float(np.percentile(worst, 95)) if worst.size else math.nan}


def _distance_edges(dist: np.ndarray, bins: int) -> np.ndarray:
    """Equal-count bins (quantiles) of the distances: every bin holds about the same number of points."""
    finite = dist[np.isfinite(dist)]
    if finite.size == 0:
        return np.linspace(0.0, 1.0, bins + 1)
    edges = np.unique(np.quantile(finite, np.linspace(0, 1, bins + 1)))
    return edges if len(edges) > 1 else np.array([edges[0], edges[0] + 1.0])


def eps_marks(settings: ErrorMapSettings, eps_min_op: list[np.ndarray]) -> list[float]:
    """The ε values whose covered sets are drawn: `coverage.eps_marks`, else each level's 50 % and 95 %
    coverage thresholds, rounded to 2 significant digits (so that every panel shows a few bands)."""
    marks = settings.coverage.eps_marks
    if marks:
        return sorted(float(m) for m in marks)
    out = set()
    for e in eps_min_op:
        finite = np.asarray(e, dtype=float)
        finite = finite[np.isfinite(finite)]
        if finite.size:
            out |= {float(f"{q:.2g}") for q in np.quantile(finite, [0.5, 0.95]) if q > 0}
    return sorted(out)


def fmt_eps(v) -> str:
    return "never (points beyond r_cov of every sample)" if v is None or not math.isfinite(v) else f"{v:.3g}"


def jsonable(obj):
    """numpy -> plain Python; non-finite floats -> None (JSON has no inf/nan)."""
    if isinstance(obj, Mapping):
        return {str(k): jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return jsonable(obj.tolist())
    if isinstance(obj, np.integer | bool | np.bool_):
        return obj.item() if hasattr(obj, "item") else obj
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj
