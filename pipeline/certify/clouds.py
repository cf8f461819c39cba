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

import math
import time
from dataclasses import dataclass

import cv2
import numpy as np
import torch

from pipeline.certify.bounds import Prepared, prepare
from pipeline.certify.cone import MARGIN
from pipeline.certify.deployed import static_pass
from pipeline.certify.renderer import PixelWindow
from pipeline.certify.split import certify_cells, eps_of
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
    return Prepared(prep.net, static_pass(prep.net, bg), prep.camera, 0.0, win, prep.float_margin)


def over_layouts(prep: Prepared, layouts: Layouts, bound, shape: tuple[int, ...], tick=None):
    """`bound(prepared under one layout) -> (lo, hi)` for every layout, as `lower, upper (C, L, ...)` (`shape`:
    `(C, ...)`); clear layouts share the clean bound, computed once. `tick()` after each layout (progress)."""
    table = torch.as_tensor(apply_table())
    lower, upper = (np.empty((shape[0], len(layouts), *shape[1:])) for _ in range(2))
    clean = None
    with torch.no_grad():
        for j in range(len(layouts)):
            if layouts.clear[j] and clean is not None:
                lower[:, j], upper[:, j] = clean
            else:
                lo, hi = bound(layout_prep(prep, layouts, j, table))
                lower[:, j], upper[:, j] = lo, hi
                if layouts.clear[j]:
                    clean = (lo, hi)
            if tick is not None:
                tick()
    return lower, upper


def layout_bounds(prep: Prepared, cells: np.ndarray, layouts: Layouts, mode: str = "crown",
                  tolerance: float = np.inf, max_depth: int = 0, batch: int = 1024, tick=None):
    """`eps_bar(P, layout)` for every cell and layout: `eps (C, L)`, per-coordinate `lower, upper (C, L, 2)` (the
    stage's :func:`.split.certify_cells` on each layout; clear layouts share the clean bound, computed once)."""
    lower, upper = over_layouts(prep, layouts, lambda p: certify_cells(p, cells, mode, tolerance, max_depth, batch,
                                                                       progress=False)[:2], (len(cells), 2), tick)
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


def draw_seed(seed: int, draw: str, stream: int) -> int | list[int]:
    """The layouts' seed of chunk `stream`: `seed` itself when every chunk shares one draw (`draw="shared"`), the
    chunk's own stream `[seed, 4407, stream]` otherwise (`"per_chunk"`: the chunks' draws are independent, so one
    unlucky draw is one chunk's, not every cell's; docs/certify.md "Under clouds")."""
    return int(seed) if draw == "shared" else [int(seed), 4407, int(stream)]


def cell_points(rng: np.random.Generator, cells: np.ndarray, k: int) -> np.ndarray:
    """`k` uniform positions in each cell `(C, 4)` (`x0, x1, y0, y1`), cell by cell: `(C * k, 2)`."""
    t = rng.uniform(size=(len(cells), k, 2))
    return np.stack([cells[:, None, 0] + t[..., 0] * (cells[:, None, 1] - cells[:, None, 0]),
                     cells[:, None, 2] + t[..., 1] * (cells[:, None, 3] - cells[:, None, 2])], -1).reshape(-1, 2)


def sampled_check(predict, camera, occ: Occlusion, cells: np.ndarray, lower, upper, layouts: Layouts,
                  samples: int, seed: int = 0, stream: int = 0):
    """Positions drawn in each cell, rendered by the camera with each layout (`Camera.render(occlusion, clouds)`,
    the loop's path): how many errors leave the layout's per-coordinate bound, and the largest excess. The
    positions: the random stream `(seed, stream)` (the app draws one per chunk of cells)."""
    rng = np.random.default_rng([seed, 44, stream])
    bad, worst = 0, -np.inf
    for j in range(len(layouts)):
        p = cell_points(rng, cells, samples)
        cl = layouts.clouds[np.full(len(p), j)]
        e = np.asarray(predict(camera.render(p, occlusion=occ, clouds=cl)), np.float64)[:, :2] - p
        e = e.reshape(len(cells), samples, 2)
        excess = np.maximum(lower[:, j, None] - e, e - upper[:, j, None]).max(-1)
        bad, worst = bad + int((excess > 0).sum()), max(worst, float(excess.max()))
    return bad, worst


def certify_clouds(model, camera, cells: np.ndarray, occ: Occlusion, layouts: int = 299, delta: float = 0.01,
                   confidence: float = 0.95, seed: int | list[int] = 0, mode: str = "crown", tolerance: float = np.inf,
                   max_depth: int = 0, batch: int = 1024, at: float | None = None, dtype=torch.float32,
                   tick=None, float_margin: float = 0.0) -> dict:
    """The table under clouds (Hydra-free): per cell `eps_bar_delta`, the layouts, the certified share at `at`
    (`c - r`, say), the clean bound; and the cost. Layouts: `occ.sample(layouts, default_rng(seed))` (`seed` an
    int or a seed sequence: the app draws per chunk of cells, `[clouds.seed, 4407, chunk]`, `draw_seed`). The gate's
    columns: :func:`pipeline.certify.clouds_run.certify_gated`. `tick()` after each layout's bounds;
    `float_margin`: :attr:`.bounds.Prepared.float_margin`."""
    t0 = time.perf_counter()
    prep = prepare(model, camera, 0.0, dtype, float_margin)
    draws = layout_maps(occ, occ.sample(layouts, np.random.default_rng(seed), camera.shape), camera.background)
    eps, lower, upper = layout_bounds(prep, np.asarray(cells, np.float64), draws, mode, tolerance, max_depth, batch,
                                      tick)
    ed = eps_delta(eps, delta, confidence)
    out = {"cells": np.asarray(cells), "eps": eps, "lower": lower, "upper": upper, "layouts": draws,
           "eps_bar_delta": ed, "n_layouts": layouts, "k_star": max_exceedances(layouts, delta, confidence),
           "delta": delta, "confidence": confidence, "seconds": time.perf_counter() - t0}
    if at is not None:
        out.update(at=at, **certified_share(eps, at, confidence), cells_certified=float((ed <= at).mean()))
    return out
