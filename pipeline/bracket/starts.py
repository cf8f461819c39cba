"""The bracket table's start cells (docs/bracket.md): square cells anchored at the first obstacle's centre, the
falsifier's start in each (a point the simulator accepts), and the cells behind an obstacle and on its `K`."""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.bracket.loop import clearance
from pipeline.control import in_diamond


def start_cells(scene, side: float) -> np.ndarray:
    """Square start cells of side `side` with edges at `p_0 ± side/2 + k side` (`p_0` the first obstacle's centre: a
    row of centres on `K`, the axis behind it), clipped to the arena."""
    (x0, x1), (y0, y1) = scene.bounds
    edges = []
    p_0 = scene.covering(0).p_0
    for lo, hi, c in ((x0, x1, p_0[0]), (y0, y1, p_0[1])):
        k0 = int(np.floor((lo - c - side / 2) / side))
        e = c - side / 2 + side * np.arange(k0, k0 + int((hi - lo) / side) + 3)
        e = np.unique(np.clip(e, lo, hi))
        edges.append(e)
    (ex, ey) = edges
    X0, Y0 = np.meshgrid(ex[:-1], ey[:-1], indexing="ij")
    X1, Y1 = np.meshgrid(ex[1:], ey[1:], indexing="ij")
    return np.stack([X0.ravel(), X1.ravel(), Y0.ravel(), Y1.ravel()], 1)


def falsifier_starts(scene, starts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per start cell the falsifier's start: the centre, or where the simulator refuses it (inside a closed
    diamond, SPEC §3.6) the cell's corner farthest out of the diamond (several obstacles: the point of a 5 x 5 grid
    over the cell farthest out of every diamond); and whether that start is one the simulator accepts (outside every
    diamond and obstacle disc)."""
    C = np.stack([starts[:, [0, 2]], starts[:, [1, 2]], starts[:, [1, 3]], starts[:, [0, 3]]], axis=1)
    centres = C.mean(axis=1)
    if scene.n_obstacles == 1:
        a, b = scene.to_frame(C.reshape(-1, 2))
        far = C[np.arange(len(C)), np.argmax((np.abs(a) + np.abs(b)).reshape(-1, 4), axis=1)]
    else:
        t = np.linspace(0.0, 1.0, 5)
        tx, ty = (g.ravel() for g in np.meshgrid(t, t, indexing="ij"))
        P = np.stack([starts[:, :1] + tx * (starts[:, 1:2] - starts[:, :1]),
                      starts[:, 2:3] + ty * (starts[:, 3:4] - starts[:, 2:3])], axis=-1)  # (N, 25, 2)
        out = np.min([np.abs(a) + np.abs(b) - cov.c for cov in scene.coverings
                      for a, b in [cov.to_frame(P.reshape(-1, 2))]], axis=0).reshape(len(P), -1)
        far = P[np.arange(len(P)), np.argmax(out, axis=1)]
    p0 = np.where(in_diamond(scene, centres)[:, None], far, centres)
    ok = ~in_diamond(scene, p0) & (clearance(p0, scene) >= 0)
    return p0, ok


def _interior(scene, starts: np.ndarray, n: int, edges: bool = False) -> tuple[np.ndarray, np.ndarray]:
    """`n x n` points per start cell `(N, n², 2)`, centred in its sub-squares (never on its edges; odd `n`: the
    centre among them; `edges`: a lattice from edge to edge instead, the closed cell's), and whether the simulator
    accepts each `(N, n²)`."""
    t = np.linspace(0.0, 1.0, n) if edges else (np.arange(n) + 0.5) / n
    tx, ty = (g.ravel() for g in np.meshgrid(t, t, indexing="ij"))
    P = np.stack([starts[:, :1] + tx * (starts[:, 1:2] - starts[:, :1]),
                  starts[:, 2:3] + ty * (starts[:, 3:4] - starts[:, 2:3])], axis=-1)
    flat = P.reshape(-1, 2)
    return P, (~in_diamond(scene, flat) & (clearance(flat, scene) >= 0)).reshape(len(P), -1)


def worst_starts(scene, starts: np.ndarray, bound, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """Per start cell `(N, 4)` the start the simulator accepts where `bound(points) -> (M,)` (the falsifier's error
    bound at a point: the map's `ε̄`, 0 where it has none) is largest, among the cell's `n x n` interior points, and
    that bound (`-inf`: no point accepted). A certificate claims every start of its cell, so a run from any of them
    that fails falsifies it; the map's bound is largest on the arena's border, where the image clips the robot."""
    P, ok = _interior(scene, starts, n)
    b = np.where(ok, np.asarray(bound(P.reshape(-1, 2)), float).reshape(ok.shape), -np.inf)
    k = np.argmax(b, axis=1)
    return P[np.arange(len(P)), k], b[np.arange(len(P)), k]


def axis_starts(scene, starts: np.ndarray, n: int = 9) -> tuple[np.ndarray, np.ndarray]:
    """Per start cell `(N, 4)` the start the simulator accepts nearest `K` (an obstacle's axis behind it: its frame's
    `a < -c`, `b = 0`) among the closed cell's `n x n` lattice points, edges included (a certificate claims the
    closed cell: its sub-squares and grid cells cover the edges), and its distance `|b|` to that axis (`inf`: no
    point of the cell behind an obstacle). The hybrid law's trap lives on `K` (docs/bracket.md, "The falsifier
    aimed at the vertex"): a run from a cell's edge nearest the axis needs less error to be held there than one from
    its centre (measured from 2.55 units off the axis: `ε_hi` 1.25–2.5 against 2.25–inf from the centres, 5 off it)."""
    P, ok = _interior(scene, starts, n, edges=True)
    d = np.where(ok, axis_distance(scene, P.reshape(-1, 2)).reshape(ok.shape), np.inf)
    k = np.argmin(d, axis=1)
    return P[np.arange(len(P)), k], d[np.arange(len(P)), k]


def axis_distance(scene, p: np.ndarray) -> np.ndarray:
    """The distance `|b|` of points `(N, 2)` to the nearest obstacle's `K` (its axis behind it, `a < -c`), `inf` for
    a point behind no obstacle `(N,)`."""
    d = np.full(len(p), np.inf)
    for cov in scene.coverings:
        a, b = cov.to_frame(p)
        d = np.minimum(d, np.where(a < -cov.c, np.abs(b), np.inf))
    return d


def behind_obstacles(df: pd.DataFrame, scene) -> tuple[np.ndarray, np.ndarray]:
    """Start cells behind an obstacle (its frame's `a < -c`, `|b| < 15`) and on `K` (also crossed by its axis
    `b = 0`), over the obstacles."""
    cells = df[["x0", "x1", "y0", "y1"]].to_numpy(float)
    centre = np.stack([(cells[:, 0] + cells[:, 1]) / 2, (cells[:, 2] + cells[:, 3]) / 2], 1)
    C = np.stack([cells[:, [0, 2]], cells[:, [1, 2]], cells[:, [1, 3]], cells[:, [0, 3]]], axis=1).reshape(-1, 2)
    behind, on_K = np.zeros(len(df), bool), np.zeros(len(df), bool)
    for cov in scene.coverings:
        a, b = cov.to_frame(centre)
        back = (a < -cov.c) & (np.abs(b) < 15)
        bc = cov.to_frame(C)[1].reshape(-1, 4)
        behind |= back
        on_K |= back & (bc.min(axis=1) <= 0) & (bc.max(axis=1) > 0)
    return behind, on_K
