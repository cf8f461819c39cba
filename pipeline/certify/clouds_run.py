"""The clouds app's run (`python -m pipeline.certify.clouds_cli`; its preflight `check` there): the cells of the
region in chunks (:mod:`.shards`: each chunk's bounds per layout and `eps_bar_delta` (:mod:`.clouds`), with a gate
the uncertainty head's bounds and `eps_bar_delta_gated` (:mod:`.gate`), and its two checks: sampled positions
against their layout's bounds, fresh layouts against `eps_bar_delta`), merged; `table.csv` and `clouds.json` in a
tracked folder `<paths.certified_dir>/clouds/<map>_<level>-<id>/`, and the summary lines."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import torch

from pipeline import tracking
from pipeline.certify import gate as g
from pipeline.certify import shards
from pipeline.certify.bounds import prepare
from pipeline.certify.clouds import cell_points, certify_clouds, draw_seed, max_exceedances, sampled_check
from pipeline.certify.clouds_cli import F, check
from pipeline.certify.stage import cells_of
from pipeline.config import build
from pipeline.errormap.analysis import operational_margin
from pipeline.errors import ConfigError
from pipeline.identity import CERTIFY_CODE, clouds_id
from pipeline.perception.maps import load_perception_map

COLUMNS = "x0,x1,y0,y1,eps_bar_delta,n_layouts,share_certified_at_c_minus_r,violation_cp,eps_clear"
GATED = ",eps_bar_delta_gated,flagged_share,undecided_share"
# a chunk's scalars: counts and seconds add up, the worst excesses are the largest
REDUCE = {k: "sum" for k in ("seconds", "gate_seconds", "check_seconds", "sampled_frames", "sampled_violations",
                             "fresh_frames", "fresh_above", "gate_sampled_violations", "gate_fresh_frames",
                             "gate_fresh_above", "gate_fresh_dropped")}
REDUCE.update({k: "max" for k in ("sampled_worst", "fresh_worst_cell_rate", "gate_sampled_worst",
                                  "gate_fresh_worst_cell_rate")})


def certify_gated(model, camera, cells, occ, layouts, delta, confidence, seed, mode, tolerance, max_depth,
                  at=None, gate: float | None = None, dtype=torch.float32, tick=None, float_margin: float = 0.0) -> dict:
    """:func:`.clouds.certify_clouds`, and with a `gate` (a map with an uncertainty head): the gate statistic's
    bounds `gate_lower, gate_upper (C, L)`, `eps_bar_delta_gated` and (with `at`) the flagged and undecided shares."""
    t0 = time.perf_counter()
    out = certify_clouds(model, camera, cells, occ, layouts, delta, confidence, seed, mode, tolerance, max_depth,
                         at=at, dtype=dtype, tick=tick, float_margin=float_margin)
    if gate is None:
        return out
    t1 = time.perf_counter()
    prep, eps, draws = prepare(model, camera, 0.0, dtype, float_margin), out["eps"], out["layouts"]
    glo, ghi = g.layout_gate(model, prep, np.asarray(cells, np.float64), draws, mode, tick)
    eg = g.eps_delta_gated(eps, glo, gate, delta, confidence)
    out.update(gate=gate, gate_lower=glo, gate_upper=ghi, eps_bar_delta_gated=eg, gate_seconds=time.perf_counter() - t1)
    out["seconds"] = time.perf_counter() - t0
    if at is not None:
        out.update(**g.shares(eps, glo, at, gate), cells_certified_gated=float((eg <= at).mean()))
    return out


def fresh_check(predict, camera, occ, cells, eps_delta, frames: int, seed: int, stream: int = 0) -> dict:
    """Frames at uniform positions of each cell under fresh layouts of the level (the loop's draw): the share whose
    error exceeds the cell's `eps_bar_delta` (to sit under `delta`, up to sampling). Positions and layouts: the
    random stream `(seed, stream)`."""
    rng = np.random.default_rng([seed, 4404, stream])
    p = cell_points(rng, cells, frames)
    imgs = camera.render(p, occlusion=occ, rng=rng)
    e = np.linalg.norm(np.asarray(predict(imgs), np.float64)[:, :2] - p, axis=-1).reshape(len(cells), frames)
    above = e > eps_delta[:, None]
    return {"frames": int(above.size), "above": int(above.sum()), "rate": float(above.mean()),
            "worst_cell_rate": float(above.mean(1).max())}


def region_cells(s, camera, scene) -> np.ndarray:
    """The operational cells of `clouds.region` (at most `clouds.limit` of them, evenly spaced)."""
    arena = tuple((float(lo), float(hi)) for lo, hi in camera.arena)
    cells, _, _, _, op = cells_of(arena, float(s.cell), s.region, scene, operational_margin("auto", camera))
    cells = cells[op]
    if s.limit and len(cells) > int(s.limit):
        cells = cells[np.linspace(0, len(cells) - 1, int(s.limit)).round().astype(int)]
    return cells


def chunk_part(pmap, camera, occ, cells, s, margin: float, stream: int, tick=None) -> shards.Part:
    """One chunk of cells: its table columns and its checks' counts (the random streams `(seed, stream)`; its
    layouts' draw :func:`.clouds.draw_seed`); `tick()` after each layout's bounds (and gate bounds)."""
    r = certify_gated(pmap.model, camera, cells, occ, s.layouts, s.delta, s.confidence,
                      draw_seed(s.seed, s.draw, stream), s.mode, s.tolerance, s.max_depth, at=margin, gate=s.gate,
                      dtype=torch.float64 if s.dtype == "float64" else torch.float32, tick=tick,
                      float_margin=s.float_margin)
    t0 = time.perf_counter()
    bad, worst = sampled_check(pmap.predict, camera, occ, cells, r["lower"], r["upper"], r["layouts"], s.samples,
                               s.seed, stream) if s.samples else (0, None)
    fresh = fresh_check(pmap.predict, camera, occ, cells, r["eps_bar_delta"], s.fresh, s.seed + 1, stream) \
        if s.fresh else {"frames": 0, "above": 0, "worst_cell_rate": None}
    clear = np.flatnonzero(r["layouts"].clear)[:1]
    arrays = {"eps_bar_delta": r["eps_bar_delta"], "share": r["share"], "violation_cp": r["violation_cp"],
              "eps_clear": r["eps"][:, clear[0]] if len(clear) else np.full(len(cells), np.nan)}
    scalars = {"seconds": r["seconds"], "sampled_frames": len(cells) * s.layouts * s.samples,
               "sampled_violations": bad, "sampled_worst": worst, "fresh_frames": fresh["frames"],
               "fresh_above": fresh["above"], "fresh_worst_cell_rate": fresh["worst_cell_rate"]}
    if s.gate is not None:
        arrays.update(eps_bar_delta_gated=r["eps_bar_delta_gated"], flagged_share=r["flagged_share"],
                      undecided_share=r["undecided_share"])
        g_bad, g_worst = g.gate_sampled_check(pmap.predicted_error, camera, occ, cells, r["gate_lower"],
                                              r["gate_upper"], r["layouts"], s.samples, s.seed, stream) \
            if s.samples else (0, None)
        gf = g.gate_fresh_check(pmap.predicted_error, camera, occ, cells, r["eps_bar_delta_gated"], s.gate, s.fresh,
                                s.seed + 1, stream) if s.fresh else {"frames": 0, "above": 0, "dropped": 0.0,
                                                                      "worst_cell_rate": None}
        scalars.update(gate_seconds=r["gate_seconds"], gate_sampled_violations=g_bad, gate_sampled_worst=g_worst,
                       gate_fresh_frames=gf["frames"], gate_fresh_above=gf["above"],
                       gate_fresh_dropped=round(gf["dropped"] * gf["frames"]),
                       gate_fresh_worst_cell_rate=gf["worst_cell_rate"])
    scalars["check_seconds"] = time.perf_counter() - t0
    return arrays, scalars


def run(cfg) -> dict:
    """`python -m pipeline.certify.clouds_cli` (module docstring there): the run after its preflight; returns the
    summary with the output folder under `path` (a shard's run: `{"path": its shard folder, "shard": i}`)."""
    checked = check(cfg)
    s, occ, folder = checked["settings"], checked["occlusion"], checked["folder"]
    torch.set_num_threads(int(s.threads))
    pmap = load_perception_map(folder, device="cpu")
    if s.gate is not None and getattr(pmap.model, "var_head", None) is None:
        raise ConfigError(f"{F}.gate", f"perception map {folder.name} has no uncertainty head (train it with "
                                       "model.uncertainty=gaussian, or gate=null)")
    camera = pmap.camera()
    scene = build(pmap.manifest["scene"], "scene")
    cells = region_cells(s, camera, scene)
    cov = scene.covering(0)
    margin = float(cov.c - cov.obstacle_radius)
    id_ = clouds_id(s.recipe(), pmap.id, pmap.manifest["scene"], camera.arena)
    root = Path(cfg.paths.certified_dir) / "clouds"
    name = f"{pmap.name}_{occ.name}"
    final = root / f"{name}-{id_}"
    if tracking.is_complete(final) and not s.force:
        summary = json.loads((final / "clouds.json").read_text())
        for line in lines(summary):
            print(line)
        print(f"clouds: {final} is complete ({F}.force=true to recompute)")
        return {**summary, "path": final, "skipped": True}
    shards_dir = root / shards.SHARDS_DIR / final.name

    def chunk(a, b, c, bar):  # the bar moves inside a chunk (a heavy chunk is minutes of bounds): each layout's
        per, done = (b - a) / (s.layouts * (1 if s.gate is None else 2)), [0.0, 0]  # pass is this share of its cells

        def tick():
            done[0] += per
            if (whole := int(done[0]) - done[1]) > 0:  # whole cells: the bar counts cells
                bar.update(whole)
                done[1] += whole

        part = chunk_part(pmap, camera, occ, cells[a:b], s, margin, c, tick)
        bar.update((b - a) - done[1])  # the rest once its checks are done
        return part

    part = shards.run_sharded(len(cells), s.chunk, s, shards_dir, "clouds", chunk, REDUCE,
                              f"clouds {occ.name} x {s.layouts} layouts")
    if part is None:
        print(f"clouds: shard {s.shard} of {s.shards} of {final.name} -> {shards_dir} (merge: the same command "
              f"without {F}.shard=)")
        return {"path": shards_dir, "shard": int(s.shard)}
    arrays, sc = part
    summary = report(s, arrays, sc, pmap, occ, cells, folder.name, margin)
    if s.gate is not None:
        summary["gated"] = gated_report(s, arrays, sc, margin)
    meta = {"recipe": s.recipe(), "inputs": {"model": str(pmap.id)}, "model_name": pmap.name,
            "code_version": tracking.code_version(*CERTIFY_CODE)}
    with tracking.tracked_output(root, name, id_, meta) as tmp:
        write(tmp, cells, arrays, summary)
    shutil.rmtree(shards_dir, ignore_errors=True)
    for line in lines(summary):
        print(line)
    print(f"clouds: wrote {final}")
    return {**summary, "path": final, "skipped": False}


def _stats(x: np.ndarray) -> dict:
    return {"median": float(np.median(x)), "p95": float(np.percentile(x, 95, method="higher")), "max": float(x.max())}


def _rate(above: int, frames: int):
    return above / frames if frames else None


def report(s, a: dict, sc: dict, pmap, occ, cells, name: str, margin: float) -> dict:
    """The summary of the ungated run, with its two checks (sampled positions, fresh layouts)."""
    ed = a["eps_bar_delta"]
    settings = {k: v for k, v in s.recipe().items() if k != "gate" or v is not None}  # gate null: as before
    return {"map": name, "occlusion": occ.name, "cells": len(cells), "layouts": s.layouts,
            "k_star": max_exceedances(s.layouts, s.delta, s.confidence), "delta": s.delta,
            "confidence": s.confidence, "c_minus_r": margin,
            "eps_bar_delta": _stats(ed), "cells_eps_delta_below_c_minus_r": float((ed <= margin).mean()),
            "layout_bounds_below_c_minus_r": float(a["share"].mean()),
            "sampled": {"frames": sc["sampled_frames"], "violations": sc["sampled_violations"],
                        "worst_excess": sc["sampled_worst"]},
            "fresh": {"frames": sc["fresh_frames"], "above": sc["fresh_above"],
                      "rate": _rate(sc["fresh_above"], sc["fresh_frames"]),
                      "worst_cell_rate": sc["fresh_worst_cell_rate"]},
            "seconds": sc["seconds"], "check_seconds": sc["check_seconds"],
            "seconds_per_cell_layout": sc["seconds"] / (len(cells) * s.layouts),
            "settings": {**settings, "maps": s.maps}}


def gated_report(s, a: dict, sc: dict, margin: float) -> dict:
    """The gate's block of the summary, with its checks (sampled predicted errors, fresh frames kept)."""
    frames = sc["gate_fresh_frames"]
    return {"gate": s.gate, "eps_bar_delta_gated": _stats(a["eps_bar_delta_gated"]),
            "cells_eps_delta_gated_below_c_minus_r": float((a["eps_bar_delta_gated"] <= margin).mean()),
            "flagged_share": float(a["flagged_share"].mean()), "undecided_share": float(a["undecided_share"].mean()),
            "sampled": {"frames": sc["sampled_frames"], "violations": sc["gate_sampled_violations"],
                        "worst_relative_excess": sc["gate_sampled_worst"]},
            "fresh": {"frames": frames, "above": sc["gate_fresh_above"], "rate": _rate(sc["gate_fresh_above"], frames),
                      "worst_cell_rate": sc["gate_fresh_worst_cell_rate"],
                      "dropped": _rate(sc["gate_fresh_dropped"], frames)},
            "seconds": sc["gate_seconds"]}


def write(out: Path, cells, a: dict, summary: dict) -> None:
    """`table.csv` (one row per cell; the gate's columns with a gate) and `clouds.json` in `out`."""
    out.mkdir(parents=True, exist_ok=True)
    table = np.column_stack([cells, a["eps_bar_delta"], np.full(len(cells), summary["layouts"]), a["share"],
                             a["violation_cp"], a["eps_clear"]])
    header = COLUMNS
    if "gated" in summary:
        table = np.column_stack([table, a["eps_bar_delta_gated"], a["flagged_share"], a["undecided_share"]])
        header += GATED
    np.savetxt(out / "table.csv", table, delimiter=",", comments="", fmt="%.10g", header=header)
    (out / "clouds.json").write_text(json.dumps(summary, indent=2, default=str))


def _pct(x) -> str:
    return "n/a" if x is None else f"{x:.2%}"


def lines(summary: dict) -> list[str]:
    """The summary lines (the gate's second)."""
    e, sm = summary["eps_bar_delta"], summary
    out = [f"clouds: {sm['map']} under {sm['occlusion']}, {sm['cells']} cells x {sm['layouts']} layouts: eps_bar_delta "
           f"(delta {sm['delta']:g}, confidence {sm['confidence']:g}) median {e['median']:.3g}, p95 {e['p95']:.3g}, "
           f"max {e['max']:.3g}; {sm['cells_eps_delta_below_c_minus_r']:.0%} of cells below c - r = "
           f"{sm['c_minus_r']:.3g}; sampled {sm['sampled']['violations']} of {sm['sampled']['frames']} past their "
           f"layout's bound; fresh layouts {_pct(sm['fresh']['rate'])} of {sm['fresh']['frames']} frames above "
           f"eps_bar_delta; {sm['seconds']:.0f} s ({sm['seconds_per_cell_layout'] * 1e3:.0f} ms per cell-layout)"]
    if "gated" in summary:
        gs, ge = summary["gated"], summary["gated"]["eps_bar_delta_gated"]
        out.append(f"gate {gs['gate']:g}: eps_bar_delta_gated median {ge['median']:.3g}, p95 {ge['p95']:.3g}, max "
                   f"{ge['max']:.3g}; {gs['cells_eps_delta_gated_below_c_minus_r']:.0%} of cells below c - r; at "
                   f"c - r the layouts are {gs['flagged_share']:.1%} flagged, {gs['undecided_share']:.1%} undecided; "
                   f"sampled {gs['sampled']['violations']} of {gs['sampled']['frames']} predicted errors past their "
                   f"bounds; fresh layouts {_pct(gs['fresh']['rate'])} of {gs['fresh']['frames']} frames above "
                   f"eps_bar_delta_gated and not dropped ({_pct(gs['fresh']['dropped'])} dropped); "
                   f"{gs['seconds']:.0f} s for the gate")
    return out
