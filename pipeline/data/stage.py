"""Stage: render a tracked camera dataset (`python -m pipeline.data data=<recipe>`, `make data`).

Output: `<paths.datasets_dir>/<name>-<id>/` with `images_<split>.npy` (uint8 (n, H, W, 3), memory-mappable),
`labels.csv`, `preview.png` and `manifest.json` (docs/data.md). The id (:func:`pipeline.identity.dataset_id`)
hashes the recipe (minus volatile keys), the visible scene, the render and cloud configs and the code.

Inputs by id (docs/dagger.md): `data.sampling.parent` (a dataset whose train split this one's extends: its images
and labels are copied first, the new draws appended) and `data.sampling.closed_loop.map` (the perception map in
the loop that collects the train split's closed-loop share) are resolved through :mod:`pipeline.lineage`; their
`name-id`s replace the references in the recipe (so in the id) and are listed under `parents` in the manifest.
"""

from __future__ import annotations

import time

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.data.plan import Plan, check
from pipeline.data.render import render_into
from pipeline.data.sampling import split_pool
from pipeline.errors import ConfigError
from pipeline.lineage import rerun_command
from pipeline.preflight import prepared


def _visits(p: Plan) -> tuple[object, dict]:
    """Load the recipe's map (on `closed_loop.device`) and simulate its closed loop once (the train split's
    pool, cached); returns the map and what the manifest records about its visits."""
    from pipeline.perception.maps import load_perception_map, resolve_device  # torch: a map in the loop

    cl = p.recipe.closed_loop
    try:
        resolve_device(cl.device)
    except ConfigError as err:
        raise ConfigError("data.sampling.closed_loop.device", err.reason) from None
    pm = load_perception_map(p.map_path, device=cl.device)
    t0 = time.perf_counter()
    visits = split_pool(p.recipe, "train", p.camera, p.occlusion, pm)
    summary = visits.summary(cl)
    err = summary.get("map_error", {})
    print(f"data: {p.parents['map']} in the loop ({cl.starts} starts, {cl.horizon:g} s, occlusion "
          f"{p.occlusion.name}): {summary['frames']} frames, {summary['outside_view_share']:.0%} outside the camera's "
          f"view; in view, map error mean {err.get('mean', float('nan')):.2f} / p95 {err.get('p95', float('nan')):.2f} "
          f"units ({time.perf_counter() - t0:.1f} s)")
    return pm, {"closed_loop_visits": summary}


def run(cfg: DictConfig) -> dict:
    """Render the dataset of `cfg.data` unless a valid one with the same id exists (`force=true` re-renders).

    Returns `{"id", "name", "path", "counts", "parents", "skipped", "seconds"}`.
    """
    t0 = time.perf_counter()
    p = prepared(cfg, check)  # the preflight's plan, when it checked this job
    out = {"id": p.id, "name": p.recipe.name, "path": p.path, "counts": p.counts, "parents": dict(p.parents)}
    if tracking.exists(p.path, "dataset") and not cfg.force:
        tracking.check_intact(p.path, "dataset", f"{rerun_command('data', [f'data={p.recipe.name}'], cfg)} force=true")
        print(f"data: {p.folder_name} exists and matches its manifest -> {p.path} (nothing to do; force=true re-renders)")
        return {**out, "skipped": True, "seconds": time.perf_counter() - t0}
    pm, visits = _visits(p) if p.map_path is not None else (None, {})
    with tracking.tracked_output(p.root, p.recipe.name, p.id, {**p.meta(), **visits}) as tmp:
        render_into(tmp, p, pm)
    secs = time.perf_counter() - t0
    counts = ", ".join(f"{s} {n}" for s, n in p.counts.items())
    kept = f" ({p.parent_train} train images of {p.parents['dataset']})" if p.parent_path is not None else ""
    print(f"data: {p.recipe.name} id {p.id}: {counts} images{kept} ({p.camera.height}x{p.camera.width}, "
          f"occlusion {p.occlusion.name}) in {secs:.1f} s -> {p.path}")
    return {**out, "skipped": False, "seconds": secs}


