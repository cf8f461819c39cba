"""The certificate end to end (SPEC §5.4, §5.6): the abstraction in a face-aligned frame, `Win` with its arrival
bound, and the certified start region on world start cells: a start cell is certified when every grid cell meeting
its starts is, within the horizon. The starts of a cell are its points the simulator accepts: outside the closed
diamond `|a| + |b| <= c` (SPEC §3.6's start rule), so a grid cell lying inside the diamond is not a start."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.bracket.abstraction import Abstraction, Grid, build, cell_hits, unsafe_cells
from pipeline.bracket.enclosures import DIRS
from pipeline.bracket.frame import Frame
from pipeline.bracket.funnel import ball_max, node_funnels, run_funnels
from pipeline.bracket.lost import LostFrames
from pipeline.bracket.modes import initial_modes
from pipeline.bracket.polytope import polytope_funnels
from pipeline.bracket.refine import FineWin, Refinement, back_vertex, refine
from pipeline.bracket.winning import arrival_frames, certified_cells, relax_frames, win
from pipeline.control import HybridController, in_diamond

POLYTOPE_BATCH = 64  # a start cell's polytope funnels run in batches of this many (its first failure ends the cell)


@dataclass
class Certificate:
    frame: Frame
    grid: Grid
    abstraction: Abstraction
    won: np.ndarray        # (nodes,)
    certified: np.ndarray  # (grid cells,) within the horizon
    stats: dict
    arrival: np.ndarray    # (grid cells,) frames to the goal from the cell, every initial node (inf: not in Win)
    no_start: np.ndarray   # (grid cells,) inside the closed diamond or outside the arena: no start lies there
    scene: object = None   # the world scene (its obstacles' diamonds)
    node_frames: np.ndarray | None = None  # (nodes,) frames to the goal from a node of Win (inf elsewhere)
    eps_cells: np.ndarray | None = None    # (grid cells,) the error bound the abstraction took on each cell
    fine: FineWin | None = None            # the back vertex's window, refined: its Win (funnels hand off there too)


def certify(law, eps_world, *, h: float, angle: float, period: float, goal_radius: float, n_split: int = 4,
            window: int = 8, frames: int = 1, horizon: float = np.inf, lost: LostFrames | None = None,
            funnels: bool = False, refine_half: float = 0.0, refine_factor: int = 16,
            directional: bool = False) -> Certificate:
    """`law`'s certificate on cells of side `h` in the frame rotated by `angle`; `eps_world(points (N, 2)) ->
    (N,)` the error bound at world points of a cell (`max` over its corners and centre is taken, so `eps_world`
    must be the largest bound over any cell it is asked about: see :mod:`pipeline.bracket.bounds`). `horizon`: the
    frames a run has (a start is certified when its arrival bound fits); `lost`: frames that may be lost
    (:mod:`pipeline.bracket.lost`; None: every frame delivered). `funnels`: nodes whose cell's funnel hands off to
    `Win` join it with the funnel's bound, and `Win` is solved again (:func:`funnels_apply`). `refine_half > 0`: a
    window of that half-width around the back vertex on cells `refine_factor` times finer, coupled to these cells
    (:mod:`pipeline.bracket.refine`; one obstacle); `directional`: the window's arrival bounds also through sets
    of nodes (:func:`pipeline.bracket.winning.directional_frames`)."""
    frame = Frame(angle)
    rlaw = frame.law(law)
    scene = rlaw.scene
    cov = scene.covering(0)  # the first obstacle's faces are grid lines at 45°
    anchor = cov.p_0 - cov.c * np.sqrt(0.5) * np.ones(2)
    (x0, x1), (y0, y1) = scene.bounds  # one cell more on each side: a set at the arena's corner is inside the grid
    grid = Grid.over([[x0 - h, x1 + h], [y0 - h, y1 + h]], h, anchor=anchor)
    boxes = grid.boxes()
    lost = lost or LostFrames(0, False, period, 0.0)
    eps = lost.eps(eps_world)(frame.to_world(grid.centres()), boxes=boxes, frame=frame)
    bounds = frame.view_bounds(law.scene.bounds)  # cells straddling the arena's edge: their part inside it
    meets = frame.meets_view(boxes, law.scene.bounds)
    view = frame.in_view(boxes, law.scene.bounds) if bounds is None else meets
    ab = build(rlaw, grid, eps, period, goal_radius, n_split=n_split, window=window, in_view=view, frames=frames,
               keep_mode=lost.keep_mode, may_stop=lost.may_stop, view=bounds)
    W, stats, to_goal = win(ab, period, scene.p_T)
    if funnels and funnels_apply(law, lost):
        pre = Certificate(frame, grid, ab, W, None, stats, None, None, law.scene, to_goal, eps)
        seeds = np.minimum(node_funnels(pre, law, period, horizon), to_goal)
        W, stats, to_goal = win(ab, period, scene.p_T, seeds=seeds)
        stats["funnel_nodes"] = int((np.isfinite(seeds) & ~pre.won).sum())
    else:
        seeds = None
    fine_win = None
    if refine_half > 0 and scene.n_obstacles == 1:
        bad, _ = unsafe_cells(scene, boxes, np.isfinite(eps), goal_radius, view)
        fine = Refinement(rlaw, grid, lost.eps(eps_world), frame, half=refine_half, factor=refine_factor,
                          period=period, goal_radius=goal_radius, n_split=n_split, keep_mode=lost.keep_mode,
                          may_stop=lost.may_stop, coarse_bad=bad, coarse_eps=eps, view=bounds,
                          arena=law.scene.bounds)
        if fine.ok:
            W, stats, to_goal = refine(ab, W, stats, to_goal, fine, period, scene.p_T, seeds, directional)
            fine_win = FineWin(fine.fine, fine.frames)
    to_goal = relax_frames(ab, W, to_goal) if seeds is not None or fine_win is not None else to_goal
    arrival = np.where(view, arrival_frames(ab, to_goal), np.inf)
    cert = certified_cells(ab, W, to_goal, horizon) & view
    corners = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], axis=1)
    no_start = in_diamond(law.scene, frame.to_world(corners.reshape(-1, 2))).reshape(-1, 4).all(axis=1)
    no_start |= ~meets  # outside the arena (a start on its edge: in a cell inside)
    stats = {**stats, "nodes": int(len(ab.safe)), "edges": int(len(ab.succ)), "cells": int(grid.n),
             "horizon_frames": float(horizon), "beyond_horizon": int((certified_cells(ab, W) & view & ~cert).sum()),
             "lost_frames": lost.describe()}
    return Certificate(frame, grid, ab, W, cert, stats, arrival, no_start, law.scene, to_goal, eps, fine_win)


def funnels_apply(law, lost: LostFrames | None) -> bool:
    """Where funnels are modelled (:mod:`pipeline.bracket.funnel`): one obstacle, a speed limit, no stop of the
    predicting gate."""
    return law.scene.n_obstacles == 1 and law.u_max is not None and not (lost is not None and lost.may_stop)


def certified_starts(cert: Certificate, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """World start cells `(N, 4)` (`x0, x1, y0, y1`): `(certified, arrival, no_start)`. Certified: every grid cell
    meeting one is certified, those inside the closed diamond aside (no start there); arrival: the largest arrival
    bound in frames over those grid cells (inf: one is not in `Win`); no_start: the cell holds no start at all."""
    C = np.stack([starts[:, [0, 2]], starts[:, [1, 2]], starts[:, [1, 3]], starts[:, [0, 3]]], axis=1)
    G = cert.frame.to_grid(C.reshape(-1, 2)).reshape(-1, 4, 2)
    H = np.einsum("nkc,jc->nkj", G, DIRS).max(axis=1) + 2e-9  # the rotated square's support (closed)
    q = len(DIRS) // 4  # the widest rotated square of them all, in grid cells (the first may be a clipped one)
    span = np.maximum(H[:, 0] + H[:, 2 * q], H[:, q] + H[:, 3 * q]).max()
    rows, cells, over = cell_hits(cert.grid, H, window=int(np.ceil(span / cert.grid.h)) + 2)
    start = ~cert.no_start[cells]
    rows, cells = rows[start], cells[start]
    ok = ~over
    np.logical_and.at(ok, rows, cert.certified[cells])
    arrival = np.full(len(starts), -np.inf)
    np.maximum.at(arrival, rows, cert.arrival[cells])
    no_start = ~over & (np.bincount(rows, minlength=len(starts)) == 0)
    world = C.reshape(-1, 2)  # a start cell wholly in one closed diamond holds no start either
    for cov in cert.scene.coverings:  # (grid cells straddling a diamond not aligned with the grid meet it outside)
        no_start |= in_diamond(cov, world).reshape(-1, 4).all(axis=1)
    arrival[over | no_start] = np.inf
    return ok & ~no_start, arrival, no_start


def funnel_starts(cert: Certificate, law, starts: np.ndarray, split: int, period: float, horizon: float,
                  lost: LostFrames | None = None,
                  polytope_split: int = 0, mode_split: int = 1) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """World start cells `(N, 4)`: `(certified, arrival frames, no_start, by_funnel)`: by the abstraction
    (:func:`certified_starts`, its verdict and bound kept) or, where it does not certify, sub-square by sub-square
    by funnels or the abstraction (module docstring; `by_funnel` marks those). `split = 0`: the abstraction alone.
    `polytope_split > 0`: a sub-square's funnel that ends without a hand-off goes on as a polytope
    (:mod:`pipeline.bracket.polytope`, perceived sets cut into `polytope_split²` sub-boxes), start cell by start cell
    where every other sub-square is certified. `mode_split`: a sub-square's initial modes decided on `mode_split²`
    sub-boxes of its perceived box (:func:`pipeline.bracket.modes.initial_modes`)."""
    ok, arrival, no_start = certified_starts(cert, starts)
    by_funnel = np.zeros(len(starts), bool)
    hybrid = isinstance(law, HybridController)
    todo = np.flatnonzero(~ok & ~no_start)
    if split == 0 or todo.size == 0 or not funnels_apply(law, lost):
        return ok, arrival, no_start, by_funnel
    t = (np.arange(split) + 0.5) / split
    tx, ty = (g.ravel() for g in np.meshgrid(t, t, indexing="ij"))
    cells = starts[todo]
    w, h = (cells[:, 1] - cells[:, 0])[:, None], (cells[:, 3] - cells[:, 2])[:, None]
    cx, cy = cells[:, :1] + tx * w, cells[:, 2:3] + ty * h
    hw, hh = np.broadcast_to(w / split / 2, cx.shape), np.broadcast_to(h / split / 2, cy.shape)
    subs = np.stack([cx - hw, cx + hw, cy - hh, cy + hh], axis=-1).reshape(-1, 4)
    centres = np.stack([cx.ravel(), cy.ravel()], axis=1)
    rad0 = float(np.hypot(hw, hh).max())
    sub_ok, sub_arr, sub_none = certified_starts(cert, subs)
    eps0 = ball_max(cert, centres, rad0, cert.eps_cells)[0]
    reach = np.where(np.isfinite(eps0), rad0 + eps0, 1e9)  # the perceived box of frame 0
    boxes = np.stack([centres[:, 0] - reach, centres[:, 0] + reach, centres[:, 1] - reach, centres[:, 1] + reach], 1)
    modes = initial_modes(law, boxes, n_split=mode_split) if hybrid else np.ones((len(centres), 1), bool)
    per_mode = np.full(modes.shape, -np.inf)
    ends = []
    for q in range(1, modes.shape[1] + 1):
        rows = np.flatnonzero(modes[:, q - 1] & ~sub_none & ~sub_ok)
        per_mode[rows, q - 1], (c, r, k) = run_funnels(cert, law, centres[rows], rad0, q, period, horizon, tails=True)
        ends.append((rows, c, r, k))
    if polytope_split > 0 and cert.frame.view_bounds(law.scene.bounds) is not None:
        per_mode = _polytope_tails(cert, law, per_mode, ends, len(todo), sub_none | sub_ok, period, horizon,
                                   polytope_split)
    funnel = np.where(modes.any(axis=1), per_mode.max(axis=1), np.inf)
    per_sub = np.where(sub_none, -np.inf, np.where(sub_ok, sub_arr, funnel)).reshape(len(todo), -1)
    bound = per_sub.max(axis=1)
    won = np.isfinite(bound)
    ok[todo[won]], arrival[todo[won]], by_funnel[todo[won]] = True, bound[won], True
    return ok, arrival, no_start, by_funnel


def _polytope_tails(cert, law, per_mode, ends, n_cells, settled, period, horizon, n_split):
    """`per_mode` `(subs, modes)` with the funnels that ended without a hand-off gone on as polytopes
    (:func:`pipeline.bracket.polytope.polytope_funnels`), start cell by start cell (`n_cells` blocks of sub-squares),
    stopping at a cell's first polytope that fails (the cell needs them all)."""
    per_mode = per_mode.copy()
    subs = len(per_mode) // n_cells
    vertex = cert.frame.to_world(back_vertex(cert.frame.scene(law.scene)))
    tail = np.full((*per_mode.shape, 4), np.nan)  # per sub-square and mode: the ball (c, ρ) and its frame k
    for q, (rows, c, r, k) in enumerate(ends):
        tail[rows, q] = np.column_stack([c, r, k])
    for i in range(n_cells):
        block = slice(i * subs, (i + 1) * subs)
        failed = (per_mode[block] == np.inf) & ~settled[block, None]
        todo = [(q, np.flatnonzero(failed[:, q])) for q in range(per_mode.shape[1]) if failed[:, q].any()]
        if not todo or any(np.isnan(tail[block][j, q, 3]).any() for q, j in todo):
            continue  # certified already, or a funnel ended where no polytope goes on (the horizon)
        got = []
        for q, j in todo:  # in batches, nearest the back vertex first (where they fail): a failing cell stops early
            t = tail[block][j, q]
            order = np.argsort(np.hypot(*(t[:, :2] - vertex).T))
            b = np.full(len(j), np.inf)
            for s in range(0, len(j), POLYTOPE_BATCH):
                r = order[s:s + POLYTOPE_BATCH]
                b[r] = polytope_funnels(cert, law, t[r, :2], t[r, 2], t[r, 3], q + 1, period, horizon, n_split,
                                        all_or_nothing=True)
                if not np.isfinite(b[r]).all():
                    break
            got.append(b)
            if not np.isfinite(b).all():
                break
        else:
            for (q, j), b in zip(todo, got):
                per_mode[i * subs + j, q] = b
    return per_mode
