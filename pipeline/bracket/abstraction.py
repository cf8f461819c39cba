"""The finite abstraction of the sampled loop and its reach-avoid certificate (SPEC §5.4).

Nodes `(P, q)`: at a frame instant (after the frame's jump decision) the true position is in the cell `P` and the
mode is `q` (one mode for the smooth laws). The held input is `hold(F_q(m))` for a perceived `m` in `P ⊕ ε̄(P)`
(a box: `ε̄(P)` the largest error bound on `P`), so it lies in the polytope `U(P, q)` of
:mod:`pipeline.bracket.inputs`. One frame later the position is in `E = P ⊕ T_s U` (the endpoint set) and the
segment in between in `S = P ⊕ conv(0, T_s U)` (the swept set). Edges over frames, not faces: `(P, q) -> (P', q')`
for every cell `P'` meeting `E` and every mode `q'` the next frame's decision allows on `P' ⊕ ε̄(P')` (interval
bounds of `V_1, V_2` against the hysteresis `χ - λ`).

Goal: cells inside `B(p_T, δ_c)`. A node is unsafe when a cell meeting `S` meets the obstacle disc or lies outside
the arena (the camera's view), `S` may leave the arena (a cell straddling its edge holds positions on its part
inside, `P ∩ A`), or `E` spans more than `window` cells per axis. `Win` is the least fixed point
`goal ∪ {n safe: every successor in Win}`, with the transience rule: a strongly connected set of nodes outside the
goal counts as transient when along every input of every node in it a fixed direction `d_j·p` or `|p - p_T|²`
strictly decreases over a frame (`Tarjan` emits the sets sinks first, so one pass in that order is the fixed
point). A start cell is certified when every initial node it can have (the initial mode and frame 0's decision
over `P ⊕ ε̄`) is in `Win`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.bracket.enclosures import DIRS, dist_range
from pipeline.bracket.modes import Modes

TOUCH = 1e-9  # world units: a set reaching a cell by less than this does not meet it (rounding of exact zeros)
HITS_CHUNK = 2048  # candidate (set, cell) pairs per block of `cell_hits` (a few hundred kB: in the cache)


@dataclass(frozen=True)
class Grid:
    """Square cells of side `h` from `(x0, y0)`: `nx x ny` cells, cell `i = ix * ny + iy`."""

    x0: float
    y0: float
    h: float
    nx: int
    ny: int

    @classmethod
    def over(cls, bounds, h: float, anchor=None) -> Grid:
        """Cells covering `bounds`; with `anchor` (a point) its coordinates are grid lines."""
        (x0, x1), (y0, y1) = bounds
        if anchor is not None:
            x0 = anchor[0] - h * math.ceil((anchor[0] - x0) / h - 1e-9)
            y0 = anchor[1] - h * math.ceil((anchor[1] - y0) / h - 1e-9)
        return cls(x0, y0, h, int(math.ceil((x1 - x0) / h - 1e-9)), int(math.ceil((y1 - y0) / h - 1e-9)))

    @property
    def n(self) -> int:
        return self.nx * self.ny

    def boxes(self) -> np.ndarray:
        ix, iy = np.divmod(np.arange(self.n), self.ny)
        x, y = self.x0 + ix * self.h, self.y0 + iy * self.h
        return np.stack([x, x + self.h, y, y + self.h], axis=1)

    def centres(self) -> np.ndarray:
        b = self.boxes()
        return np.stack([(b[:, 0] + b[:, 1]) / 2, (b[:, 2] + b[:, 3]) / 2], axis=1)


def dilate(boxes: np.ndarray, eps: np.ndarray) -> np.ndarray:
    e = np.asarray(eps, float)[:, None] * np.array([-1.0, 1.0, -1.0, 1.0])
    return boxes + e


@dataclass
class Abstraction:
    grid: Grid
    modes: int
    U: np.ndarray          # (cells, modes, J) support of the held input
    safe: np.ndarray       # (nodes,) node safe for one frame
    goal: np.ndarray       # (cells,)
    indptr: np.ndarray     # CSR successors of node n = cell * modes + (q - 1)
    succ: np.ndarray
    initial: np.ndarray    # (cells, modes) possible initial nodes
    multi: np.ndarray | None = None  # (nodes,) edges over several frames (positions beyond P along them)
    frames: int = 1        # the frames of a `multi` node's edges


def cell_hits(grid: Grid, H: np.ndarray, window: int):
    """Cells meeting the polygons `{d_j·x <= H_j}` `(N, J)`: `(rows, cells, overflow)` (overflow: a polygon
    reaching outside the grid or wider than `window` cells)."""
    q = len(DIRS) // 4  # the axis directions: +x, +y, -x, -y
    xl, xh, yl, yh = -H[:, 2 * q], H[:, 0], -H[:, 3 * q], H[:, q]
    ixl = np.floor((xl - grid.x0) / grid.h).astype(np.int64)
    ixh = np.floor((xh - grid.x0) / grid.h).astype(np.int64)
    iyl = np.floor((yl - grid.y0) / grid.h).astype(np.int64)
    iyh = np.floor((yh - grid.y0) / grid.h).astype(np.int64)
    overflow = (ixl < 0) | (iyl < 0) | (ixh >= grid.nx) | (iyh >= grid.ny)
    overflow |= (ixh - ixl >= window) | (iyh - iyl >= window) | ~np.isfinite(H).all(axis=1)
    ok = np.flatnonzero(~overflow)
    steps = np.arange(window)  # the cells of each set's bounding box: offsets (w // window, w % window)
    inside = (steps <= (ixh - ixl)[ok, None])[:, :, None] & (steps <= (iyh - iyl)[ok, None])[:, None, :]
    r, w = np.nonzero(inside.reshape(len(ok), window * window))
    ix, iy = ixl[ok][r] + w // window, iyl[ok][r] + w % window
    cx, cy = grid.x0 + (ix + 0.5) * grid.h, grid.y0 + (iy + 0.5) * grid.h
    rad = 0.5 * grid.h * (np.abs(DIRS[:, 0]) + np.abs(DIRS[:, 1]))
    # half-open cells [x0, x1) x [y0, y1) and sets P + T_s U of half-open P: in every direction either the
    # cell's minimum or the set's maximum lies on an open side (see docs/bracket.md), so they meet only if
    # lo < H strictly (to TOUCH in floating point)
    H_touch = H[ok] - TOUCH
    meets = np.empty(len(r), bool)
    for a in range(0, len(r), HITS_CHUNK):  # in chunks that stay in the cache: 2x faster, the same bits
        s = slice(a, a + HITS_CHUNK)
        lo = cx[s, None] * DIRS[:, 0]  # min over the closed cell of d_j·x: cx d_x + cy d_y - rad
        lo += cy[s, None] * DIRS[:, 1]
        lo -= rad
        meets[s] = (lo < H_touch[r[s]]).all(axis=-1)
    return ok[r[meets]], ix[meets] * grid.ny + iy[meets], overflow


def _frames(grid: Grid, hP, Uq, period, frames, window, bad_cell, stop, view=None):
    """Edges over `frames` frames where nothing can interrupt them: `R_0 = P`, `R_{i+1} = R_i ⊕ T_s U_i` with
    `U_i` the hull of `U` over the cells meeting `R_i` (the position at frame `i` is in one of them, in the same
    mode: no cell met can jump, `stop`), each frame's swept set checked for safety. A node whose reach set meets a
    goal or jump cell (or spreads over `window` cells) before the last frame keeps one-frame edges. `view` (`(J,)`
    bounds, :meth:`pipeline.bracket.frame.Frame.view_bounds`): a swept set that may leave the arena is unsafe.
    Returns the endpoint sets, the unsafe nodes and the hull of the inputs used (for the transience rule)."""
    n = len(hP)
    R, used = hP.copy(), Uq.copy()
    unsafe = np.zeros(n, bool)
    one = np.zeros(n, bool)  # nodes that fall back to one frame
    E1 = None
    for i in range(frames):
        if i == 0:
            Ui = Uq
        else:
            r, c, over = cell_hits(grid, R, window)
            Ui = np.full_like(Uq, -np.inf)
            np.maximum.at(Ui, r, Uq[c])
            hit = over.copy()
            np.logical_or.at(hit, r, stop[c] | bad_cell[c])
            one |= hit
            Ui = np.where(one[:, None], Uq, Ui)
        S = R + period * np.maximum(Ui, 0.0)
        r, c, over = cell_hits(grid, S, window)
        bad = over.copy()
        np.logical_or.at(bad, r, bad_cell[c])
        if view is not None:
            bad |= (S > view + TOUCH).any(axis=1)
        if i == 0:
            unsafe |= bad
            E1 = hP + period * Uq
        else:
            unsafe |= bad & ~one
        R = R + period * Ui
        used = np.where(one[:, None], used, np.maximum(used, Ui))
    multi = ~one if frames > 1 else np.zeros(n, bool)
    return np.where(one[:, None], E1, R), unsafe, np.where(one[:, None], Uq, used), multi


def unsafe_cells(scene, boxes: np.ndarray, known: np.ndarray, goal_radius: float,
                 in_view: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """`(bad, goal)` `(cells,)`: cells a run must not be in (meeting an obstacle's disc, out of the view, or without
    an error bound and not in the goal) and the goal cells (inside `B(p_T, goal_radius)`)."""
    bad_cell = np.zeros(len(boxes), bool)
    for cov in scene.coverings:  # a cell meeting an obstacle's disc
        bad_cell |= dist_range(boxes, cov.p_0)[0] <= cov.obstacle_radius
    if in_view is not None:
        bad_cell |= ~in_view
    goal = (dist_range(boxes, scene.p_T)[1] <= goal_radius) & ~bad_cell
    return bad_cell | (~known & ~goal), goal


def build(law, grid: Grid, eps_cells: np.ndarray, period: float, goal_radius: float, n_split: int = 4,
          window: int = 8, in_view: np.ndarray | None = None, frames: int = 1, keep_mode: bool = False,
          may_stop: bool = False, view: np.ndarray | None = None) -> Abstraction:
    """The abstraction of `law`'s sampled loop on `grid` with the error bound `eps_cells` `(cells,)` (module doc).

    Lost frames (SPEC §5.6; :mod:`pipeline.bracket.lost`, which widens `eps_cells` for the input held from an older
    frame): `keep_mode`, a frame may bring no decision (the mode is kept: every node also steps to its own mode);
    `may_stop`, a frame's input may be 0 (the predicting gate's stop past `max_drift`).

    The camera's view: `in_view` `(cells,)` the cells a run may be in (others are unsafe); with `view` (the arena
    as `(J,)` support bounds) a cell may straddle the arena's edge: its positions are the cell's part inside the
    arena (its polygon clipped by `view`), and a swept set that may leave the arena is unsafe."""
    boxes = grid.boxes()
    scene = law.scene
    eps_cells = np.asarray(eps_cells, float)
    known = np.isfinite(eps_cells)  # a cell without a bound: its nodes are unsafe (nothing is known there)
    M = dilate(boxes, np.where(known, eps_cells, 0.0))
    logic = Modes(law, M, keep_mode)
    modes = logic.modes
    U = logic.inputs(period, n_split)
    if may_stop:
        U = np.maximum(U, 0.0)  # the polytope's hull with the origin
    cen = grid.centres()
    hP = cen @ DIRS.T + 0.5 * grid.h * (np.abs(DIRS[:, 0]) + np.abs(DIRS[:, 1]))
    if view is not None:  # a cell's part inside the arena (cells out of view keep theirs: they are unsafe)
        hP = np.where(np.ones(grid.n, bool)[:, None] if in_view is None else in_view[:, None], np.minimum(hP, view), hP)
    bad_cell, goal = unsafe_cells(scene, boxes, known, goal_radius, in_view)
    n_nodes = grid.n * modes
    safe = np.ones(n_nodes, bool)
    rows_all, cols_all = [], []
    rate_U = U.copy()
    multi = np.zeros(n_nodes, bool)
    for k in range(modes):
        E, unsafe, used, multi_k = _frames(grid, hP, U[:, k], period, frames, window, bad_cell,
                                           goal | ~logic.no_jump(k), view)
        multi[np.arange(grid.n) * modes + k] = multi_k
        safe[np.arange(grid.n) * modes + k] = ~unsafe & ~bad_cell & logic.relevant[:, k]
        rate_U[:, k] = used
        r, c, _ = cell_hits(grid, E, window)
        for mask, k1 in logic.successors(k, c):
            rows_all.append(r[mask] * modes + k)
            cols_all.append(c[mask] * modes + k1)
    rows, cols = np.concatenate(rows_all), np.concatenate(cols_all)
    order = np.lexsort((cols, rows))
    rows, cols = rows[order], cols[order]
    keep = np.ones(len(rows), bool)
    keep[1:] = (rows[1:] != rows[:-1]) | (cols[1:] != cols[:-1])
    rows, cols = rows[keep], cols[keep]
    indptr = np.searchsorted(rows, np.arange(n_nodes + 1))
    return Abstraction(grid, modes, rate_U, safe, goal, indptr, cols, logic.initial, multi, frames)
