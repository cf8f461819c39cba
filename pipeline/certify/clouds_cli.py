"""`python -m pipeline.certify.clouds_cli clouds.maps=<ref> clouds.occlusion=heavy clouds.layouts=299 ...`: perception
certified under clouds (issue 44; :mod:`pipeline.certify.clouds`), a Hydra app (conf/certify_clouds.yaml).

For the map and the cells of `clouds.region`: a sound bound per cell and cloud layout (N layouts of the level's
own process), the Clopper-Pearson `eps_bar_delta` per cell, and two checks of it: `samples` positions per cell and
layout rendered with that layout through the real camera (none may pass its layout's bound) and `fresh` frames per
cell under fresh layouts (the share above `eps_bar_delta` should sit under `delta`). Writes `table.csv` (one row
per cell) and `summary.json` to the run dir and prints one summary line. Not yet a tracked stage (no id, no
sharding): its outputs are a run's, like `python -m pipeline.simulate`'s. Bad settings: one line, exit 2.
"""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.errormap.analysis import operational_margin
from pipeline.errors import ConfigError
from pipeline.lineage import resolve_map
from pipeline.render.occlusion import load_occlusion

F = "clouds"


def check(cfg: DictConfig) -> dict:
    """Preflight (no torch): every setting, the map's folder and the cloud level, or one line naming the field."""
    s = tracking.to_plain(cfg.clouds)
    for key, lo, hi in (("delta", 0.0, 1.0), ("confidence", 0.0, 1.0)):
        v = s[key]
        if not isinstance(v, (int, float)) or not lo < v < hi:
            raise ConfigError(f"{F}.{key}", f"must be a number in ({lo:g}, {hi:g}), got {v!r}")
    for key in ("layouts", "threads"):
        if not isinstance(s[key], int) or isinstance(s[key], bool) or s[key] < 1:
            raise ConfigError(f"{F}.{key}", f"must be a positive integer, got {s[key]!r}")
    for key in ("samples", "fresh", "max_depth", "seed"):
        if not isinstance(s[key], int) or isinstance(s[key], bool) or s[key] < 0:
            raise ConfigError(f"{F}.{key}", f"must be a non-negative integer, got {s[key]!r}")
    if s["limit"] is not None and (not isinstance(s["limit"], int) or s["limit"] < 1):
        raise ConfigError(f"{F}.limit", f"must be null or a positive integer, got {s['limit']!r}")
    if not isinstance(s["cell"], (int, float)) or s["cell"] <= 0:
        raise ConfigError(f"{F}.cell", f"must be a positive number, got {s['cell']!r}")
    if s["mode"] not in ("crown", "forward", "ibp"):
        raise ConfigError(f"{F}.mode", f"must be crown, forward or ibp, got {s['mode']!r}")
    reg = np.asarray(s["region"], dtype=object)
    if reg.shape != (2, 2):
        raise ConfigError(f"{F}.region", f"must be [[x0, x1], [y0, y1]], got {s['region']!r}")
    occ = load_occlusion(s["occlusion"], field=f"{F}.occlusion")
    folder = resolve_map(s["maps"], cfg.paths.models_dir, field=f"{F}.maps")
    return {"settings": s, "occlusion": occ, "folder": folder}


def fresh_check(predict, camera, occ, cells, eps_delta, frames: int, seed: int) -> dict:
    """Frames at uniform positions of each cell under fresh layouts of the level (the loop's draw): the share whose
    error exceeds the cell's `eps_bar_delta` (to sit under `delta`, up to sampling)."""
    rng = np.random.default_rng([seed, 4404])
    t = rng.uniform(size=(len(cells), frames, 2))
    p = np.stack([cells[:, None, 0] + t[..., 0] * (cells[:, None, 1] - cells[:, None, 0]),
                  cells[:, None, 2] + t[..., 1] * (cells[:, None, 3] - cells[:, None, 2])], -1).reshape(-1, 2)
    imgs = camera.render(p, occlusion=occ, rng=rng)
    e = np.linalg.norm(np.asarray(predict(imgs), np.float64)[:, :2] - p, axis=-1).reshape(len(cells), frames)
    above = e > eps_delta[:, None]
    return {"frames": int(above.size), "above": int(above.sum()), "rate": float(above.mean()),
            "worst_cell_rate": float(above.mean(1).max())}


def run(cfg: DictConfig) -> dict:
    import torch  # torch-heavy, the run only: the preflight (and --help) imports none of these

    from pipeline.certify.clouds import certify_clouds, sampled_check
    from pipeline.certify.stage import cells_of
    from pipeline.perception.maps import load_perception_map

    checked = check(cfg)
    s, occ, folder = checked["settings"], checked["occlusion"], checked["folder"]
    torch.set_num_threads(int(s["threads"]))
    pmap = load_perception_map(folder, device="cpu")
    camera = pmap.camera()
    scene = build(pmap.manifest["scene"], "scene")
    arena = tuple((float(lo), float(hi)) for lo, hi in camera.arena)
    cells, _, _, _, op = cells_of(arena, float(s["cell"]), s["region"], scene, operational_margin("auto", camera))
    cells = cells[op]
    if s["limit"] and len(cells) > int(s["limit"]):
        cells = cells[np.linspace(0, len(cells) - 1, int(s["limit"])).round().astype(int)]
    cov = scene.covering(0)
    margin = float(cov.c - cov.obstacle_radius)
    r = certify_clouds(pmap.model, camera, cells, occ, int(s["layouts"]), float(s["delta"]), float(s["confidence"]),
                       int(s["seed"]), s["mode"], float(s["tolerance"]), int(s["max_depth"]), at=margin)
    t0 = time.perf_counter()
    bad, worst = sampled_check(pmap.predict, camera, occ, cells, r["lower"], r["upper"], r["layouts"],
                               int(s["samples"]), int(s["seed"])) if s["samples"] else (0, None)
    fresh = fresh_check(pmap.predict, camera, occ, cells, r["eps_bar_delta"], int(s["fresh"]), int(s["seed"]) + 1)
    check_s = time.perf_counter() - t0
    clean = r["eps"][:, np.flatnonzero(r["layouts"].clear)[:1]] if r["layouts"].clear.any() else None
    ed = r["eps_bar_delta"]
    summary = {"map": folder.name, "occlusion": occ.name, "cells": len(cells), "layouts": r["n_layouts"],
               "k_star": r["k_star"], "delta": r["delta"], "confidence": r["confidence"], "c_minus_r": margin,
               "eps_bar_delta": {"median": float(np.median(ed)), "p95": float(np.percentile(ed, 95, method='higher')),
                                 "max": float(ed.max())},
               "cells_eps_delta_below_c_minus_r": r["cells_certified"],
               "layout_bounds_below_c_minus_r": float(r["share"].mean()),
               "sampled": {"frames": len(cells) * len(r["layouts"]) * int(s["samples"]), "violations": bad,
                           "worst_excess": worst},
               "fresh": fresh, "seconds": r["seconds"], "check_seconds": check_s,
               "seconds_per_cell_layout": r["seconds"] / (len(cells) * r["n_layouts"]), "settings": s}
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = np.column_stack([cells, ed, np.full(len(cells), r["n_layouts"]), r["share"], r["violation_cp"],
                             np.full(len(cells), np.nan) if clean is None else clean[:, 0]])
    np.savetxt(out / "table.csv", table, delimiter=",", comments="", fmt="%.10g",
               header="x0,x1,y0,y1,eps_bar_delta,n_layouts,share_certified_at_c_minus_r,violation_cp,eps_clear")
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=str))
    print(f"clouds: {folder.name} under {occ.name}, {len(cells)} cells x {r['n_layouts']} layouts: eps_bar_delta "
          f"(delta {r['delta']:g}, confidence {r['confidence']:g}) median {np.median(ed):.3g}, p95 "
          f"{np.percentile(ed, 95, method='higher'):.3g}, max {ed.max():.3g}; {r['cells_certified']:.0%} of cells below c - r = "
          f"{margin:.3g}; sampled {bad} of {summary['sampled']['frames']} past their layout's bound; fresh layouts "
          f"{fresh['rate']:.2%} of {fresh['frames']} frames above eps_bar_delta; {r['seconds']:.0f} s "
          f"({summary['seconds_per_cell_layout'] * 1e3:.0f} ms per cell-layout)")
    return summary


main = stage_main("certify_clouds", run="pipeline.certify.clouds_cli:run", check="pipeline.certify.clouds_cli:check")

if __name__ == "__main__":
    main()
