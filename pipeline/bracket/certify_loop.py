"""The certificate end to end (SPEC §5.4): the abstraction in a face-aligned frame, `Win`, and the certified
start region on world start cells (a start cell is certified when every grid cell meeting it is)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.bracket.abstraction import Abstraction, Grid, build, cell_hits
from pipeline.bracket.enclosures import DIRS
from pipeline.bracket.frame import Frame
from pipeline.bracket.winning import certified_cells, win


@dataclass
class Certificate:
    frame: Frame
    grid: Grid
    abstraction: Abstraction
    won: np.ndarray        # (nodes,)
    certified: np.ndarray  # (grid cells,)
    stats: dict


def certify(law, eps_world, *, h: float, angle: float, period: float, goal_radius: float, n_split: int = 4,
            window: int = 8, frames: int = 1) -> Certificate:
    """`law`'s certificate on cells of side `h` in the frame rotated by `angle`; `eps_world(points (N, 2)) ->
    (N,)` the error bound at world points of a cell (`max` over its corners and centre is taken, so `eps_world`
    must be the largest bound over any cell it is asked about: see :mod:`pipeline.bracket.errors`)."""
    frame = Frame(angle)
    rlaw = frame.law(law)
    scene = rlaw.scene
    anchor = scene.p_0 - scene.c * np.sqrt(0.5) * np.ones(2)  # the faces' lines are grid lines at 45°
    grid = Grid.over(scene.bounds, h, anchor=anchor)
    boxes = grid.boxes()
    eps = eps_world(frame.to_world(grid.centres()), boxes=boxes, frame=frame)
    view = frame.in_view(boxes, law.scene.bounds)
    ab = build(rlaw, grid, eps, period, goal_radius, n_split=n_split, window=window, in_view=view, frames=frames)
    W, stats = win(ab, period, scene.p_T)
    cert = certified_cells(ab, W) & view
    stats = {**stats, "nodes": int(len(ab.safe)), "edges": int(len(ab.succ)), "cells": int(grid.n)}
    return Certificate(frame, grid, ab, W, cert, stats)


def certified_starts(cert: Certificate, starts: np.ndarray) -> np.ndarray:
    """World start cells `(N, 4)` (`x0, x1, y0, y1`) certified: every grid cell meeting one is certified."""
    C = np.stack([starts[:, [0, 2]], starts[:, [1, 2]], starts[:, [1, 3]], starts[:, [0, 3]]], axis=1)
    G = cert.frame.to_grid(C.reshape(-1, 2)).reshape(-1, 4, 2)
    H = np.einsum("nkc,jc->nkj", G, DIRS).max(axis=1) + 2e-9  # the rotated square's support (closed)
    rows, cells, over = cell_hits(cert.grid, H, window=int(np.ceil(2 * (starts[0, 1] - starts[0, 0])
                                                                     / cert.grid.h)) + 3)
    ok = ~over
    np.logical_and.at(ok, rows, cert.certified[cells])
    return ok
