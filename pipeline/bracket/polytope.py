"""Funnels past the free region (docs/bracket.md "Funnels", "Through the guard's range"): where a ball funnel of
:mod:`pipeline.bracket.funnel` ends (the perceived ball comes within the guard's range of the mode's wedge, or
near a push-out), the set of positions goes on as a polytope stepped with the abstraction's own input enclosures.

A run of a start sub-square that passes a back face far from the vertex (the runs from beside `K`) leaves the free
region about `1 + ρ + ε` from the face, where the window's cells under its ball are not all winning: the one-frame
abstraction there forgets where in a cell a run is, and over the few frames to the face its paths drift toward the
vertex by about a fine cell a frame, which no run does. Here the set is kept without cells:

- **The set** `X_k = {x : d_j·x <= h_j}` over the support directions `DIRS` in the abstraction's frame (the faces
  on grid lines), from the ball's support `d_j·g + ρ`. The perceived set `X_k ⊕ B(ε)` lies in `{d_j·x <= h_j + ε}`.
- **The decision keeps the mode** (the hybrid law): the perceived set's bounding box is cut into `n_split²`
  sub-boxes; those meeting it (separating axes over `DIRS`, which hold the boxes' normals) are tested with the
  abstraction's interval decisions (:func:`pipeline.bracket.modes.decisions`); a possible jump ends the funnel.
- **The hand-off** at a frame instant: every cell meeting `X_k` (coarse, or the refined window's fine cells) in
  `Win` in the mode: every run is in a winning node after the frame's decision; the bound `k + max frames`.
- **One frame**: a position perceived in sub-box `M_i` lies in `X_k ∩ (M_i ⊕ B(ε))` and holds an input of `M_i`'s
  flow or push-out piece (:func:`pipeline.bracket.inputs.support` with `parts`, the window's tighter enclosures), so
  `X_{k+1} ⊆ ∪_i (X_k ∩ (M_i ⊕ B(ε))) ⊕ T_s U_i`, whose support over `DIRS` is the largest over the pieces of
  `min(h, h(M_i) + ε) + T_s h(U_i)`; the held segments lie in the same with `max(h(U_i), 0)`, which must miss the
  obstacle's disc (a direction separates them) and stay in the arena. A perceived sub-box holding no input in the
  mode (the law would not hold `q` there) ends the funnel.

Everything is an over-approximation of the runs' positions (H-representations intersect and add soundly), so a
hand-off is a proof for every run of the ball. One obstacle, as the ball funnels; the smooth laws have one mode
and their own input enclosures (the same step, no decision)."""

from __future__ import annotations

import numpy as np

from pipeline.bracket.enclosures import DIRS, split
from pipeline.bracket.inputs import support
from pipeline.bracket.modes import decisions
from pipeline.bracket.refine import box_support
from pipeline.control import HybridController

_AXES = [int(np.argmax(DIRS @ v)) for v in np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])]
TOL = 1e-9
MAX_SIDE = 3.0    # world units: a polytope whose bounding box grows wider ends its funnel (the cells under a wide
#                   set are seldom all winning, and listing them is what costs)
MAX_FRAMES = 60   # frames a polytope may go on without a hand-off (past the face's slide from the vertex to a side one)


def bbox(h: np.ndarray) -> np.ndarray:
    """Bounding boxes `(..., 4)` (`x0, x1, y0, y1`) of polytopes `{d_j·x <= h_j}` `(..., J)`."""
    return np.stack([-h[..., _AXES[1]], h[..., _AXES[0]], -h[..., _AXES[3]], h[..., _AXES[2]]], -1)


def meets(boxes: np.ndarray, h: np.ndarray) -> np.ndarray:
    """`(..., K)`: whether boxes `(..., K, 4)` meet polytopes `(..., J)` (no direction of `DIRS` separates them; the
    boxes' normals are among `DIRS`, so for a box and such a polytope this is exact)."""
    x = np.minimum(boxes[..., 0:1] * DIRS[:, 0], boxes[..., 1:2] * DIRS[:, 0])
    y = np.minimum(boxes[..., 2:3] * DIRS[:, 1], boxes[..., 3:4] * DIRS[:, 1])
    return (x + y <= h[..., None, :] + TOL).all(axis=-1)


def cells_max(grid, h: np.ndarray, vals: np.ndarray, cells: int = 200_000) -> np.ndarray:
    """Per polytope `(N, J)` (grid frame), the largest of `vals` over the cells of `grid` meeting it (inf where its
    bounding box leaves the grid); `cells`: candidate cells per block of polytopes."""
    out = np.full(len(h), np.inf)
    B = bbox(h)
    side = (B[:, [1, 3]] - B[:, [0, 2]]).max() if len(h) else 0.0
    chunk = max(1, cells // int((side / grid.h + 2) ** 2))
    for s in range(0, len(h), chunk):
        hb = h[s:s + chunk]
        B = bbox(hb)
        lo = np.floor((B[:, [0, 2]] - [grid.x0, grid.y0]) / grid.h).astype(np.int64)
        hi = np.floor((B[:, [1, 3]] - [grid.x0, grid.y0]) / grid.h).astype(np.int64)
        over = (lo < 0).any(1) | (hi[:, 0] >= grid.nx) | (hi[:, 1] >= grid.ny)
        w = int((hi - lo).max()) + 1 if len(hb) else 1
        ox, oy = (g.ravel() for g in np.meshgrid(np.arange(w), np.arange(w), indexing="ij"))
        ix, iy = lo[:, :1] + ox, lo[:, 1:] + oy
        inside = (ix <= hi[:, :1]) & (iy <= hi[:, 1:])
        x, y = grid.x0 + ix * grid.h, grid.y0 + iy * grid.h
        boxes = np.stack([x, x + grid.h, y, y + grid.h], -1)
        hit = inside & meets(boxes, hb)
        idx = np.clip(ix, 0, grid.nx - 1) * grid.ny + np.clip(iy, 0, grid.ny - 1)
        v = np.where(hit, vals[idx], -np.inf).max(axis=1)
        out[s:s + chunk] = np.where(over, np.inf, v)
    return out


def step(rlaw, h: np.ndarray, eps: np.ndarray, q: int, period: float, n_split: int, hybrid: bool = True):
    """One frame from polytopes `h` `(A, J)` in mode `q` of `rlaw` (the law in the abstraction's frame) with errors
    within `eps` `(A,)`: `(next, swept, jump, unheld)`: the next polytopes and the held segments' (support over
    `DIRS`; the frame's decision kept `q`), whether a perceived sub-box may jump the mode, and whether one holds no
    input in mode `q` (module docstring)."""
    hm = h + eps[:, None]
    subs = split(bbox(hm), n_split)  # (A, S, 4)
    meet = meets(subs, hm)
    jump = np.zeros(len(h), bool)
    if hybrid:
        jump = (decisions(rlaw, subs.reshape(-1, 4))[1][:, q - 1].reshape(meet.shape) & meet).any(axis=1)
    rows, si = np.nonzero(meet)
    U = support(rlaw, subs[rows, si], q, period, 1, parts=True)[0]  # (K, pieces, J): the flow and the push-out
    live = np.isfinite(U).all(axis=-1)
    unheld = np.zeros(len(h), bool)
    np.logical_or.at(unheld, rows, ~live.any(axis=1))
    pos = np.minimum(box_support(subs[rows, si]) + eps[rows, None], h[rows])  # X ∩ (M_i ⊕ B(ε))
    nxt, swept = np.full_like(h, -np.inf), np.full_like(h, -np.inf)
    for p in range(U.shape[1]):
        m = live[:, p]
        group_max(nxt, rows[m], pos[m] + period * U[m, p])
        group_max(swept, rows[m], pos[m] + period * np.maximum(U[m, p], 0.0))
    return nxt, swept, jump, unheld


def group_max(out: np.ndarray, rows: np.ndarray, vals: np.ndarray) -> None:
    """`np.maximum.at(out, rows, vals)` for ascending `rows` (as `np.nonzero` gives them): one `reduceat` per run of
    equal rows (the same values; `ufunc.at` was a fifth of a polytope step)."""
    if len(rows) == 0:
        return
    first = np.flatnonzero(np.r_[True, rows[1:] != rows[:-1]])
    at = rows[first]
    out[at] = np.maximum(out[at], np.maximum.reduceat(vals, first, axis=0))


def polytope_funnels(cert, law, centres: np.ndarray, rads: np.ndarray, start: np.ndarray, q: int, period: float,
                     horizon: float, n_split: int = 16, all_or_nothing: bool = False) -> np.ndarray:
    """Per ball `B(centres_i, rads_i)` (world) holding the runs at frame `start_i` in mode `q` before that frame's
    decision (where a ball funnel leaves the free region): the arrival bound in frames through the polytope funnel
    (module docstring; inf where none hands off within the horizon). `all_or_nothing`: stop at the first funnel
    that fails (the caller needs them all: a start cell)."""
    n = len(centres)
    best = np.full(n, np.inf)
    view = cert.frame.view_bounds(law.scene.bounds)
    if n == 0 or view is None:  # an arena not on the support directions: not modelled here
        return best
    rlaw = cert.frame.law(law)
    hybrid = isinstance(law, HybridController)
    cov = rlaw.scene.covering(0)
    h = cert.frame.to_grid(np.asarray(centres, float)) @ DIRS.T + np.asarray(rads, float)[:, None]
    k = np.asarray(start, float).copy()
    last = k + MAX_FRAMES
    node_frames = np.where(cert.won, cert.node_frames, np.inf).reshape(-1, cert.abstraction.modes)[:, q - 1]
    fine = cert.fine
    alive = np.arange(n)
    disc = DIRS @ cov.p_0 - cov.obstacle_radius  # a direction with d·x <= disc_j misses the disc's every point
    while alive.size:
        ha, ka = h[alive], k[alive]
        eps = cells_max(cert.grid, ha, cert.eps_cells)
        hand = cells_max(cert.grid, ha, node_frames)
        if fine is not None:
            hand = np.minimum(hand, cells_max(fine.grid, ha, fine.frames[:, q - 1]))
        known = np.isfinite(eps)
        nxt, swept, jump, unheld = step(rlaw, ha, np.where(known, eps, 0.0), q, period, n_split, hybrid)
        bad = ~known | jump | unheld  # the mode after this frame's decision might not be q: no hand-off either
        won = ~bad & np.isfinite(hand) & (ka + hand <= horizon)
        best[alive[won]] = ka[won] + hand[won]
        clear = (disc > swept + TOL).any(axis=1) & (swept <= view + TOL).all(axis=1)
        B = bbox(nxt)
        narrow = np.isfinite(nxt).all(axis=1) & ((B[:, [1, 3]] - B[:, [0, 2]]).max(axis=1) <= MAX_SIDE)
        keep = ~bad & ~won & clear & narrow & (ka + 1 < np.minimum(horizon, last[alive]))
        if all_or_nothing and (~won & ~keep).any():
            return np.full(n, np.inf)
        h[alive[keep]], k[alive[keep]] = nxt[keep], ka[keep] + 1
        alive = alive[keep]
    return np.where(best <= horizon, best, np.inf)
