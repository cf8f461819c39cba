"""Perception certified under clouds (issue 44): sound in the position for one layout, a probability over layouts.

**One layout: sound.** :meth:`pipeline.render.Occlusion.apply` blends a layout (one bank field at one cyclic shift)
over the rendered image, robot included (the robot is drawn *under* the cloud), per pixel and channel:
`out = round(img (255 - a) / 255) + tint`, with `a` the field's opacity (uint8) and `tint = round(a colour / 255)`
(OpenCV's uint8 multiply by `1/255`, then a saturating add that never saturates: `out <= 255 - a + a`). That is an
affine map of the clean pixel with weight `w = (255 - a) / 255 >= 0`, so the renderer's linear bounds `lo <= img <=
hi` (:mod:`.renderer`) give `w lo + tint - r <= out <= w hi + tint + r`, with the apply's own rounding `r = 0.5`
where `0 < a < 255` (`a = 0`: `out = img`; `a = 255`: `out = tint`), and the exact value where the clean pixel is
known exactly (a static pixel of the window). Outside the window the image is the static image under the layout,
computed by `apply` itself. :func:`layout_bound` is then the unchanged bound (:func:`.bounds.certified_error_bound`,
CROWN/IBP through the folded network, adaptive splitting) on those pixels: `eps_bar(P, layout)` holds for every
position of the cell `P` and every frame rendered there with that layout.

**Over layouts: a probability.** Layouts drawn from the level's own process (:meth:`Occlusion.sample`: the
`probability` of clouds included), i.i.d., `N` of them, bounded per cell: `eps_bar_delta(P)` (:func:`eps_delta`)
is the `(k*+1)`-th largest of the `N` bounds, `k*` the most exceedances whose exact binomial (Clopper-Pearson)
upper bound at confidence `1 - beta` is `<= delta`. The order statistic of i.i.d. draws makes this exact: for
`E = X_(N-k)`, `Pr[Pr_L(eps_bar(P, L) > E) > delta] <= Pr[Bin(N, delta) <= k] <= beta` (ties included). So with
confidence `1 - beta`, a frame at any position of `P` under a fresh layout is within `eps_bar_delta(P)` with
probability `>= 1 - delta` (the layout is drawn independently of the position, as in the loop). `N >= 299` is
needed for `delta = 0.01` at 95% (`k* = 0`: the largest of the `N` bounds).

Layouts are shared by every cell (a layout's static pass once, then all cells batched as the stage batches them);
a clear layout (no cloud drawn) is the clean bound, computed once. With a gate (`camera.gate`'s value), the map's
predicted error is bounded over the same cells and layouts (:mod:`.gate`): a layout where every frame is dropped
(flagged) is no violation, and `eps_bar_delta_gated` counts only the layouts neither certified nor flagged. Not
covered yet: `kappa > 0` under clouds, pose maps' heading under clouds (the position bound is computed).
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import torch

from pipeline.certify.bounds import Prepared, prepare
from pipeline.certify.clouds_cli import F, check
from pipeline.certify.cone import MARGIN
from pipeline.certify.deployed import static_pass
from pipeline.certify.renderer import PixelWindow
from pipeline.certify.split import certify_cells, eps_of
from pipeline.certify.stage import cells_of
from pipeline.config import build
from pipeline.errormap.analysis import operational_margin
from pipeline.errors import ConfigError
from pipeline.perception.maps import load_perception_map
from pipeline.render.occlusion import CloudSample, Occlusion

ROUNDING = 0.5  # the apply's uint8 rounding of `img (255 - a) / 255` (checked exhaustively in the tests)


def apply_table() -> np.ndarray:
    """`round(img (255 - a) / 255)` as `Occlusion.apply` computes it (OpenCV), for every `(img, a)`: `(256, 256)`."""
    img = np.repeat(np.arange(256, dtype=np.uint8), 256).reshape(256, 256, 1).repeat(3, -1)
    a = np.tile(np.arange(256, dtype=np.uint8), 256).reshape(256, 256, 1).repeat(3, -1)
    return cv2.multiply(img, cv2.bitwise_not(a), scale=1 / 255)[..., 0].astype(np.float64)


@dataclass
class Layouts:
    """Cloud layouts as per-pixel maps: opacity `alpha (L, H, W)` and `tint (L, H, W, 3)` (uint8, what `apply`
    adds), `clear (L,)`: no cloud drawn (the clean image), `static (L, H, W, 3)`: the camera's static image under
    each (by `apply` itself), and the draws they came from."""

    alpha: np.ndarray
    tint: np.ndarray
    clear: np.ndarray
    static: np.ndarray
    clouds: CloudSample

    def __len__(self) -> int:
        return len(self.clear)


def layout_maps(occ: Occlusion, clouds: CloudSample, background: np.ndarray) -> Layouts:
    """What `occ.apply` does to an image `(H, W, 3)` under each layout of `clouds`, read from `apply` itself: on a
    black image it leaves the tint, on a white one `255 - a + tint` (exact: `255 (255 - a) / 255` rounds to
    `255 - a`); and `background` under each layout."""
    n, (h, w) = len(clouds), background.shape[:2]
    black, white = np.zeros((n, h, w, 3), np.uint8), np.full((n, h, w, 3), 255, np.uint8)
    static = np.repeat(np.asarray(background, np.uint8)[None], n, 0)
    for img in (black, white, static):
        occ.apply(img, clouds)
    alpha = 255 - (white.astype(np.int64) - black)
    if np.any(alpha != alpha[..., :1]) or alpha.min() < 0:
        raise AssertionError("Occlusion.apply is not the per-pixel blend this bound assumes")
    clear = ~(np.asarray(clouds.mask, bool) & occ.active)
    return Layouts(alpha[..., 0].astype(np.uint8), black, clear, static, clouds)


def cloud_window(pw: PixelWindow, alpha: torch.Tensor, tint: torch.Tensor, table: torch.Tensor) -> PixelWindow:
    """The renderer's window `pw` under per-item layouts: `alpha (N, H, W)`, `tint (N, H, W, 3)` (one per cell of
    the batch; see the module doc). Pixels outside the image (the zero padding) stay zero."""
    n, _, _, kr, kc = pw.lo.shape
    h, w = alpha.shape[-2:]
    rows = (pw.origin[:, 0, None] + torch.arange(kr)).clamp(-MARGIN, h + MARGIN - 1)
    cols = (pw.origin[:, 1, None] + torch.arange(kc)).clamp(-MARGIN, w + MARGIN - 1)
    inside = ((rows >= 0) & (rows < h))[:, :, None] & ((cols >= 0) & (cols < w))[:, None, :]  # (N, Kr, Kc)
    idx = torch.arange(n)[:, None, None]
    r, c = rows.clamp(0, h - 1)[:, :, None], cols.clamp(0, w - 1)[:, None, :]
    a = torch.where(inside, alpha[idx, r, c].to(torch.float64), 0.0)[:, None]  # (N, 1, Kr, Kc): level
    b = torch.where(inside[..., None], tint[idx, r, c].to(torch.float64), 0.0).permute(0, 3, 1, 2)  # (N, 3, Kr, Kc)
    weight = ((255.0 - a) / 255.0)[:, None]  # (N, 1, 1, Kr, Kc): on every slot
    slack = ROUNDING * ((a > 0) & (a < 255)).to(torch.float64)
    lo, hi = pw.lo * weight, pw.hi * weight
    lo[:, 0] += b - slack
    hi[:, 0] += b + slack
    # a pixel the clean image fixes exactly (a static pixel of the window): the apply's exact output
    v = pw.lo[:, 0]
    exact = (pw.lo == pw.hi).all(1) & (pw.lo[:, 1:] == 0).all(1) & (v == v.round()) & (v >= 0) & (v <= 255)
    known = table[v.clamp(0, 255).long(), a.expand_as(v).long()] + b
    lo[:, 0] = torch.where(exact, known, lo[:, 0])
    hi[:, 0] = torch.where(exact, known, hi[:, 0])
    lo[:, 1:] = torch.where(exact[:, None], 0.0, lo[:, 1:])
    hi[:, 1:] = torch.where(exact[:, None], 0.0, hi[:, 1:])
    return PixelWindow(pw.origin, lo, hi)


def layout_prep(prep: Prepared, layouts: Layouts, j: int, table: torch.Tensor | None = None) -> Prepared:
    """`prep` (kappa 0) under layout `j`: its static image under the layout (the camera's static image through
    `apply`), and the renderer's window mapped by :func:`cloud_window`."""
    if prep.kappa != 0:
        raise ValueError("the bound under clouds covers kappa = 0 (a pixel attack under clouds is not covered)")
    if layouts.clear[j]:
        return prep
    table = torch.as_tensor(apply_table()) if table is None else table
    alpha, tint = torch.as_tensor(layouts.alpha[j]), torch.as_tensor(layouts.tint[j])
    win = lambda pw: cloud_window(pw, alpha.expand(len(pw.origin), *alpha.shape),  # noqa: E731
                                  tint.expand(len(pw.origin), *tint.shape), table)
    bg = torch.as_tensor(layouts.static[j], device=prep.net.head_w.device)
    return Prepared(prep.net, static_pass(prep.net, bg), prep.camera, 0.0, win)


def layout_bounds(prep: Prepared, cells: np.ndarray, layouts: Layouts, mode: str = "crown",
                  tolerance: float = np.inf, max_depth: int = 0, batch: int = 1024):
    """`eps_bar(P, layout)` for every cell and layout: `eps (C, L)`, per-coordinate `lower, upper (C, L, 2)` (the
    stage's :func:`.split.certify_cells` on each layout; clear layouts share the clean bound, computed once)."""
    table = torch.as_tensor(apply_table())
    lower, upper = np.empty((len(cells), len(layouts), 2)), np.empty((len(cells), len(layouts), 2))
    clean = None
    with torch.no_grad():
        for j in range(len(layouts)):
            if layouts.clear[j] and clean is not None:
                lower[:, j], upper[:, j] = clean
                continue
            lo, hi = certify_cells(layout_prep(prep, layouts, j, table), cells, mode, tolerance, max_depth, batch,
                                   progress=False)[:2]
            lower[:, j], upper[:, j] = lo, hi
            if layouts.clear[j]:
                clean = (lo, hi)
    return eps_of(lower, upper), lower, upper


def binom_cdf(k, n: int, p) -> np.ndarray:
    """`Pr[Bin(n, p) <= k]`, exact up to float64 (log-space sum of the terms), broadcast over `k` and `p`."""
    k, p = np.broadcast_arrays(np.asarray(k, np.float64), np.asarray(p, np.float64))
    i = np.arange(n + 1, dtype=np.float64)
    logc = np.array([math.lgamma(n + 1) - math.lgamma(j + 1) - math.lgamma(n - j + 1) for j in range(n + 1)])
    with np.errstate(divide="ignore", invalid="ignore"):
        lp, lq = np.log(p)[..., None], np.log1p(-p)[..., None]
        terms = logc + np.where(i > 0, i * lp, 0.0) + np.where(i < n, (n - i) * lq, 0.0)
    terms = np.where(i <= k[..., None], terms, -np.inf)
    top = terms.max(-1, keepdims=True)
    return np.minimum(1.0, np.exp(top[..., 0]) * np.exp(terms - top).sum(-1))


def cp_upper(k, n: int, confidence: float) -> np.ndarray:
    """The exact one-sided binomial (Clopper-Pearson) upper bound on a probability at `confidence`, from `k`
    occurrences in `n` trials: the `p` with `Pr[Bin(n, p) <= k] = 1 - confidence` (the beta quantile
    `B^-1(confidence; k + 1, n - k)`), by bisection (no scipy in the project), rounded up; 1 when `k >= n`."""
    k = np.asarray(k, np.float64)
    lo, hi = np.zeros_like(k), np.ones_like(k)
    for _ in range(64):  # Pr[Bin(n, p) <= k] decreases in p
        mid = (lo + hi) / 2
        above = binom_cdf(k, n, mid) > 1 - confidence
        lo, hi = np.where(above, mid, lo), np.where(above, hi, mid)
    return np.where(k >= n, 1.0, hi)


def max_exceedances(n: int, delta: float, confidence: float) -> int:
    """`k*`: the most of `n` layouts that may exceed `eps` with the CP upper bound still `<= delta` (-1: none,
    `n` too small)."""
    ok = np.flatnonzero(cp_upper(np.arange(n + 1), n, confidence) <= delta)
    return int(ok.max()) if ok.size else -1


def eps_delta(eps: np.ndarray, delta: float = 0.01, confidence: float = 0.95) -> np.ndarray:
    """`eps_bar_delta (C,)` from the bounds `eps (C, N)` of `N` i.i.d. layouts: the smallest `e` with the CP bound
    on `Pr(eps_bar(P, layout) > e)` `<= delta` at `confidence` (inf when `N` is too small for `delta`)."""
    n = eps.shape[1]
    k = max_exceedances(n, delta, confidence)
    if k < 0:
        return np.full(len(eps), np.inf)
    return -np.sort(-eps, axis=1)[:, k]  # the (k+1)-th largest: at most k strictly above it


def certified_share(eps: np.ndarray, at: float, confidence: float = 0.95) -> dict:
    """At `eps = at`: per cell the share of layouts certified and the CP upper bound on the violation probability
    (`(C,)` each)."""
    k = (eps > at).sum(1)
    return {"share": 1 - k / eps.shape[1], "violation_cp": cp_upper(k, eps.shape[1], confidence)}


def sampled_check(predict, camera, occ: Occlusion, cells: np.ndarray, lower, upper, layouts: Layouts,
                  samples: int, seed: int = 0):
    """Positions drawn in each cell, rendered by the camera with each layout (`Camera.render(occlusion, clouds)`,
    the loop's path): how many errors leave the layout's per-coordinate bound, and the largest excess."""
    rng = np.random.default_rng([seed, 44])
    bad, worst = 0, -np.inf
    for j in range(len(layouts)):
        t = rng.uniform(size=(len(cells), samples, 2))
        p = np.stack([cells[:, None, 0] + t[..., 0] * (cells[:, None, 1] - cells[:, None, 0]),
                      cells[:, None, 2] + t[..., 1] * (cells[:, None, 3] - cells[:, None, 2])], -1).reshape(-1, 2)
        cl = layouts.clouds[np.full(len(p), j)]
        e = np.asarray(predict(camera.render(p, occlusion=occ, clouds=cl)), np.float64)[:, :2] - p
        e = e.reshape(len(cells), samples, 2)
        excess = np.maximum(lower[:, j, None] - e, e - upper[:, j, None]).max(-1)
        bad, worst = bad + int((excess > 0).sum()), max(worst, float(excess.max()))
    return bad, worst


def certify_clouds(model, camera, cells: np.ndarray, occ: Occlusion, layouts: int = 299, delta: float = 0.01,
                   confidence: float = 0.95, seed: int = 0, mode: str = "crown", tolerance: float = np.inf,
                   max_depth: int = 0, batch: int = 1024, at: float | None = None, dtype=torch.float32,
                   gate: float | None = None) -> dict:
    """The table under clouds (Hydra-free): per cell `eps_bar_delta`, the layouts, the certified share at `at`
    (`c - r`, say), the clean bound; and the cost. Layouts: `occ.sample(layouts, default_rng(seed))`. With a
    `gate` (a map with an uncertainty head): the gate statistic's bounds `gate_lower, gate_upper (C, L)`,
    `eps_bar_delta_gated` and (with `at`) the flagged and undecided shares (:mod:`.gate`)."""
    t0 = time.perf_counter()
    prep = prepare(model, camera, 0.0, dtype)
    draws = layout_maps(occ, occ.sample(layouts, np.random.default_rng(seed), camera.shape), camera.background)
    eps, lower, upper = layout_bounds(prep, np.asarray(cells, np.float64), draws, mode, tolerance, max_depth, batch)
    ed = eps_delta(eps, delta, confidence)
    out = {"cells": np.asarray(cells), "eps": eps, "lower": lower, "upper": upper, "layouts": draws,
           "eps_bar_delta": ed, "n_layouts": layouts, "k_star": max_exceedances(layouts, delta, confidence),
           "delta": delta, "confidence": confidence, "seconds": time.perf_counter() - t0}
    if at is not None:
        out.update(at=at, **certified_share(eps, at, confidence), cells_certified=float((ed <= at).mean()))
    if gate is not None:
        from pipeline.certify import gate as g

        t1 = time.perf_counter()
        glo, ghi = g.layout_gate(model, prep, np.asarray(cells, np.float64), draws, mode)
        eg = g.eps_delta_gated(eps, glo, gate, delta, confidence)
        out.update(gate=gate, gate_lower=glo, gate_upper=ghi, eps_bar_delta_gated=eg,
                   gate_seconds=time.perf_counter() - t1)
        out["seconds"] = time.perf_counter() - t0
        if at is not None:
            out.update(**g.shares(eps, glo, at, gate), cells_certified_gated=float((eg <= at).mean()))
    return out


# ------------------------------------------------------------------------ the app's run (clouds_cli: its check)
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


def run(cfg) -> dict:
    """`python -m pipeline.certify.clouds_cli` (module docstring there): the run after its preflight."""
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
    gate = s.get("gate")
    if gate is not None and getattr(pmap.model, "var_head", None) is None:
        raise ConfigError(f"{F}.gate", f"perception map {folder.name} has no uncertainty head (train it with "
                                       "model.uncertainty=gaussian, or gate=null)")
    r = certify_clouds(pmap.model, camera, cells, occ, int(s["layouts"]), float(s["delta"]), float(s["confidence"]),
                       int(s["seed"]), s["mode"], float(s["tolerance"]), int(s["max_depth"]), at=margin,
                       gate=None if gate is None else float(gate))
    t0 = time.perf_counter()
    bad, worst = sampled_check(pmap.predict, camera, occ, cells, r["lower"], r["upper"], r["layouts"],
                               int(s["samples"]), int(s["seed"])) if s["samples"] else (0, None)
    fresh = fresh_check(pmap.predict, camera, occ, cells, r["eps_bar_delta"], int(s["fresh"]), int(s["seed"]) + 1)
    if gate is not None:
        from pipeline.certify.gate import gate_fresh_check, gate_sampled_check

        g_bad, g_worst = gate_sampled_check(pmap.predicted_error, camera, occ, cells, r["gate_lower"],
                                            r["gate_upper"], r["layouts"], int(s["samples"]), int(s["seed"])) \
            if s["samples"] else (0, None)
        g_fresh = gate_fresh_check(pmap.predicted_error, camera, occ, cells, r["eps_bar_delta_gated"], r["gate"],
                                   int(s["fresh"]), int(s["seed"]) + 1)
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
               "seconds_per_cell_layout": r["seconds"] / (len(cells) * r["n_layouts"]),
               "settings": {k: v for k, v in s.items() if k != "gate" or v is not None}}  # gate null: as before
    out = Path(cfg.paths.output_dir)
    out.mkdir(parents=True, exist_ok=True)
    table = np.column_stack([cells, ed, np.full(len(cells), r["n_layouts"]), r["share"], r["violation_cp"],
                             np.full(len(cells), np.nan) if clean is None else clean[:, 0]])
    np.savetxt(out / "table.csv", table, delimiter=",", comments="", fmt="%.10g",
               header="x0,x1,y0,y1,eps_bar_delta,n_layouts,share_certified_at_c_minus_r,violation_cp,eps_clear")
    if gate is not None:
        eg = r["eps_bar_delta_gated"]
        summary["gated"] = {"gate": r["gate"], "eps_bar_delta_gated": {
            "median": float(np.median(eg)), "p95": float(np.percentile(eg, 95, method="higher")), "max": float(eg.max())},
            "cells_eps_delta_gated_below_c_minus_r": r["cells_certified_gated"],
            "flagged_share": float(r["flagged_share"].mean()), "undecided_share": float(r["undecided_share"].mean()),
            "sampled": {"frames": len(cells) * len(r["layouts"]) * int(s["samples"]), "violations": g_bad,
                        "worst_relative_excess": g_worst},
            "fresh": g_fresh, "seconds": r["gate_seconds"]}
        table = np.column_stack([table, eg, r["flagged_share"], r["undecided_share"]])
        np.savetxt(out / "table.csv", table, delimiter=",", comments="", fmt="%.10g",
                   header="x0,x1,y0,y1,eps_bar_delta,n_layouts,share_certified_at_c_minus_r,violation_cp,eps_clear,"
                          "eps_bar_delta_gated,flagged_share,undecided_share")
    (out / "clouds.json").write_text(json.dumps(summary, indent=2, default=str))
    print(f"clouds: {folder.name} under {occ.name}, {len(cells)} cells x {r['n_layouts']} layouts: eps_bar_delta "
          f"(delta {r['delta']:g}, confidence {r['confidence']:g}) median {np.median(ed):.3g}, p95 "
          f"{np.percentile(ed, 95, method='higher'):.3g}, max {ed.max():.3g}; {r['cells_certified']:.0%} of cells below c - r = "
          f"{margin:.3g}; sampled {bad} of {summary['sampled']['frames']} past their layout's bound; fresh layouts "
          f"{fresh['rate']:.2%} of {fresh['frames']} frames above eps_bar_delta; {r['seconds']:.0f} s "
          f"({summary['seconds_per_cell_layout'] * 1e3:.0f} ms per cell-layout)")
    if gate is not None:
        gs = summary["gated"]
        print(f"gate {gate:g}: eps_bar_delta_gated median {gs['eps_bar_delta_gated']['median']:.3g}, p95 "
              f"{gs['eps_bar_delta_gated']['p95']:.3g}, max {gs['eps_bar_delta_gated']['max']:.3g}; "
              f"{gs['cells_eps_delta_gated_below_c_minus_r']:.0%} of cells below c - r; at c - r the layouts are "
              f"{gs['flagged_share']:.1%} flagged, {gs['undecided_share']:.1%} undecided; sampled {g_bad} of "
              f"{gs['sampled']['frames']} predicted errors past their bounds; fresh layouts "
              f"{g_fresh['rate']:.2%} of {g_fresh['frames']} frames above eps_bar_delta_gated and not dropped "
              f"({g_fresh['dropped']:.1%} dropped); {r['gate_seconds']:.0f} s for the gate")
    return summary
