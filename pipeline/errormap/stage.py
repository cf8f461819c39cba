"""Stage: ε-error maps of a trained perception map (`python -m pipeline.errormap`, SPEC §2, Assumption 1).

For each occlusion level, renders the camera image `h(p)` at every point of a grid over the arena, runs the
perception map `l` on it and measures `E(p) = l(h(p)) - p` (:mod:`.estimates`); then the numbers of
:mod:`.analysis` (statistics, the Lipschitz estimate, Assumption 1's coverage set of the operational set, the
error model of Dean et al., the error against the distance to the data), written by :mod:`.writers` into a
tracked folder `<paths.errormaps_dir>/<model name>-<id>/` (docs/errormap.md lists the files and summary keys).

`run` accepts injected objects (perception map, camera, occlusions, dataset) so that the tests drive this very
code path with a synthetic map.
"""

from __future__ import annotations

import json
import time
from collections.abc import Mapping
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd
from omegaconf import DictConfig, OmegaConf

from pipeline import identity, tracking
from pipeline.config import build
from pipeline.config import settings as settings_
from pipeline.control import Scene
from pipeline.data import open_dataset
from pipeline.errormap import estimates as core
from pipeline.errormap.analysis import (
    analyse_heading,
    analyse_level,
    dean_center,
    eps_marks,
    fmt_eps,
    jsonable,
    operational_margin,
    operational_set,
)
from pipeline.errormap.checks import check
from pipeline.errormap.read import summary_table
from pipeline.errormap.settings import ErrorMapSettings
from pipeline.errormap.writers import write_outputs
from pipeline.errors import ConfigError, DatasetError, ModelError
from pipeline.lineage import debug_overrides, errormap_settings, rerun_command, resolve_dataset, resolve_map
from pipeline.perception.maps import load_perception_map
from pipeline.profiling import phase, record
from pipeline.render import load_occlusion


def _occlusions(cfg, levels) -> dict:
    """The cloud levels named by `occlusion_levels`, built from the run's `occlusions` node."""
    return {name: load_occlusion(name, cfg.occlusions, field="occlusion_levels") for name in levels}


def _scene_and_arena(pmap, camera) -> tuple[Scene, tuple, dict]:
    """The scene the model's images show (recorded in its manifest) and the camera's arena."""
    manifest = getattr(pmap, "manifest", None) or {}
    scene_cfg = manifest.get("scene")
    if not scene_cfg:
        raise ModelError(f"perception map {getattr(pmap, 'name', '?')}: its manifest records no scene")
    scene = build(scene_cfg, "scene")
    arena = getattr(camera, "arena", None) or scene.bounds
    return scene, tuple((float(lo), float(hi)) for lo, hi in arena), scene_cfg


def _occlusion_config(o) -> dict:
    """A cloud level as its id hashes it (an injected stand-in without `config()`: its plain attributes)."""
    if hasattr(o, "config"):
        return o.config()
    return {"type": type(o).__name__, **{k: v for k, v in getattr(o, "__dict__", {}).items()
                                         if isinstance(v, int | float | str | bool)}}


def _images_of(result) -> Any:
    return getattr(result, "images", result)


def _render_fn(camera, occlusion, shared=None, heading: float | None = None):
    """`render(points, rng)` for core.error_field; `shared`: one cloud sample shown in every image; `heading`: the
    heading every image shows (a pose map's error map)."""
    def pose(points):
        return {} if heading is None else {"heading": np.full(len(points), heading)}

    if shared is not None:
        def render(points: np.ndarray, rng: np.random.Generator | None):
            clouds = shared[np.zeros(len(points), dtype=np.intp)]
            return _images_of(camera.render(points, occlusion=occlusion, clouds=clouds, **pose(points)))
    else:
        def render(points: np.ndarray, rng: np.random.Generator | None):
            return _images_of(camera.render(points, occlusion=occlusion, rng=rng, **pose(points)))

    return render


def heading_grid(n: int) -> np.ndarray:
    """`n` headings evenly spaced over the circle from -π (radians)."""
    return -np.pi + 2.0 * np.pi * np.arange(n) / n


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
        pred[s : s + batch] = np.asarray(predict(np.asarray(images[sel])), dtype=float)[:, :2]  # a pose: its position
        bar.update(len(sel))
    bar.close()
    return positions[idx], pred


def _load_map(cfg, ref):
    """The map `ref` names, resolved with the run's `debug` level (a name means the map of the same debug size)."""
    try:
        folder = resolve_map(ref, cfg.paths.models_dir, overrides=debug_overrides(cfg))
    except DatasetError as err:
        raise ModelError(str(err)) from None
    return load_perception_map(folder, models_dir=cfg.paths.models_dir, device=cfg.get("device", "auto"))


def run(cfg: DictConfig, *, perception_map=None, camera=None, occlusions: Mapping | None = None,
        dataset=None) -> dict:
    """Error map of `cfg.maps` (one perception map, or each of a list); returns the result dict (see `run_one`).

    For a list: every map is loaded first (an unknown one fails before any work), then
    `{"maps": [result, ...], "table": summary_table(...)}`.
    """
    models = tracking.to_plain(cfg.get("maps"))
    if isinstance(models, list) and perception_map is None:
        check(cfg)
        loaded = [_load_map(cfg, ref) for ref in models]
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
    plan = _plan(cfg, perception_map, camera, occlusions)
    pmap, s, final = plan.pmap, plan.s, plan.final
    if tracking.exists(final, "error map") and not s.force:
        tracking.check_intact(final, "error map",
                              f"{rerun_command('errormap', [f'maps=[{final.name}]'], cfg)} force=true")
        print(f"errormap: {final} is complete (force=true to recompute)")
        return {"path": final, "summary": json.loads((final / "summary.json").read_text()), "skipped": True,
                "fields": None}
    ds = dataset if dataset is not None else _dataset(pmap, plan.manifest, cfg)
    progress = s.progress  # a bar on a terminal, one line every few seconds in a log

    t0 = time.perf_counter()
    with phase("train samples"):
        samples, sample_pred = _train_samples(ds, pmap.predict, s.train_samples, s.batch, s.seed, progress)
    t_train = time.perf_counter() - t0
    sample_err_vec = sample_pred - samples
    margin = operational_margin(s.operational_margin, plan.camera)
    with phase("error fields"):
        results, fields, operational = _compute_levels(plan, samples, sample_err_vec, margin, progress)
    s = _coverage_marks(s, plan.levels, results, fields, operational)
    summary = _summary(cfg, plan, s, results, samples, sample_err_vec, t_train, margin, operational)

    meta = {"recipe": plan.recipe, "inputs": {"model": str(pmap.id), "dataset": getattr(ds, "id", None)},
            "model_name": pmap.name, "code_version": tracking.code_version(*identity.ERRORMAP_CODE),
            "occlusions": {lv: o.config() for lv, o in plan.occ.items() if hasattr(o, "config")}}
    with tracking.tracked_output(plan.root, pmap.name, plan.id, meta) as tmp:
        write_outputs(tmp, summary, fields, results, plan.scene, plan.arena, s, samples, sample_err_vec)
    print(f"errormap: wrote {final}")
    record(f"errormap {pmap.name}")
    return {"path": final, "summary": summary, "skipped": False, "fields": fields}


@dataclass(frozen=True, eq=False)
class _Plan:
    """What one error map is computed from: its settings (`s`, typed; the id hashes the plain `recipe`), the
    perception map, camera and cloud levels, the scene and arena of the map's images, the grid `(points, shape, xs,
    ys)`, and where it goes (id, folder)."""

    s: ErrorMapSettings
    levels: list
    pmap: Any
    camera: Any
    occ: dict
    scene: Scene
    arena: tuple
    manifest: dict
    grid: tuple
    recipe: dict
    id: str
    root: Path
    final: Path
    pose: bool = False
    headings: tuple = (None,)


def _plan(cfg: DictConfig, perception_map, camera, occlusions) -> _Plan:
    """Check the settings, load (or take) the objects, lay the grid and name the output: no work yet."""
    s = settings_(cfg, ErrorMapSettings)
    settings = errormap_settings(cfg)  # plain: what the id hashes
    levels = s.occlusion_levels
    pmap = perception_map if perception_map is not None else _load_map(cfg, cfg.maps)
    camera = camera if camera is not None else pmap.camera()
    occ = dict(occlusions) if occlusions is not None else _occlusions(cfg, levels)
    missing = [lv for lv in levels if lv not in occ]
    if missing:
        raise ConfigError("occlusion_levels", f"no occlusion object for {missing}")
    scene, arena, scene_cfg = _scene_and_arena(pmap, camera)
    manifest = getattr(pmap, "manifest", None) or {}
    try:
        grid = core.arena_grid(arena, s.grid.step)
    except ValueError as err:
        raise ConfigError("grid.step", str(err)) from None

    pose = bool(getattr(pmap, "pose", False))  # a pose map: each point at `headings` headings, heading errors too
    headings = heading_grid(s.headings) if pose else [None]
    if not pose:
        settings = {k: v for k, v in settings.items() if k != "headings"}
    recipe = tracking.strip_keys(settings, identity.ERRORMAP_VOLATILE)
    id_ = identity.errormap_id(settings, {lv: _occlusion_config(o) for lv, o in occ.items()}, str(pmap.id),
                               scene_cfg, arena, pose)
    root = Path(cfg.paths.errormaps_dir)
    return _Plan(s, levels, pmap, camera, occ, scene, arena, manifest, grid, recipe, id_, root,
                 root / f"{pmap.name}-{id_}", pose, headings)


def _dataset(pmap, manifest: dict, cfg: DictConfig):
    """The dataset the perception map was trained on, by the id (or name) its manifest records."""
    ds_ref = manifest.get("dataset_id") or manifest.get("dataset_name")
    if not ds_ref:
        raise DatasetError(f"perception map {pmap.name}-{pmap.id}: manifest names no dataset_id")
    if manifest.get("dataset_name") and manifest.get("dataset_id"):
        ds_ref = f"{manifest['dataset_name']}-{manifest['dataset_id']}"
    try:
        folder = resolve_dataset(ds_ref, cfg.paths.get("datasets_dir"), debug_overrides(cfg))
        return open_dataset(folder, datasets_dir=cfg.paths.get("datasets_dir"))
    except DatasetError as err:
        raise DatasetError(f"the training data of perception map {pmap.name}-{pmap.id} (its error map samples the "
                           f"training positions): {err}") from None


def _compute_levels(plan: _Plan, samples, sample_err_vec, margin, progress: bool):
    """E over the grid for each occlusion level and its analysis: `(results, fields, operational)`."""
    s, (points, shape, xs, ys) = plan.s, plan.grid
    operational = operational_set(points, plan.scene, plan.arena, margin)
    near = core.nearest_distance(points, samples)
    sample_err = np.linalg.norm(sample_err_vec, axis=1)
    results, fields = {}, {"x": xs, "y": ys, "operational": operational.reshape(shape), "nearest": near.reshape(shape)}
    for li, level in enumerate(plan.levels):
        t1 = time.perf_counter()
        E = _error_draws(plan, li, level, progress)  # (K, N, 2), a pose map's (K * headings, N, 3)
        seconds = time.perf_counter() - t1
        r = results[level] = analyse_level(E[..., :2], points, shape, operational, samples, sample_err, near,
                                           plan.scene, s)
        r.update(draws=len(E) // len(plan.headings), seconds=seconds,
                 points_per_s=len(E) * len(points) / max(seconds, 1e-12))
        fields[f"E_{level}"] = E[..., :2].reshape(len(E), *shape, 2).astype(np.float32)
        if plan.pose:
            r["heading"] = analyse_heading(E[..., 2], points, operational, plan.scene, s)
            fields[f"H_{level}"] = np.degrees(E[..., 2]).reshape(len(E), *shape).astype(np.float32)
        fields[f"eps_min_{level}"] = r.pop("_eps_min").reshape(shape)
        fields[f"slope_{level}"] = r.pop("_slope")
        head = (f"; heading error mean {r['heading']['mean_deg']:.3g}°, p95 {r['heading']['p95_deg']:.3g}°"
                if plan.pose else "")
        print(f"errormap: {plan.pmap.name} [{level}]: |E| over the operational set mean {r['mean']:.3g}, "
              f"p95 {r['p95']:.3g}, max {r['max']:.3g}; L {r['L_max']:.3g} (p99 {r['L_p99']:.3g}); "
              f"covered for eps >= {fmt_eps(r['eps_cover'])}{head}; {r['points_per_s']:.0f} points/s")
    return results, fields, operational


def _error_draws(plan: _Plan, li: int, level: str, progress: bool) -> np.ndarray:
    """The K rendered draws of E over the grid at one level (one for a deterministic level), `(K, N, 2)` (a pose
    map's `(K * headings, N, 3)`, the heading error last); draw d
    uses the stream `(seed, li, d)`, and with `clouds: shared` one cloud sample shown at every point."""
    s, occ, camera = plan.s, plan.occ[level], plan.camera
    random = not _is_deterministic(level, occ)
    k = s.draws if random else 1
    shared_clouds = s.clouds == "shared"
    draws = []
    for d in range(k):
        rng = np.random.default_rng([s.seed, li, d])
        shared = occ.sample(1, rng, tuple(camera.shape)) if random and shared_clouds else None
        for th in plan.headings:  # a pose map: one field per heading (a draw each); else one field
            draws.append(core.error_field(plan.pmap.predict, _render_fn(camera, occ, shared, th), plan.grid[0],
                                          batch=s.batch, rng=rng, progress=progress, heading=th,
                                          desc=f"error map [{level}{f' {d + 1}/{k}' if k > 1 else ''}]"))
    return np.stack(draws)


def _coverage_marks(s: ErrorMapSettings, levels, results: dict, fields: dict, operational) -> ErrorMapSettings:
    """The ε marks whose covered sets are drawn (given, or per level's thresholds), each level's covered fraction
    at them (`coverage_at`, into `results`); returns the settings with the marks."""
    marks = eps_marks(s, [fields[f"eps_min_{lv}"].ravel()[operational] for lv in levels])
    for lv in levels:
        em = fields[f"eps_min_{lv}"].ravel()[operational]
        results[lv]["coverage_at"] = {f"{m:g}": float(core.coverage_curve(em, [m])[0]) for m in marks}
    return replace(s, coverage=replace(s.coverage, eps_marks=marks))


def _summary(cfg, plan: _Plan, s: ErrorMapSettings, results, samples, sample_err_vec, t_train, margin,
             operational) -> dict:
    """summary.json: the model, the grid, the coverage settings, the train samples' errors and Dean et al.'s fit,
    and every level's numbers."""
    points, shape = plan.grid[0], plan.grid[1]
    pmap, manifest, marks = plan.pmap, plan.manifest, s.coverage.eps_marks
    center = dean_center(s.dean.center, plan.scene)
    sample_err = np.linalg.norm(sample_err_vec, axis=1)
    train_summary = {**core.error_stats(sample_err), "seconds": t_train,
                     "dean": jsonable(core.dean_fit(sample_err_vec, samples, center, s.dean.eps_C))}
    return {
        "id": plan.id,
        "name": pmap.name,
        "model": {"ref": str(cfg.maps), "id": str(pmap.id), "name": pmap.name,
                  "dataset_id": manifest.get("dataset_id"), "dataset_name": manifest.get("dataset_name")},
        "grid": {"step": float(s.grid.step), "nx": int(shape[1]), "ny": int(shape[0]),
                 "n_points": int(len(points)), "n_operational": int(operational.sum()),
                 "operational_margin": margin,
                 "arena": [list(a) for a in plan.arena]},
        "r_cov": s.coverage.r_cov,
        "eps_marks": marks,
        "lipschitz_used": s.coverage.lipschitz,
        **({"headings_deg": np.degrees(plan.headings).tolist()} if plan.pose else {}),
        "dean_center": [float(c) for c in center],
        "train_samples": train_summary,
        "levels": jsonable(results),
    }
