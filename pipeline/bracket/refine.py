"""Finer cells at the back vertex (SPEC §5.4's adaptive refinement; docs/bracket.md "The back vertex, refined").

With cells of one unit the abstraction holds a strongly connected set of about 16 nodes, both modes, within 1.6 units
of the diamond's back vertex: a cell there meets both jump regions (the perceived point above the vertex jumps
mode 1 to 2, below it mode 2 to 1) and both push-outs, so abstract paths circle, and no ranking function of the
transience rule decreases along the attraction and both push-outs at once. Every node whose abstract paths drift
into it is lost with it: behind the obstacle, nothing within 7.5 units of the axis was certified. The runs
themselves leave the vertex in a frame or two (a push-out or the flow moves them half a unit along a face, away
from the other mode's jump region), which finer cells see once a node's inputs are kept apart per sub-box (the
push-out and the slide, not their hull), each piece with its least speed (:mod:`pipeline.bracket.pieces`): on a
window of ±3 units at cells of 1/8 or 1/16 the one-frame graph has no cycle at `ε = 0.1` (measured; at 0.5 a band
within about 2 units of the vertex stays out of `Win`).

:func:`refine` builds that graph (cells of `h / factor` on the coarse cells within `half` of the vertex, edges over
one frame, the same law, error bound and lost-frame rules) and couples it to the coarse abstraction both ways:

- a fine node whose swept set leaves the window (an **exit**) is judged on the coarse grid: safe when the swept set
  meets no unsafe coarse cell and stays in the arena, winning when every coarse node its endpoint set can be in
  after the next frame's decision (:meth:`pipeline.bracket.modes.Modes.successors` on the coarse cells) is in `Win`,
  with the bound `1 + max frames` of those nodes; a losing exit is unsafe;
- the fine `Win` is solved with the exits as seeds (:func:`pipeline.bracket.winning.win`);
- a coarse node `(P, q)` whose cell lies in the window joins `Win` as a seed when every fine node `(P_f, q)`,
  `P_f ⊂ P`, is in the fine `Win` (same semantics: a frame instant, the position in `P`, the mode after the
  decision), with the largest fine bound; the coarse `Win` is solved again, and the rounds repeat while `Win` grows.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from pipeline.bracket.abstraction import Abstraction, Grid, cell_hits, dilate, unsafe_cells
from pipeline.bracket.enclosures import DIRS, split
from pipeline.bracket.inputs import support
from pipeline.bracket.modes import Modes
from pipeline.bracket.winning import directional_frames, win

ROUNDS = 4  # fine and coarse Win solved alternately at most this many times (they stop as soon as nothing is added)


def back_vertex(scene) -> np.ndarray:
    """The diamond vertex of the first obstacle farthest from the target (in `scene`'s own frame)."""
    cov = scene.covering(0)
    corners = np.array([cov.p_0 + s * cov.c * e for e in (cov.e_a, cov.e_b) for s in (1.0, -1.0)])
    return corners[np.argmax(np.hypot(*(corners - scene.p_T).T))]


def window_grid(grid: Grid, centre: np.ndarray, half: float, factor: int) -> tuple[Grid, np.ndarray] | None:
    """The fine grid (cells `grid.h / factor`) on the coarse cells whose square lies within `half` of `centre`
    (per axis), and those coarse cells' indices; None when no whole coarse cell fits or the window leaves the grid."""
    h = grid.h
    ix0 = math.ceil((centre[0] - half - grid.x0) / h - 1e-9)
    ix1 = math.floor((centre[0] + half - grid.x0) / h + 1e-9)
    iy0 = math.ceil((centre[1] - half - grid.y0) / h - 1e-9)
    iy1 = math.floor((centre[1] + half - grid.y0) / h + 1e-9)
    if ix1 <= ix0 or iy1 <= iy0 or ix0 < 0 or iy0 < 0 or ix1 > grid.nx or iy1 > grid.ny:
        return None
    fine = Grid(grid.x0 + ix0 * h, grid.y0 + iy0 * h, h / factor, (ix1 - ix0) * factor, (iy1 - iy0) * factor)
    cx, cy = np.meshgrid(np.arange(ix0, ix1), np.arange(iy0, iy1), indexing="ij")
    return fine, (cx * grid.ny + cy).ravel()


def box_support(B: np.ndarray) -> np.ndarray:
    """`(..., J)` support values of boxes `(..., 4)` (`x0, x1, y0, y1`) on the directions `DIRS`."""
    return (np.maximum(B[..., 0:1] * DIRS[:, 0], B[..., 1:2] * DIRS[:, 0])
            + np.maximum(B[..., 2:3] * DIRS[:, 1], B[..., 3:4] * DIRS[:, 1]))


def _hits(grid: Grid, H: np.ndarray, window: int, chunk: int = 4096):
    """:func:`pipeline.bracket.abstraction.cell_hits` in chunks of sets (its candidate cells are `window²` per set)."""
    parts = [cell_hits(grid, H[s:s + chunk], window) for s in range(0, len(H), chunk)]
    if not parts:
        return np.zeros(0, np.int64), np.zeros(0, np.int64), np.zeros(0, bool)
    return (np.concatenate([r + s for (r, _, _), s in zip(parts, range(0, len(H), chunk))]),
            np.concatenate([c for _, c, _ in parts]), np.concatenate([o for _, _, o in parts]))


def _max_dist(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """The largest distance between a point of box `a` and one of box `b` (rows `(N, 4)`)."""
    dx = np.maximum(np.abs(b[:, 1] - a[:, 0]), np.abs(a[:, 1] - b[:, 0]))
    dy = np.maximum(np.abs(b[:, 3] - a[:, 2]), np.abs(a[:, 3] - b[:, 2]))
    return np.hypot(dx, dy)


def _csr(rows: list, cols: list, n: int) -> tuple[np.ndarray, np.ndarray]:
    rows, cols = np.concatenate(rows), np.concatenate(cols)
    key = np.unique(rows * n + cols)
    rows, cols = np.divmod(key, n)
    return np.searchsorted(rows, np.arange(n + 1)), cols


@dataclasses.dataclass
class FineWin:
    """The window's fine `Win` as the funnels read it (:func:`pipeline.bracket.funnel.run_funnels`): its grid (the
    abstraction's frame) and, per fine cell and mode, the arrival bound in frames (inf: not in `Win`)."""

    grid: Grid
    frames: np.ndarray  # (fine cells, modes)


class Refinement:
    """The fine graph of one window, built once per certificate, and its coupling to the coarse `Win` (module doc).

    Its edges are a union over the perceived box's sub-boxes `M_i` (not over their hull, as the coarse abstraction's):
    a position `p` of `P` perceived in `M_i` lies in `P ∩ (M_i ⊕ ε)`, and its held input in `U(M_i, q)`, so the
    endpoint set is `∪_i (P ∩ (M_i ⊕ ε)) ⊕ T_s U(M_i, q)`: at the vertex the push-out (perceived inside the diamond)
    and the slide along the face (perceived outside) are two sets, not the segment between them."""

    def __init__(self, rlaw, coarse: Grid, eps_fn, frame, *, half: float, factor: int, period: float,
                 goal_radius: float, n_split: int, keep_mode: bool, may_stop: bool, coarse_bad: np.ndarray,
                 coarse_eps: np.ndarray, view: np.ndarray | None, arena):
        self.ok = False
        made = window_grid(coarse, back_vertex(rlaw.scene), half, factor)
        if made is None:
            return
        self.fine, self.cells = made
        g = self.fine
        corner = np.array([[g.x0, g.x0 + g.nx * g.h, g.y0, g.y0 + g.ny * g.h]])
        if not frame.in_view(corner, arena)[0]:
            return
        self.coarse, self.factor, self.period, self.p_T = coarse, factor, period, rlaw.scene.p_T
        boxes = g.boxes()
        eps = eps_fn(frame.to_world(g.centres()), boxes=boxes, frame=frame)
        known = np.isfinite(eps)
        e = np.where(known, eps, 0.0)
        M = dilate(boxes, e)
        logic = Modes(rlaw, M, keep_mode)
        c_logic = Modes(rlaw, dilate(coarse.boxes(), np.where(np.isfinite(coarse_eps), coarse_eps, 0.0)), keep_mode)
        bad_f, goal = unsafe_cells(rlaw.scene, boxes, known, goal_radius)
        modes, n = logic.modes, g.n
        width = int(np.ceil((2 * rlaw.u_max * period + coarse.h) / g.h)) + 2 if rlaw.u_max else 4 * factor
        subs = dilate(split(M, n_split).reshape(-1, 4), np.repeat(e, n_split * n_split)).reshape(n, -1, 4)
        P = np.broadcast_to(boxes[:, None, :], subs.shape)
        pos = np.stack([np.maximum(P[..., 0], subs[..., 0]), np.minimum(P[..., 1], subs[..., 1]),
                        np.maximum(P[..., 2], subs[..., 2]), np.minimum(P[..., 3], subs[..., 3])], -1)
        hB = box_support(pos)
        hull = np.empty((n, modes, len(DIRS)))
        safe = np.ones(n * modes, bool)
        rows, cols, ex_rows, ex_cols, exits, ex_bad = [], [], [], [], [], []
        for k in range(modes):
            U, floor = support(rlaw, M, k % 2 + 1, period, n_split, parts=True)
            reps = U.shape[1] // hB.shape[1]  # each piece on its sub-box's positions
            hB_k, pos_k = np.tile(hB, (1, reps, 1)), np.tile(pos, (1, reps, 1))
            if may_stop:  # the predicting gate's stop: 0 joins every piece's inputs
                U, floor = np.maximum(U, 0.0), np.zeros_like(floor)
            hull[:, k] = U.max(axis=1)
            node, part = np.nonzero(np.isfinite(U).all(axis=-1))  # sub-boxes where mode k is held
            S = hB_k[node, part] + period * np.maximum(U[node, part], 0.0)
            E = hB_k[node, part] + period * U[node, part]
            r, c, over = _hits(g, S, width)
            out = np.zeros(n, bool)
            out[node[over]] = True  # a swept set leaves the window: the node is judged on the coarse grid
            bad = np.zeros(n, bool)
            np.logical_or.at(bad, node[r], bad_f[c])
            safe[np.arange(n) * modes + k] = ~bad & ~bad_f & logic.relevant[:, k]
            inner = ~out[node]
            r, c, _ = _hits(g, E[inner], width)
            far = _max_dist(pos_k[node, part][inner][r], boxes[c]) >= period * floor[node, part][inner][r] - 1e-9
            r, c = r[far], c[far]  # a piece's inputs of norm >= floor move a run at least T_s floor
            for mask, k1 in logic.successors(k, c):
                rows.append(node[inner][r[mask]] * modes + k)
                cols.append(c[mask] * modes + k1)
            sel = out[node]
            r, c, cover = cell_hits(coarse, S[sel], 12)
            cbad = cover.copy()
            np.logical_or.at(cbad, r, coarse_bad[c])
            if view is not None:
                cbad |= (S[sel] > view + 1e-9).any(axis=1)
            badn = np.zeros(n, bool)
            np.logical_or.at(badn, node[sel][cbad], True)
            r, c, _ = cell_hits(coarse, E[sel], 12)
            for mask, k1 in c_logic.successors(k, c):
                ex_rows.append(node[sel][r[mask]] * modes + k)
                ex_cols.append(c[mask] * modes + k1)
            exits.append(np.flatnonzero(out) * modes + k)
            ex_bad.append(np.flatnonzero(out & (badn | bad_f)) * modes + k)
        indptr, succ = _csr(rows, cols, n * modes)
        self.ab = Abstraction(g, modes, hull, safe, goal, indptr, succ, logic.initial, None, 1)
        self.exits, self.exit_unsafe = np.concatenate(exits), np.concatenate(ex_bad)
        self.edge_from, self.edge_to = np.concatenate(ex_rows), np.concatenate(ex_cols)
        self.ok = True

    def coarse_seeds(self, won: np.ndarray, frames: np.ndarray, tighten: bool = False) -> tuple[np.ndarray, dict]:
        """Per coarse node, the arrival bound the window proves (inf elsewhere), from the coarse `Win` and bounds;
        `tighten`: the fine bounds also through sets of nodes (:func:`pipeline.bracket.winning.directional_frames`)."""
        n_f, modes = len(self.ab.safe), self.ab.modes
        best = np.full(n_f, -np.inf)  # the exits' bounds: 1 + the largest over their coarse successors
        np.maximum.at(best, self.edge_from, np.where(won[self.edge_to], frames[self.edge_to], np.inf))
        seeds = np.full(n_f, np.inf)
        seeds[self.exits] = np.where(np.isfinite(best[self.exits]), 1.0 + best[self.exits], np.inf)
        seeds[self.exit_unsafe] = np.inf
        ab = self.ab
        safe = ab.safe.copy()
        safe[self.exits] = False  # an exit is winning through its seed or not at all
        fine = dataclasses.replace(ab, safe=safe)
        W, stats, fr = win(fine, self.period, self.p_T, seeds=np.where(np.isfinite(seeds), seeds, np.inf))
        if tighten:  # bounds through sets of nodes as well (docs/bracket.md "Arrival bounds through a set")
            fr = directional_frames(fine, W, fr, self.period, safe & ~np.repeat(ab.goal, modes))  # exits: unsafe
        self.frames = np.where(W, fr, np.inf).reshape(-1, modes)  # the funnels hand off here too (FineWin)
        f = self.factor
        g = self.fine
        ix, iy = np.divmod(np.arange(g.n), g.ny)
        parent = (ix // f) * (g.ny // f) + iy // f  # the window's coarse cell of each fine cell
        per = np.full((len(self.cells), modes), -np.inf)
        np.maximum.at(per, parent, np.where(W, fr, np.inf).reshape(-1, modes))
        out = np.full(self.coarse.n * modes, np.inf)
        out.reshape(-1, modes)[self.cells] = per
        return out, {"fine_cells": int(g.n), "fine_won": int(W.sum()), "fine_components": stats["components"]}


def refine(ab, won, stats, frames, refinement: Refinement, period: float, p_T: np.ndarray,
           seeds: np.ndarray | None, directional: bool = False):
    """Rounds of fine and coarse `Win` (module docstring), until the window adds nothing: the coarse `(Win, stats,
    frames)`. `directional`: then one more round with the fine bounds tightened through sets of nodes (one: the
    tightening costs seconds, and the rounds before it have settled `Win`)."""
    seeds = np.full(len(won), np.inf) if seeds is None else seeds.copy()
    info = {}

    def one_round(tighten: bool) -> bool:
        nonlocal seeds, won, stats, frames, info
        add, info = refinement.coarse_seeds(won, frames, tighten=tighten)
        new = np.minimum(seeds, np.where(add < frames, add, np.inf))  # only where the window proves a smaller bound
        if np.array_equal(new, seeds):
            return False
        seeds = new
        won, stats, frames = win(ab, period, p_T, seeds=seeds)
        return True

    for _ in range(ROUNDS):
        if not one_round(False):
            break
    if directional:
        one_round(True)
    return won, {**stats, **info, "refined_nodes": int((np.isfinite(seeds) & won).sum())}, frames
