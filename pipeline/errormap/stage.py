"""Stage: ε-error maps of a trained perception map (`python -m pipeline.errormap`, issue 5, SPEC §2).

For each occlusion level, renders the camera image `h(p)` at every point of a grid over the arena, runs the
perception map `l` on it and measures `F(p) = l(h(p)) - p`; then the Lipschitz estimate of `F`, the
Assumption-1 coverage of the operational set (arena minus the diamond) by the model's training samples,
the error model of Dean et al., and error against distance to the nearest training sample. Writes a tracked
folder `<paths.errormaps_dir>/<model name>-<id>/` (docs/errormap.md lists the files and summary keys).

The math lives in `pipeline.errormap.core`; `run` accepts injected objects (perception map, camera,
occlusions, dataset) so that the tests drive this very code path with a synthetic map.
"""

from __future__ import annotations

import json
import math
import sys
import time
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline import tracking
from pipeline.cli import REPO_ROOT
from pipeline.control import Scene, in_diamond
from pipeline.errormap import core
from pipeline.errors import ConfigError, DatasetError, ModelError

VOLATILE = ("force", "progress", "paths", "hydra", "maps", "occlusions", "device")
LIPSCHITZ_CHOICES = ("max", "p99")
DEFAULT_ARENA = ((-50.0, 50.0), (-30.0, 30.0))


# ------------------------------------------------------------------------------------------- config
def _plain(cfg) -> Any:
    return OmegaConf.to_container(cfg, resolve=True) if isinstance(cfg, DictConfig | ListConfig) else cfg


def validate(cfg) -> dict:
    """Check the errormap config; returns the plain settings. Raises ConfigError naming the key."""
    get = cfg.get
    step = get("grid", {}).get("step", 0.5)
    if not isinstance(step, int | float) or not math.isfinite(step) or step <= 0:
        raise ConfigError("grid.step", f"must be a number > 0 (world units), got {step!r}")
    levels = _plain(get("occlusion_levels", ["none"]))
    if isinstance(levels, str):
        levels = [levels]
    if not levels or not all(isinstance(x, str) and x for x in levels) or len(set(levels)) != len(levels):
        raise ConfigError("occlusion_levels", f"must be a non-empty list of distinct level names, got {levels!r}")
    ints = {"draws": 1, "batch": 1, "distance_bins": 1}
    for key, low in ints.items():
        val = get(key)
        if not isinstance(val, int) or isinstance(val, bool) or val < low:
            raise ConfigError(key, f"must be an integer >= {low}, got {val!r}")
    n_train = get("train_samples")
    if n_train is not None and (not isinstance(n_train, int) or n_train < 1):
        raise ConfigError("train_samples", f"must be an integer >= 1 or null (all), got {n_train!r}")
    cov = get("coverage", {})
    r_cov = cov.get("r_cov", 1.0)
    if r_cov is not None and (not isinstance(r_cov, int | float) or not r_cov > 0):
        raise ConfigError("coverage.r_cov", f"must be > 0 or null (unlimited), got {r_cov!r}")
    lip = cov.get("lipschitz", "max")
    if lip not in LIPSCHITZ_CHOICES:
        raise ConfigError("coverage.lipschitz", f"must be one of {LIPSCHITZ_CHOICES}, got {lip!r}")
    for key in ("eps", "eps_marks"):
        vals = _plain(cov.get(key))
        if vals is None:
            continue
        try:
            arr = np.asarray(vals, dtype=float).ravel()
        except (TypeError, ValueError):
            arr = np.array([np.nan])
        if not np.all(np.isfinite(arr)) or np.any(arr < 0) or (key == "eps" and arr.size == 0):
            raise ConfigError(f"coverage.{key}", f"must be a list of numbers >= 0, got {vals!r}")
    dean = get("dean", {})
    center = _plain(dean.get("center", "origin"))
    if not (center in ("origin", "target") or (isinstance(center, list) and len(center) == 2)):
        raise ConfigError("dean.center", f"must be origin, target or a pair [x, y], got {center!r}")
    eps_c = _plain(dean.get("eps_C", []))
    try:
        eps_c_arr = np.asarray(eps_c, dtype=float).ravel()
    except (TypeError, ValueError):
        eps_c_arr = np.array([np.nan])
    if not np.all(np.isfinite(eps_c_arr)) or np.any(eps_c_arr < 0):
        raise ConfigError("dean.eps_C", f"must be a list of numbers >= 0, got {eps_c!r}")
    r_t = get("near_target_radius", 5.0)
    if isinstance(r_t, bool) or not isinstance(r_t, int | float) or not r_t > 0:
        raise ConfigError("near_target_radius", f"must be a number > 0 (world units), got {r_t!r}")
    margin = get("operational_margin", "auto")
    if margin != "auto" and (not isinstance(margin, int | float) or isinstance(margin, bool) or not margin >= 0):
        raise ConfigError("operational_margin", f"must be auto (half the robot) or a number >= 0, got {margin!r}")
    clouds = get("clouds", "independent")
    if clouds not in ("independent", "shared"):
        raise ConfigError("clouds", f"must be independent (a fresh cloud draw per image) or shared (one per draw), "
                                    f"got {clouds!r}")
    formats = _plain(get("formats", ["png"]))
    if not formats or not all(f in ("png", "pdf", "svg") for f in formats):
        raise ConfigError("formats", f"must be a non-empty list of png/pdf/svg, got {formats!r}")
    plain = {k: _plain(cfg[k]) for k in cfg.keys() if k not in ("paths", "hydra")}  # paths need a Hydra run
    plain["occlusion_levels"] = list(levels)
    return plain


# --------------------------------------------------------------------------------------- injection
def _load_map(ref, models_dir, device="auto"):
    try:
        from pipeline.train import load_perception_map
    except ImportError as err:  # the train stage is not installed in this tree
        raise DatasetError(f"cannot load perception map {ref!r}: pipeline.train is unavailable ({err})") from None
    return load_perception_map(ref, models_dir=models_dir, device=device)


def _occlusions(cfg, levels) -> dict:
    """The cloud levels named by `occlusion_levels`, built from the run's `occlusions` node."""
    from pipeline.render import load_occlusion

    return {name: load_occlusion(name, cfg.occlusions, field="occlusion_levels") for name in levels}


def _open_dataset(ref, datasets_dir):
    from pipeline.data import open_dataset

    return open_dataset(ref, datasets_dir=datasets_dir)


def _scene_and_arena(pmap, camera) -> tuple[Scene, tuple, dict]:
    """The scene the model's images show (recorded in its manifest)."""
    manifest = getattr(pmap, "manifest", None) or {}
    scene_cfg = manifest.get("scene")
    if not scene_cfg:
        raise ModelError(f"perception map {getattr(pmap, 'name', '?')}: its manifest records no scene")
    scene = Scene.from_config(OmegaConf.create(scene_cfg))
    arena = getattr(camera, "arena", None)
    if arena is None:
        a = scene_cfg.get("arena") or {}
        arena = (tuple(a.get("x", DEFAULT_ARENA[0])), tuple(a.get("y", DEFAULT_ARENA[1])))
    arena = tuple((float(lo), float(hi)) for lo, hi in arena)
    return scene, arena, scene_cfg


def _images_of(result) -> Any:
    return getattr(result, "images", result)


def _render_fn(camera, occlusion, shared=None):
    """`render(points, rng)` for core.error_field; `shared`: one cloud sample shown in every image."""
    if shared is not None:
        def render(points: np.ndarray, rng: np.random.Generator | None):
            clouds = shared[np.zeros(len(points), dtype=np.intp)]
            return _images_of(camera.render(points, occlusion=occlusion, clouds=clouds))
    else:
        def render(points: np.ndarray, rng: np.random.Generator | None):
            return _images_of(camera.render(points, occlusion=occlusion, rng=rng))

    return render


def _is_deterministic(name: str, occlusion) -> bool:
    """No random draws in the images: level `none`, no object, or an inactive Occlusion."""
    return occlusion is None or name == "none" or not getattr(occlusion, "active", True)


def _train_samples(dataset, predict, n_max, batch, seed, progress):
    """Positions p_d and predictions l(theta_d) on (a sorted random subsample of) the train split."""
    positions = np.asarray(dataset.positions("train"), dtype=float)
    images = dataset.images("train")
    n = len(positions)
    if n == 0:
        raise DatasetError(f"dataset {getattr(dataset, 'name', '?')}: empty train split")
    if n_max is not None and n > n_max:
        idx = np.sort(np.random.default_rng([int(seed), 7919]).choice(n, size=n_max, replace=False))
    else:
        idx = np.arange(n)
    pred = np.empty((len(idx), 2))
    bar = core._progress(len(idx), "train samples", progress)
    for s in range(0, len(idx), batch):
        sel = idx[s : s + batch]
        pred[s : s + batch] = np.asarray(predict(np.asarray(images[sel])), dtype=float)
        bar.update(len(sel))
    bar.close()
    return positions[idx], pred


# ---------------------------------------------------------------------------------------------- run
def run(cfg: DictConfig, *, perception_map=None, camera=None, occlusions: Mapping | None = None,
        dataset=None) -> dict:
    """Error map of `cfg.maps` (one perception map, or each of a list); returns the result dict (see `run_one`).

    For a list: every map is loaded first (an unknown one fails before any work), then
    `{"maps": [result, ...], "table": summary_table(...)}`.
    """
    models = _plain(cfg.get("maps"))
    if isinstance(models, list) and perception_map is None:
        validate(cfg)
        if not models:
            raise ConfigError("maps", "needs at least one perception map")
        loaded = [_load_map(ref, cfg.paths.models_dir, cfg.get("device", "auto")) for ref in models]
        results = [run_one(OmegaConf.merge(cfg, {"maps": ref}), perception_map=pm)
                   for ref, pm in zip(models, loaded)]
        table = summary_table([r["summary"] for r in results])
        with pd.option_context("display.width", 200, "display.max_columns", 20, "display.precision", 3):
            print(table.drop(columns=["model_id", "errormap"]).to_string(index=False))
        return {"maps": results, "table": table}
    return run_one(cfg, perception_map=perception_map, camera=camera, occlusions=occlusions, dataset=dataset)


def run_one(cfg: DictConfig, *, perception_map=None, camera=None, occlusions: Mapping | None = None,
            dataset=None) -> dict:
    """Error map of one perception map. Returns `{"path", "summary", "skipped", "fields"}`.

    Injected objects replace the loaders: `perception_map` (`.predict(images) -> (N, 2)`, `.id`, `.name`,
    `.manifest`, `.camera()`), `camera` (`.render(points, occlusion=, rng=)`), `occlusions`
    (`{level: occlusion object}`), `dataset` (`.positions("train")`, `.images("train")`).
    """
    settings = validate(cfg)
    levels = settings["occlusion_levels"]
    pmap = perception_map if perception_map is not None else _load_map(cfg.maps, cfg.paths.models_dir,
                                                                        cfg.get("device", "auto"))
    camera = camera if camera is not None else pmap.camera()
    occ = dict(occlusions) if occlusions is not None else _occlusions(cfg, levels)
    shared_clouds = settings.get("clouds", "independent") == "shared"
    missing = [lv for lv in levels if lv not in occ]
    if missing:
        raise ConfigError("occlusion_levels", f"no occlusion object for {missing}")
    scene, arena, scene_cfg = _scene_and_arena(pmap, camera)
    manifest = getattr(pmap, "manifest", None) or {}
    try:
        points, shape, xs, ys = core.arena_grid(arena, settings["grid"]["step"])
    except ValueError as err:
        raise ConfigError("grid.step", str(err)) from None

    recipe = tracking.strip_keys(settings, VOLATILE)
    _, id_ = errormap_identity(cfg, pmap, camera, settings=settings, occlusions=occ)
    root = Path(cfg.paths.errormaps_dir)
    final = root / f"{pmap.name}-{id_}"
    if tracking.is_complete(final) and not settings.get("force", False):
        print(f"errormap: {final} is complete (force=true to recompute)")
        return {"path": final, "summary": json.loads((final / "summary.json").read_text()), "skipped": True,
                "fields": None}

    ds = dataset
    if ds is None:
        ds_ref = manifest.get("dataset_id") or manifest.get("dataset_name")
        if not ds_ref:
            raise DatasetError(f"perception map {pmap.name}-{pmap.id}: manifest names no dataset_id")
        ds = _open_dataset(ds_ref, cfg.paths.get("datasets_dir"))
    progress = bool(settings.get("progress", True)) and sys.stderr.isatty()
    batch = int(settings["batch"])

    t0 = time.perf_counter()
    samples, sample_pred = _train_samples(ds, pmap.predict, settings.get("train_samples"), batch,
                                          settings["seed"], progress)
    t_train = time.perf_counter() - t0
    sample_err_vec = sample_pred - samples
    sample_err = np.linalg.norm(sample_err_vec, axis=1)
    margin = operational_margin(settings.get("operational_margin", "auto"), camera)
    operational = operational_set(points, scene, arena, margin)
    near = core.nearest_distance(points, samples)

    results, fields = {}, {"x": xs, "y": ys, "operational": operational.reshape(shape), "nearest": near.reshape(shape)}
    for li, level in enumerate(levels):
        random = not _is_deterministic(level, occ[level])
        k = int(settings["draws"]) if random else 1
        t1 = time.perf_counter()
        draws = []
        for d in range(k):
            rng = np.random.default_rng([int(settings["seed"]), li, d])
            shared = occ[level].sample(1, rng, tuple(camera.shape)) if random and shared_clouds else None
            draws.append(core.error_field(pmap.predict, _render_fn(camera, occ[level], shared), points,
                                          batch=batch, rng=rng, progress=progress,
                                          desc=f"error map [{level}{f' {d + 1}/{k}' if k > 1 else ''}]"))
        F = np.stack(draws)  # (K, N, 2)
        seconds = time.perf_counter() - t1
        results[level] = analyse_level(F, points, shape, operational, samples, sample_err, near, scene,
                                       settings)
        results[level].update(draws=k, seconds=seconds, points_per_s=k * len(points) / max(seconds, 1e-12))
        fields[f"F_{level}"] = F.reshape(k, *shape, 2).astype(np.float32)
        fields[f"eps_min_{level}"] = results[level].pop("_eps_min").reshape(shape)
        fields[f"slope_{level}"] = results[level].pop("_slope")
        r = results[level]
        print(f"errormap: {pmap.name} [{level}]: |F| over the operational set mean {r['mean']:.3g}, "
              f"p95 {r['p95']:.3g}, max {r['max']:.3g}; L {r['L_max']:.3g} (p99 {r['L_p99']:.3g}); "
              f"covered for eps >= {_fmt_eps(r['eps_cover'])}; {r['points_per_s']:.0f} points/s")

    marks = eps_marks(settings, [fields[f"eps_min_{lv}"].ravel()[operational] for lv in levels])
    for lv in levels:
        em = fields[f"eps_min_{lv}"].ravel()[operational]
        results[lv]["coverage_at"] = {f"{m:g}": float(core.coverage_curve(em, [m])[0]) for m in marks}
    settings = {**settings, "coverage": {**settings["coverage"], "eps_marks": marks}}
    center = _dean_center(settings["dean"].get("center", "origin"), scene)
    train_summary = {**core.error_stats(sample_err), "seconds": t_train,
                     "dean": _jsonable(core.dean_fit(sample_err_vec, samples, center, settings["dean"]["eps_C"]))}
    summary = {
        "id": id_,
        "name": pmap.name,
        "model": {"ref": str(cfg.maps), "id": str(pmap.id), "name": pmap.name,
                  "dataset_id": manifest.get("dataset_id"), "dataset_name": manifest.get("dataset_name")},
        "grid": {"step": float(settings["grid"]["step"]), "nx": int(shape[1]), "ny": int(shape[0]),
                 "n_points": int(len(points)), "n_operational": int(operational.sum()),
                 "operational_margin": margin,
                 "arena": [list(a) for a in arena]},
        "r_cov": settings["coverage"]["r_cov"],
        "eps_marks": marks,
        "lipschitz_used": settings["coverage"]["lipschitz"],
        "dean_center": [float(c) for c in center],
        "train_samples": train_summary,
        "levels": _jsonable(results),
    }
    meta = {"recipe": recipe, "inputs": {"model": str(pmap.id), "dataset": getattr(ds, "id", None)},
            "model_name": pmap.name, "code_version": tracking.code_version("errormap", "render"),
            "occlusions": {lv: o.config() for lv, o in occ.items() if hasattr(o, "config")}}
    with tracking.tracked_output(root, pmap.name, id_, meta) as tmp:
        write_outputs(tmp, summary, fields, results, scene, arena, settings, samples, sample_err_vec)
    print(f"errormap: wrote {final}")
    return {"path": final, "summary": summary, "skipped": False, "fields": fields}


def errormap_identity(cfg, pmap, camera=None, *, settings=None, occlusions=None) -> tuple[str, str]:
    """(folder name, id) of the error map a composed errormap config computes for `pmap`: the settings (minus
    volatile keys), the occlusion levels' parameters, the map id, its scene and arena, and the code."""
    settings = settings if settings is not None else validate(cfg)
    camera = camera if camera is not None else pmap.camera()
    occ = occlusions if occlusions is not None else _occlusions(cfg, settings["occlusion_levels"])
    _, arena, scene_cfg = _scene_and_arena(pmap, camera)
    occ_cfg = {lv: o.config() if hasattr(o, "config") else
               {"type": type(o).__name__, **{k: v for k, v in getattr(o, "__dict__", {}).items()
                                         if isinstance(v, int | float | str | bool)}}
               for lv, o in occ.items()}
    id_ = tracking.content_id(tracking.strip_keys(settings, VOLATILE), occ_cfg, str(pmap.id), scene_cfg,
                              [float(v) for pair in arena for v in pair], tracking.code_version("errormap", "render"))
    return pmap.name, id_


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


def _dean_center(center, scene: Scene) -> np.ndarray:
    if center == "origin":
        return np.zeros(2)
    if center == "target":
        return np.asarray(scene.p_T, dtype=float)
    return np.asarray(center, dtype=float)


def analyse_level(F: np.ndarray, points: np.ndarray, shape: tuple[int, int], operational: np.ndarray,
                  samples: np.ndarray, sample_err: np.ndarray, near: np.ndarray, scene: Scene,
                  settings: Mapping) -> dict:
    """All numbers of one occlusion level from its error field `F (K, N, 2)` (K draws per point).

    Statistics pool the K draws; the worst draw per point, `e(p) = max_k |F_k(p)|`, is what Assumption 1
    bounds, so it is the heat map, the Lipschitz bound check and the error-vs-distance quantity.
    """
    k = F.shape[0]
    mag = np.linalg.norm(F, axis=-1)  # (K, N)
    worst = mag.max(axis=0)
    op_stats = core.error_stats(mag[:, operational])
    arena_stats = core.error_stats(mag)
    # where the closed loop spends its time: within r_T of the target (operational points only)
    r_t = float(settings.get("near_target_radius", 5.0))
    near_t = operational & (np.hypot(*(points - scene.p_T).T) <= r_t)
    near_stats = core.error_stats(mag[:, near_t]) if near_t.any() else {}
    step = float(settings["grid"]["step"])
    grid_f = F.reshape(k, *shape, 2)
    lip_op = core.lipschitz_estimate(grid_f, step, operational.reshape(shape))
    lip_all = core.lipschitz_estimate(grid_f, step)
    L = lip_op["max"] if settings["coverage"]["lipschitz"] == "max" else lip_op["p99"]
    r_cov = settings["coverage"]["r_cov"]
    eps_min = core.coverage_eps_min(points, samples, sample_err, L, r_cov)
    eps_op = eps_min[operational]
    reachable = near[operational] <= (np.inf if r_cov is None else r_cov)
    eps_values = settings["coverage"].get("eps")
    eps_values = core.eps_sweep(eps_op) if eps_values is None else np.asarray(eps_values, dtype=float)
    eps_values = np.unique(np.concatenate([eps_values, np.asarray(settings["coverage"].get("eps_marks") or [])]))
    center = _dean_center(settings["dean"].get("center", "origin"), scene)
    op_idx = np.flatnonzero(operational)
    dean = core.dean_fit(F[:, op_idx].reshape(-1, 2), np.tile(points[op_idx], (k, 1)), center,
                         settings["dean"]["eps_C"])
    edges = _distance_edges(near[operational], int(settings["distance_bins"]))
    binned = core.binned_stats(near[operational], worst[operational], edges)
    # Lemma 1 on the grid: where a sample lies within r_cov, does |F(p)| <= eps_min(p) hold?
    has_bound = np.isfinite(eps_op)
    bound_ok = worst[operational][has_bound] <= eps_op[has_bound] * (1 + 1e-9) + 1e-12
    return {
        **op_stats,
        "arena": arena_stats,
        "near_target": {**{k: near_stats.get(k) for k in ("mean", "p95", "max")}, "radius": r_t,
                        "n_points": int(near_t.sum())},
        "L_max": lip_op["max"], "L_p99": lip_op["p99"], "L": L, "L_pairs": lip_op["n_pairs"],
        "L_arena_max": lip_all["max"], "L_arena_p99": lip_all["p99"],
        "eps_cover": core.smallest_covering_eps(eps_op, 1.0),
        "eps_cover_95": core.smallest_covering_eps(eps_op, 0.95),
        "eps_cover_50": core.smallest_covering_eps(eps_op, 0.5),
        "eps_uniform": float(worst[operational].max()) if operational.any() else math.nan,
        "reachable": float(reachable.mean()) if reachable.size else math.nan,
        "bound_holds": float(bound_ok.mean()) if bound_ok.size else math.nan,
        "coverage": {"eps": eps_values, "fraction": core.coverage_curve(eps_op, eps_values)},
        "dean": dean,
        "error_vs_distance": binned,
        "_eps_min": eps_min,
        "_slope": lip_op["slope"],
    }


def _distance_edges(dist: np.ndarray, bins: int) -> np.ndarray:
    """Equal-count bins (quantiles) of the distances: every bin holds about the same number of points."""
    finite = dist[np.isfinite(dist)]
    if finite.size == 0:
        return np.linspace(0.0, 1.0, bins + 1)
    edges = np.unique(np.quantile(finite, np.linspace(0, 1, bins + 1)))
    return edges if len(edges) > 1 else np.array([edges[0], edges[0] + 1.0])


def eps_marks(settings: Mapping, eps_min_op: list[np.ndarray]) -> list[float]:
    """The ε values whose covered sets are drawn: `coverage.eps_marks`, else each level's 50 % and 95 %
    coverage thresholds, rounded to 2 significant digits (so that every panel shows a few bands)."""
    marks = settings["coverage"].get("eps_marks")
    if marks:
        return sorted(float(m) for m in marks)
    out = set()
    for e in eps_min_op:
        finite = np.asarray(e, dtype=float)
        finite = finite[np.isfinite(finite)]
        if finite.size:
            out |= {float(f"{q:.2g}") for q in np.quantile(finite, [0.5, 0.95]) if q > 0}
    return sorted(out)


def _fmt_eps(v) -> str:
    return "never (points beyond r_cov of every sample)" if v is None or not math.isfinite(v) else f"{v:.3g}"


def _jsonable(obj):
    """numpy -> plain Python; non-finite floats -> None (JSON has no inf/nan)."""
    if isinstance(obj, Mapping):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, list | tuple):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return _jsonable(obj.tolist())
    if isinstance(obj, np.integer | bool | np.bool_):
        return obj.item() if hasattr(obj, "item") else obj
    if isinstance(obj, float | np.floating):
        v = float(obj)
        return v if math.isfinite(v) else None
    return obj


# ------------------------------------------------------------------------------------------ writing
def write_outputs(folder: Path, summary: dict, fields: dict, results: dict, scene: Scene, arena,
                  settings: Mapping, samples: np.ndarray, sample_err_vec: np.ndarray) -> None:
    """CSV tables, summary.json, fields.npz and the figures (docs/errormap.md)."""
    levels = list(results)
    rows = []
    for lv, r in results.items():
        for region, st in (("operational", {k: r[k] for k in ("n", "mean", "median", "p95", "max", "rms")}),
                           ("arena", r["arena"])):
            rows.append({"level": lv, "region": region, **st})
    pd.DataFrame(rows).to_csv(folder / "stats.csv", index=False)
    pd.DataFrame([{"level": lv, "region": reg, "L_max": r[f"L{suf}max"], "L_p99": r[f"L{suf}p99"]}
                  for lv, r in results.items()
                  for reg, suf in (("operational", "_"), ("arena", "_arena_"))]).to_csv(
        folder / "lipschitz.csv", index=False)
    pd.DataFrame([{"level": lv, "eps": e, "coverage": f, "L": r["L"]}
                  for lv, r in results.items()
                  for e, f in zip(r["coverage"]["eps"], r["coverage"]["fraction"])]).to_csv(
        folder / "coverage.csv", index=False)
    dean_rows = []
    dean_sets = {lv: r["dean"] for lv, r in results.items()}
    dean_sets["train"] = summary["train_samples"]["dean"]
    for lv, d in dean_sets.items():
        dean_rows += [{"data": lv, "kind": "front", "eps_C": c, "eps_eta": e} for c, e in (d["front"] or [])]
        dean_rows += [{"data": lv, "kind": "at", "eps_C": c, "eps_eta": e} for c, e in (d["at"] or [])]
    pd.DataFrame(dean_rows, columns=["data", "kind", "eps_C", "eps_eta"]).to_csv(folder / "dean_fit.csv", index=False)
    pd.DataFrame([{"level": lv, **{k: r["error_vs_distance"][k][b] for k in
                                   ("lo", "hi", "count", "mean", "median", "p95", "max")}}
                  for lv, r in results.items() for b in range(len(r["error_vs_distance"]["lo"]))]).to_csv(
        folder / "error_vs_distance.csv", index=False)
    np.savez_compressed(folder / "fields.npz", samples=samples.astype(np.float32),
                        sample_err=sample_err_vec.astype(np.float32), **fields)
    figures = _figures(folder, fields, results, scene, arena, settings, levels)
    summary["files"] = sorted(p.name for p in folder.iterdir()) + ["summary.json"]
    summary["figures"] = figures
    (folder / "summary.json").write_text(json.dumps(_jsonable(summary), indent=2) + "\n")


def _shared_norm(arrays: list[np.ndarray]):
    """One colour scale for all panels: logarithmic when the values span more than 20x (a clean and an
    occluded level side by side), else linear from 0. Returns `(norm, floor)`; plot `max(values, floor)`."""
    from matplotlib.colors import LogNorm, Normalize

    vals = np.concatenate([np.asarray(a, dtype=float).ravel() for a in arrays])
    vals = vals[np.isfinite(vals)]
    vmax = float(np.percentile(vals, 99.5)) if vals.size else 1.0
    vmax = vmax if vmax > 0 else 1.0
    pos = vals[vals > 0]
    vmin = max(float(np.percentile(pos, 1)) if pos.size else vmax, vmax * 1e-4)
    if vmax / vmin > 20:
        return LogNorm(vmin=vmin, vmax=vmax), vmin
    return Normalize(vmin=0.0, vmax=vmax), 0.0


def _figures(folder: Path, fields: dict, results: dict, scene: Scene, arena, settings, levels) -> list[str]:
    from matplotlib import pyplot as plt
    from matplotlib.colors import BoundaryNorm

    from pipeline.viz import draw_scene, save

    fmts = tuple(settings.get("formats", ["png"]))
    (x0, x1), (y0, y1) = arena
    extent = (x0, x1, y0, y1)
    n = len(levels)
    out = []

    def panels(title):
        fig, axes = plt.subplots(n, 1, figsize=(7.5, 3.6 * n), squeeze=False, layout="constrained")
        fig.suptitle(title)
        return fig, axes[:, 0]

    # error map: worst |F| per point, shared colour scale
    worst = {lv: np.linalg.norm(fields[f"F_{lv}"], axis=-1).max(axis=0) for lv in levels}
    norm, floor = _shared_norm(list(worst.values()))
    fig, axes = panels("ε-error map |F(p)| = |l(h(p)) - p|")
    for ax, lv in zip(axes, levels):
        im = ax.imshow(np.maximum(worst[lv], floor), origin="lower", extent=extent, cmap="magma_r", norm=norm,
                       interpolation="nearest")
        draw_scene(ax, scene, arena)
        r = results[lv]
        ax.set_title(f"occlusion {lv}: mean {r['mean']:.2f}, p95 {r['p95']:.2f}, max {r['max']:.2f}"
                     f" (operational set)", fontsize=9)
        fig.colorbar(im, ax=ax, label="|F| (world units)", extend="max", shrink=0.85)
    out += save(fig, folder / "error_map", fmts)

    # local slope map
    slopes = {lv: fields[f"slope_{lv}"] for lv in levels}
    norm, floor = _shared_norm(list(slopes.values()))
    fig, axes = panels("local slope of F (largest difference quotient to a neighbour)")
    for ax, lv in zip(axes, levels):
        sl = np.where(np.isfinite(slopes[lv]), np.maximum(slopes[lv], floor), np.nan)  # NaN: not operational
        im = ax.imshow(sl, origin="lower", extent=extent, cmap=plt.get_cmap("viridis").with_extremes(bad="0.92"),
                       norm=norm, interpolation="nearest")
        draw_scene(ax, scene, arena)
        ax.set_title(f"occlusion {lv}: L max {results[lv]['L_max']:.3g}, p99 {results[lv]['L_p99']:.3g}",
                     fontsize=9)
        fig.colorbar(im, ax=ax, label="|ΔF| / |Δp|", extend="max", shrink=0.85)
    out += save(fig, folder / "slope_map", fmts)

    # coverage: curve + eps_min maps with covered-set contours
    marks = sorted(settings["coverage"].get("eps_marks") or [])
    fig, axes = plt.subplots(n + 1, 1, figsize=(7.5, 3.5 * (n + 1)), squeeze=False, layout="constrained")
    axes = axes[:, 0]
    for lv in levels:
        c = results[lv]["coverage"]
        (line,) = axes[0].plot(c["eps"], c["fraction"], label=f"{lv} (L = {results[lv]['L']:.3g})")
        ec = results[lv]["eps_cover"]
        if ec is not None and math.isfinite(ec):
            axes[0].axvline(ec, ls=":", color=line.get_color())
    for m in marks:
        axes[0].axvline(m, color="0.6", lw=0.6)
    axes[0].set_xlabel("ε")
    axes[0].set_ylabel("covered fraction\nof the operational set")
    axes[0].set_ylim(0, 1.02)
    axes[0].legend(fontsize=8)
    axes[0].set_title(f"Assumption 1: p ∈ S(L, ε), r_cov = {settings['coverage']['r_cov']} "
                      "(dotted: smallest ε covering the operational set)", fontsize=9)
    # nested covered sets: the colour of p is the smallest marked ε whose covering set contains it
    bounds = [0.0, *marks, np.inf]
    cmap = plt.get_cmap("viridis", len(bounds) - 1).with_extremes(bad="tab:red")
    norm = BoundaryNorm(np.arange(len(bounds)) - 0.5, cmap.N)
    for ax, lv in zip(axes[1:], levels):
        em = fields[f"eps_min_{lv}"]
        band = np.where(np.isfinite(em), np.searchsorted(marks, em, side="left"), np.nan)
        im = ax.imshow(band, origin="lower", extent=extent, cmap=cmap, norm=norm, interpolation="nearest")
        ax.imshow(np.where(fields["operational"], np.nan, 1.0), origin="lower", extent=extent, cmap="Greys",
                  vmin=0, vmax=1.6, alpha=0.75, interpolation="nearest")  # grey veil: not operational
        draw_scene(ax, scene, arena)
        ax.set_title(f"occlusion {lv}: covered sets (red: no sample within r_cov); operational set covered "
                     f"for ε >= {_fmt_eps(results[lv]['eps_cover'])}", fontsize=8)
        cb = fig.colorbar(im, ax=ax, ticks=range(len(bounds) - 1), shrink=0.85)
        cb.ax.set_yticklabels([f"ε ≤ {m:g}" for m in marks] + [f"ε > {marks[-1]:g}" if marks else "covered"],
                              fontsize=7)
    out += save(fig, folder / "coverage", fmts)

    # error vs distance to the nearest training sample
    fig, ax = plt.subplots(figsize=(7, 4), layout="constrained")
    op = fields["operational"].ravel()
    near = fields["nearest"].ravel()[op]
    rng = np.random.default_rng(0)
    for lv in levels:
        w = worst[lv].ravel()[op]
        sub = rng.choice(len(w), size=min(len(w), 4000), replace=False)
        sc = ax.scatter(near[sub], w[sub], s=2, alpha=0.25)
        b = results[lv]["error_vs_distance"]
        mid = (b["lo"] + b["hi"]) / 2
        ax.plot(mid, b["median"], "-o", ms=3, color=sc.get_facecolor()[0][:3], label=f"{lv}: median")
        ax.plot(mid, b["p95"], "--", color=sc.get_facecolor()[0][:3], label=f"{lv}: p95")
    ax.set_xlabel("distance to the nearest training sample")
    ax.set_ylabel("|F(p)|")
    ax.set_title("where the map is trustworthy: error vs distance to the data", fontsize=9)
    ax.legend(fontsize=8)
    out += save(fig, folder / "error_vs_distance", fmts)
    return [Path(p).name for p in out]


# -------------------------------------------------------------------------------------- read back
def default_errormaps_dir() -> Path:
    return REPO_ROOT / "outputs" / "errormaps"


def load_error_map(ref, errormaps_dir=None) -> dict:
    """A finished error map by model name (latest), id, `name-id` or path: its summary.json plus
    `"path"` (Path) and `"paths"` (`{file name: Path}`). Unknown or incomplete -> DatasetError."""
    root = Path(errormaps_dir) if errormaps_dir is not None else default_errormaps_dir()
    from pipeline.lineage import resolve_errormap

    folder = resolve_errormap(ref, root)
    problems = tracking.verify(folder, full=False)
    if problems:
        raise DatasetError(f"error map {folder}: " + "; ".join(problems[:3]))
    summary = json.loads((folder / "summary.json").read_text())
    summary["path"] = folder
    summary["paths"] = {p.name: p for p in sorted(folder.iterdir()) if p.is_file()}
    return summary


def summary_table(refs, errormaps_dir=None) -> pd.DataFrame:
    """One row per (error map, occlusion level): the headline numbers the experiments stage quotes."""
    rows = []
    for ref in refs:
        s = ref if isinstance(ref, Mapping) else load_error_map(ref, errormaps_dir)  # a summary or a reference
        for lv, r in s["levels"].items():
            rows.append({
                "model": s["model"]["name"], "model_id": s["model"]["id"], "occlusion": lv,
                "mean": r["mean"], "p95": r["p95"], "max": r["max"],
                "near_target_mean": r.get("near_target", {}).get("mean"),
                "near_target_p95": r.get("near_target", {}).get("p95"), "L": r["L"], "L_p99": r["L_p99"],
                "eps_cover": r["eps_cover"], "eps_cover_95": r["eps_cover_95"], "bound_holds": r["bound_holds"],
                "dean_eps_eta_at_0": r["dean"]["eps_eta_at_0"], "dean_eps_C_at_0": r["dean"]["eps_C_at_0"],
                "errormap": s["id"],
            })
    return pd.DataFrame(rows)
