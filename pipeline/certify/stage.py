"""Stage: the certified error map of a perception map (`python -m pipeline.certify`, SPEC §5.3).

Over the cells of side `cell` whose centres lie in the operational set (the errormap stage's: the arena shrunk
by the margin, minus the diamond), per `kappa`: the sound bound `eps_bar(P)` of `|l(h(p)) - p|` (:mod:`.bounds`,
adaptive splitting :mod:`.split`), the sampled `eps_emp(P)` (the largest error of `samples` positions per cell)
and the tightness `eps_bar / eps_emp`; statistics over the set, Assumption 1's certified coverage
`S_eps = {P : eps_bar(P) <= eps}` and the smallest `eps` covering the set, and Theorem 1's hypothesis: the
largest `eps_bar` against the margin the hybrid controller tolerates (`c - r`). Every sampled error is checked
against its cell's bound (soundness). Output: a tracked folder `<paths.certified_dir>/<map>-<id>/`.
"""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

from pipeline import identity, tracking
from pipeline.certify import shards
from pipeline.certify.attack import pgd_check
from pipeline.certify.bounds import prepare
from pipeline.certify.figures import scope, write_figures, write_table
from pipeline.certify.settings import CertifySettings
from pipeline.certify.split import certify_cells, eps_of, leaf_cells, pose_cells, sampled_errors
from pipeline.config import build
from pipeline.config import settings as settings_
from pipeline.control.covering import in_diamond
from pipeline.errormap import estimates as core
from pipeline.errormap.analysis import operational_margin, operational_set
from pipeline.errors import ConfigError, ModelError
from pipeline.lineage import debug_overrides, resolve_map
from pipeline.perception.maps import load_perception_map


def cells_of(arena, cell: float, region, scene, margin: float, diamond: str = "exclude"):
    """The grid of cells (`(x0, x1, y0, y1)` rows), its shape and centres, and the operational ones (`diamond`
    "include": the diamond's cells too, but those wholly inside an obstacle's disc, which no run reaches)."""
    try:
        points, shape, xs, ys = core.arena_grid(arena, cell)
    except ValueError as err:
        raise ConfigError("cell", str(err)) from None
    op = operational_set(points, scene, arena, margin)
    if diamond == "include":
        op = op | in_diamond(scene, points)
        op &= ~in_discs(scene, points, cell / 2)
    if region is not None:
        (rx0, rx1), (ry0, ry1) = region
        op &= (points[:, 0] >= rx0) & (points[:, 0] <= rx1) & (points[:, 1] >= ry0) & (points[:, 1] <= ry1)
    if not op.any():
        raise ConfigError("region", "no cell of the operational set lies in it")
    h = cell / 2
    cells = np.column_stack([points[:, 0] - h, points[:, 0] + h, points[:, 1] - h, points[:, 1] + h])
    return cells, shape, xs, ys, op


def in_discs(scene, centres: np.ndarray, half: float) -> np.ndarray:
    """The cells (of half-side `half` around `centres`) that lie wholly inside an obstacle's disc: their farthest
    corner within the radius."""
    out = np.zeros(len(centres), bool)
    for o in scene.obstacles:
        far = np.hypot(np.abs(centres[:, 0] - o.center[0]) + half, np.abs(centres[:, 1] - o.center[1]) + half)
        out |= far <= o.radius
    return out


REDUCE = {"violations": "sum", "worst": "max", "seconds": "sum", "sampled_seconds": "sum"}  # a chunk's scalars


def _stats(values: np.ndarray) -> dict:
    return {k: v for k, v in core.error_stats(values).items() if k != "rms"}


def _per_kappa(prep, pmap, camera, cells, s, margin_cr, shards_dir: Path):
    """Bounds, depth, sampled errors and the numbers of one `kappa` over `cells` (a pose map's: each with every
    heading interval, reported per position cell as the worst over them), computed in chunks (:mod:`.shards`);
    `None` for a run of one shard (`s.shard`), which only saves its part."""
    k = int(s.headings) if prep.net.heading is not None else 1
    bounded = pose_cells(cells, k) if prep.net.heading is not None else cells
    sample = prep.kappa == 0

    def chunk(a, b, c, bar):
        t0 = time.perf_counter()
        lower, upper, depth, leaves, heading = certify_cells(prep, bounded[a:b], s.mode, s.tolerance, s.max_depth,
                                                             s.batch, bar=bar)
        t1 = time.perf_counter()
        emp, violations, worst, head_emp = sampled_errors(
            pmap.predict, camera, bounded[a:b], lower, upper, s.samples, s.seed, heading=heading, stream=c,
            progress=False) if sample else (None, 0, (-np.inf, None), None)
        return ({"lower": lower, "upper": upper, "depth": depth, "leaves": leaves, "heading": heading, "emp": emp,
                 "head_emp": head_emp},
                {"violations": violations, "worst": list(worst), "seconds": t1 - t0,
                 "sampled_seconds": time.perf_counter() - t1})

    part = shards.run_sharded(len(bounded), s.batch, s, shards_dir, f"kappa{prep.kappa:g}", chunk, REDUCE,
                              f"certify kappa={prep.kappa:g}")
    if part is None:
        return None, None
    a, sc = part
    lower, upper, depth, leaves, heading = (a[k] for k in ("lower", "upper", "depth", "leaves", "heading"))
    emp, head_emp, seconds, sampled_seconds = a.get("emp"), a.get("head_emp"), sc["seconds"], sc["sampled_seconds"]
    violations, worst = sc["violations"], sc["worst"]
    pgd = None
    if s.pgd_cells > 0:  # an attacker on the bound: PGD over the position and the admissible images
        t2 = time.perf_counter()
        leaf_of = None if s.max_depth == 0 else (  # the leaves the bounds were computed on: the relaxations to attack
            lambda c: leaf_cells(prep, c, s.mode, s.tolerance, s.max_depth, s.batch))
        pgd = pgd_check(pmap.model, camera, bounded, lower, upper, prep.kappa, s.pgd_cells, s.pgd_steps,
                        s.seed, progress=bool(s.progress), leaves=leaf_of)
        pgd["seconds"] = time.perf_counter() - t2
    per_cell = lambda v, f: None if v is None else f(v.reshape(len(cells), k, *v.shape[1:]), 1)  # noqa: E731
    lower, upper, heading, emp, head_emp = (per_cell(v, f) for v, f in ((lower, np.min), (upper, np.max),
                                                                          (heading, np.max), (emp, np.max),
                                                                          (head_emp, np.max)))
    depth, leaves = per_cell(depth, np.max), per_cell(leaves, np.sum)
    eps = eps_of(lower, upper)
    out = {"kappa": prep.kappa, "eps_bar": _stats(eps), "seconds": seconds, "cells_per_s": len(bounded) / max(seconds, 1e-9),
           "depth": {str(d): int((depth == d).sum()) for d in range(int(s.max_depth) + 1)},
           "leaves": int(leaves.sum()), "eps_cover": float(eps.max()),
           "theorem1": {"max_eps_bar": float(eps.max()), "margin_c_minus_r": margin_cr,
                        "holds": bool(eps.max() < margin_cr), "covered_fraction": float((eps < margin_cr).mean())}}
    arrays = {"lower": lower, "upper": upper, "eps": eps, "depth": depth}
    if prep.net.heading is not None:
        out["heading_bar_deg"] = _stats(np.degrees(heading))
        arrays["heading"] = heading
    if emp is not None:
        tight = eps / np.maximum(emp, 1e-12)
        out.update(eps_emp=_stats(emp), tightness=_stats(tight), sampled_seconds=sampled_seconds,
                   soundness={"samples": int(len(bounded) * s.samples), "violations": violations,
                              "worst_excess": worst[0], "counterexample": worst[1] if worst[0] > 0 else None})
        arrays.update(emp=emp)
        if head_emp is not None:
            out["heading_emp_deg"] = _stats(np.degrees(head_emp))
            arrays["heading_emp"] = head_emp
    if pgd is not None:
        out["pgd"] = pgd
    return out, arrays


def _load(cfg: DictConfig, ref):
    try:
        folder = resolve_map(ref, cfg.paths.models_dir, overrides=debug_overrides(cfg))
    except Exception as err:  # noqa: BLE001 - an unknown map: one line
        raise ModelError(str(err)) from None
    return load_perception_map(folder, models_dir=cfg.paths.models_dir, device="cpu")


def run(cfg: DictConfig, *, perception_map=None, camera=None) -> dict:
    """The certified error map of `cfg.maps`; returns `{"path", "summary", "skipped"}`. `perception_map` and
    `camera` may be injected (`.model` a `PerceptionNet`, `.predict`, `.id`, `.name`, `.manifest`, `.camera()`)."""
    plain = tracking.to_plain({k: cfg[k] for k in cfg.keys() if k not in ("paths", "hydra")})  # what the id hashes
    s = settings_(cfg, CertifySettings)
    pmap = perception_map if perception_map is not None else _load(cfg, cfg.maps)
    camera = camera if camera is not None else pmap.camera()
    manifest = getattr(pmap, "manifest", None) or {}
    if not manifest.get("scene"):
        raise ModelError(f"perception map {pmap.name}: its manifest records no scene")
    scene = build(manifest["scene"], "scene")
    arena = tuple((float(lo), float(hi)) for lo, hi in camera.arena)
    id_ = identity.certify_id(plain, str(pmap.id), manifest["scene"], arena)
    root = Path(cfg.paths.certified_dir)
    final = root / f"{pmap.name}-{id_}"
    if tracking.is_complete(final) and not s.force:
        print(f"certify: {final} is complete (force=true to recompute)")
        return {"path": final, "summary": json.loads((final / "summary.json").read_text()), "skipped": True}
    margin = operational_margin(s.operational_margin, camera)
    cells, shape, xs, ys, op = cells_of(arena, float(s.cell), s.region, scene, margin, s.diamond)
    cov = scene.covering(0)
    margin_cr = float(cov.c - cov.obstacle_radius)
    torch.set_num_threads(int(s.threads))
    dtype = torch.float64 if s.dtype == "float64" else torch.float32
    levels, tables, fields = {}, {}, {"x": xs, "y": ys, "operational": op.reshape(shape)}
    shards_dir = root / shards.SHARDS_DIR / final.name
    for kappa in s.kappas:
        prep = prepare(pmap.model, camera, float(kappa), dtype, s.float_margin)
        r, arrays = _per_kappa(prep, pmap, camera, cells[op], s, margin_cr, shards_dir)
        if r is None:
            continue
        levels[f"{float(kappa):g}"] = r
        tables[f"{float(kappa):g}"] = np.column_stack([cells[op], arrays["eps"]])
        for k, v in arrays.items():
            full = np.full((len(cells), *v.shape[1:]), np.nan)
            full[op] = v
            fields[f"{k}_{float(kappa):g}"] = full.reshape(*shape, *v.shape[1:])
        _say(pmap.name, r, s.region)
    if s.shard is not None:
        print(f"certify: shard {s.shard} of {s.shards} of {final.name} -> {shards_dir} (merge: the same command "
              f"without shard=)")
        return {"path": shards_dir, "summary": None, "skipped": False, "shard": int(s.shard)}
    head = "keypoint" if getattr(pmap.model, "keypoint", False) else "flat"
    pose = bool(getattr(pmap.model, "pose", False))
    summary = {"id": id_, "name": pmap.name, "model": {"ref": str(cfg.maps), "id": str(pmap.id), "name": pmap.name,
                                                       "position_head": head, "outputs": "pose" if pose else "position"},
               **({"headings": int(s.headings)} if pose else {}),
               "cell": float(s.cell), "n_cells": int(op.sum()), "region": tracking.to_plain(s.region),
               "operational_margin": margin, "diamond": s.diamond,
               "mode": s.mode, "tolerance": s.tolerance, "max_depth": s.max_depth, "samples": s.samples,
               "float_margin": s.float_margin,
               "margin_c_minus_r": margin_cr, "torch_threads": int(s.threads), "kappas": levels}
    meta = {"recipe": tracking.strip_keys(plain, identity.CERTIFY_VOLATILE), "inputs": {"model": str(pmap.id)},
            "model_name": pmap.name, "code_version": tracking.code_version(*identity.CERTIFY_CODE)}
    with tracking.tracked_output(root, pmap.name, id_, meta) as tmp:
        (tmp / "summary.json").write_text(json.dumps(summary, indent=2))
        np.savez_compressed(tmp / "cells.npz", **fields)
        write_table(tmp / "table.md", summary)
        for k, t in tables.items():  # the cell table `python -m pipeline.bracket bracket.error_map=<this folder>` reads
            np.savetxt(tmp / f"error_map_kappa{k}.csv", t, delimiter=",", header="x0,x1,y0,y1,eps_bar", comments="",
                       fmt="%.17g")
        write_figures(tmp, fields, summary, arena, s.formats)
    shutil.rmtree(shards_dir, ignore_errors=True)  # merged: the shards are in the map now
    print(f"certify: wrote {final}")
    return {"path": final, "summary": summary, "skipped": False}


def _say(name: str, r: dict, region=None) -> None:
    e = r["eps_bar"]
    emp = f"; sampled p95 {r['eps_emp']['p95']:.3g}, max {r['eps_emp']['max']:.3g}; tightness median " \
          f"{r['tightness']['median']:.3g}; {r['soundness']['violations']} of {r['soundness']['samples']} sampled " \
          f"errors outside their bound" if "eps_emp" in r else ""
    a = r.get("pgd")
    emp += f"; PGD on {a['cells']} cells (every image the relaxation admits): {a['violations']} past their bound, " \
           f"reaching at most {a['share_max']:.0%} of it (median {a['share_median']:.0%})" if a else ""
    emp += f"; a search over real renders: {a['render_violations']} past, at most {a['render_share_max']:.0%} " \
           f"(median {a['render_share_median']:.0%})" if a and "render_share_max" in a else ""
    if "heading_bar_deg" in r:
        h = r["heading_bar_deg"]
        emp += f"; heading bound median {h['median']:.3g} deg, max {h['max']:.3g} deg" + (
            f" (sampled max {r['heading_emp_deg']['max']:.3g} deg)" if "heading_emp_deg" in r else "")
    print(f"certify: {name} [kappa {r['kappa']:g}]: certified eps over {scope(region, e['n'])} "
          f"mean {e['mean']:.3g}, "
          f"p95 {e['p95']:.3g}, max {e['max']:.3g} (c - r = {r['theorem1']['margin_c_minus_r']:.3g}: "
          f"{'holds' if r['theorem1']['holds'] else 'not shown'}){emp}; {r['seconds']:.0f} s")
