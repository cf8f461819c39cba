"""The clouds app's run (`python -m pipeline.certify.clouds_cli`; its preflight `check` there): the cells of the
region, the bound per layout and `eps_bar_delta` (:mod:`.clouds`), with a gate the uncertainty head's bounds and
`eps_bar_delta_gated` (:mod:`.gate`), the two checks (sampled positions against their layout's bounds, fresh layouts
against `eps_bar_delta`), `table.csv` and `clouds.json` in the run dir, and the summary lines."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np
import torch

from pipeline.certify import gate as g
from pipeline.certify.bounds import prepare
from pipeline.certify.clouds import cell_points, certify_clouds, sampled_check
from pipeline.certify.clouds_cli import F, check
from pipeline.certify.stage import cells_of
from pipeline.config import build
from pipeline.errormap.analysis import operational_margin
from pipeline.errors import ConfigError
from pipeline.perception.maps import load_perception_map

COLUMNS = "x0,x1,y0,y1,eps_bar_delta,n_layouts,share_certified_at_c_minus_r,violation_cp,eps_clear"
GATED = ",eps_bar_delta_gated,flagged_share,undecided_share"


def certify_gated(model, camera, cells, occ, layouts, delta, confidence, seed, mode, tolerance, max_depth,
                  at=None, gate: float | None = None) -> dict:
    """:func:`.clouds.certify_clouds`, and with a `gate` (a map with an uncertainty head): the gate statistic's
    bounds `gate_lower, gate_upper (C, L)`, `eps_bar_delta_gated` and (with `at`) the flagged and undecided shares."""
    t0 = time.perf_counter()
    out = certify_clouds(model, camera, cells, occ, layouts, delta, confidence, seed, mode, tolerance, max_depth,
                         at=at)
    if gate is None:
        return out
    t1 = time.perf_counter()
    prep, eps, draws = prepare(model, camera, 0.0, torch.float32), out["eps"], out["layouts"]
    glo, ghi = g.layout_gate(model, prep, np.asarray(cells, np.float64), draws, mode)
    eg = g.eps_delta_gated(eps, glo, gate, delta, confidence)
    out.update(gate=gate, gate_lower=glo, gate_upper=ghi, eps_bar_delta_gated=eg, gate_seconds=time.perf_counter() - t1)
    out["seconds"] = time.perf_counter() - t0
    if at is not None:
        out.update(**g.shares(eps, glo, at, gate), cells_certified_gated=float((eg <= at).mean()))
    return out


def fresh_check(predict, camera, occ, cells, eps_delta, frames: int, seed: int) -> dict:
    """Frames at uniform positions of each cell under fresh layouts of the level (the loop's draw): the share whose
    error exceeds the cell's `eps_bar_delta` (to sit under `delta`, up to sampling)."""
    rng = np.random.default_rng([seed, 4404])
    p = cell_points(rng, cells, frames)
    imgs = camera.render(p, occlusion=occ, rng=rng)
    e = np.linalg.norm(np.asarray(predict(imgs), np.float64)[:, :2] - p, axis=-1).reshape(len(cells), frames)
    above = e > eps_delta[:, None]
    return {"frames": int(above.size), "above": int(above.sum()), "rate": float(above.mean()),
            "worst_cell_rate": float(above.mean(1).max())}


def region_cells(s: dict, camera, scene) -> np.ndarray:
    """The operational cells of `clouds.region` (at most `clouds.limit` of them, evenly spaced)."""
    arena = tuple((float(lo), float(hi)) for lo, hi in camera.arena)
    cells, _, _, _, op = cells_of(arena, float(s["cell"]), s["region"], scene, operational_margin("auto", camera))
    cells = cells[op]
    if s["limit"] and len(cells) > int(s["limit"]):
        cells = cells[np.linspace(0, len(cells) - 1, int(s["limit"])).round().astype(int)]
    return cells


def run(cfg) -> dict:
    """`python -m pipeline.certify.clouds_cli` (module docstring there): the run after its preflight."""
    checked = check(cfg)
    s, occ, folder = checked["settings"], checked["occlusion"], checked["folder"]
    torch.set_num_threads(int(s["threads"]))
    pmap = load_perception_map(folder, device="cpu")
    camera = pmap.camera()
    scene = build(pmap.manifest["scene"], "scene")
    cells = region_cells(s, camera, scene)
    cov = scene.covering(0)
    margin = float(cov.c - cov.obstacle_radius)
    gate = s.get("gate")
    if gate is not None and getattr(pmap.model, "var_head", None) is None:
        raise ConfigError(f"{F}.gate", f"perception map {folder.name} has no uncertainty head (train it with "
                                       "model.uncertainty=gaussian, or gate=null)")
    r = certify_gated(pmap.model, camera, cells, occ, int(s["layouts"]), float(s["delta"]), float(s["confidence"]),
                      int(s["seed"]), s["mode"], float(s["tolerance"]), int(s["max_depth"]), at=margin,
                      gate=None if gate is None else float(gate))
    summary = report(s, r, pmap, camera, occ, cells, folder.name, margin)
    if gate is not None:
        summary["gated"] = gated_report(s, r, pmap, camera, occ, cells)
    write(Path(cfg.paths.output_dir), cells, r, summary)
    for line in lines(summary, r):
        print(line)
    return summary


def _stats(x: np.ndarray) -> dict:
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95, method="higher")), "max": float(x.max())}


def report(s: dict, r: dict, pmap, camera, occ, cells, name: str, margin: float) -> dict:
    """The summary of the ungated run, with its two checks (sampled positions, fresh layouts)."""
    t0 = time.perf_counter()
    bad, worst = sampled_check(pmap.predict, camera, occ, cells, r["lower"], r["upper"], r["layouts"],
                               int(s["samples"]), int(s["seed"])) if s["samples"] else (0, None)
    fresh = fresh_check(pmap.predict, camera, occ, cells, r["eps_bar_delta"], int(s["fresh"]), int(s["seed"]) + 1)
    return {"map": name, "occlusion": occ.name, "cells": len(cells), "layouts": r["n_layouts"],
            "k_star": r["k_star"], "delta": r["delta"], "confidence": r["confidence"], "c_minus_r": margin,
            "eps_bar_delta": _stats(r["eps_bar_delta"]), "cells_eps_delta_below_c_minus_r": r["cells_certified"],
            "layout_bounds_below_c_minus_r": float(r["share"].mean()),
            "sampled": {"frames": len(cells) * len(r["layouts"]) * int(s["samples"]), "violations": bad,
                        "worst_excess": worst},
            "fresh": fresh, "seconds": r["seconds"], "check_seconds": time.perf_counter() - t0,
            "seconds_per_cell_layout": r["seconds"] / (len(cells) * r["n_layouts"]),
            "settings": {k: v for k, v in s.items() if k != "gate" or v is not None}}  # gate null: as before


def gated_report(s: dict, r: dict, pmap, camera, occ, cells) -> dict:
    """The gate's block of the summary, with its checks (sampled predicted errors, fresh frames kept)."""
    g_bad, g_worst = g.gate_sampled_check(pmap.predicted_error, camera, occ, cells, r["gate_lower"], r["gate_upper"],
                                          r["layouts"], int(s["samples"]), int(s["seed"])) \
        if s["samples"] else (0, None)
    g_fresh = g.gate_fresh_check(pmap.predicted_error, camera, occ, cells, r["eps_bar_delta_gated"], r["gate"],
                                 int(s["fresh"]), int(s["seed"]) + 1)
    return {"gate": r["gate"], "eps_bar_delta_gated": _stats(r["eps_bar_delta_gated"]),
            "cells_eps_delta_gated_below_c_minus_r": r["cells_certified_gated"],
            "flagged_share": float(r["flagged_share"].mean()), "undecided_share": float(r["undecided_share"].mean()),
            "sampled": {"frames": len(cells) * len(r["layouts"]) * int(s["samples"]), "violations": g_bad,
                        "worst_relative_excess": g_worst},
            "fresh": g_fresh, "seconds": r["gate_seconds"]}


def write(out: Path, cells, r: dict, summary: dict) -> None:
    """`table.csv` (one row per cell; the gate's columns with a gate) and `clouds.json` in the run dir `out`."""
    out.mkdir(parents=True, exist_ok=True)
    clean = r["eps"][:, np.flatnonzero(r["layouts"].clear)[:1]] if r["layouts"].clear.any() else None
    table = np.column_stack([cells, r["eps_bar_delta"], np.full(len(cells), r["n_layouts"]), r["share"],
                             r["violation_cp"], np.full(len(cells), np.nan) if clean is None else clean[:, 0]])
    header = COLUMNS
    if "gated" in summary:
        table = np.column_stack([table, r["eps_bar_delta_gated"], r["flagged_share"], r["undecided_share"]])
        header += GATED
    np.savetxt(out / "table.csv", table, delimiter=",", comments="", fmt="%.10g", header=header)
    (out / "clouds.json").write_text(json.dumps(summary, indent=2, default=str))


def lines(summary: dict, r: dict) -> list[str]:
    """The summary lines (the gate's second)."""
    e, sm = summary["eps_bar_delta"], summary
    out = [f"clouds: {sm['map']} under {sm['occlusion']}, {sm['cells']} cells x {sm['layouts']} layouts: eps_bar_delta "
           f"(delta {sm['delta']:g}, confidence {sm['confidence']:g}) median {e['median']:.3g}, p95 {e['p95']:.3g}, "
           f"max {e['max']:.3g}; {sm['cells_eps_delta_below_c_minus_r']:.0%} of cells below c - r = "
           f"{sm['c_minus_r']:.3g}; sampled {sm['sampled']['violations']} of {sm['sampled']['frames']} past their "
           f"layout's bound; fresh layouts {sm['fresh']['rate']:.2%} of {sm['fresh']['frames']} frames above "
           f"eps_bar_delta; {sm['seconds']:.0f} s ({sm['seconds_per_cell_layout'] * 1e3:.0f} ms per cell-layout)"]
    if "gated" in summary:
        gs, ge = summary["gated"], summary["gated"]["eps_bar_delta_gated"]
        out.append(f"gate {gs['gate']:g}: eps_bar_delta_gated median {ge['median']:.3g}, p95 {ge['p95']:.3g}, max "
                   f"{ge['max']:.3g}; {gs['cells_eps_delta_gated_below_c_minus_r']:.0%} of cells below c - r; at "
                   f"c - r the layouts are {gs['flagged_share']:.1%} flagged, {gs['undecided_share']:.1%} undecided; "
                   f"sampled {gs['sampled']['violations']} of {gs['sampled']['frames']} predicted errors past their "
                   f"bounds; fresh layouts {gs['fresh']['rate']:.2%} of {gs['fresh']['frames']} frames above "
                   f"eps_bar_delta_gated and not dropped ({gs['fresh']['dropped']:.1%} dropped); "
                   f"{gs['seconds']:.0f} s for the gate")
    return out
