"""Adaptive splitting and sampling over a set of cells (SPEC §5.2-5.3).

:func:`certify_cells` bounds every cell, bisects (into four; a pose cell into eight: its heading too) the cells whose
bound `eps` is above the tolerance until it holds or the depth reaches `max_depth`, and returns per top cell the worst
bound over its leaves and the depth reached. :func:`sampled_errors` is `eps_emp`: the largest `|l(h(p)) - p|` over `n` positions drawn in each
cell, and the check that each of them lies inside its cell's bound.
"""

from __future__ import annotations

import contextlib

import numpy as np
import torch

from pipeline.certify.bounds import Prepared, certified_error_bound
from pipeline.progress import progress as progress_bar


def _children(cells: np.ndarray) -> np.ndarray:
    """Each cell `(x0, x1, y0, y1)` bisected in both axes: `(4 N, 4)`, children of cell `i` at `4 i .. 4 i + 3`; a
    pose cell `(x0, x1, y0, y1, th0, th1)` in its heading too: `(8 N, 6)`."""
    x0, x1, y0, y1 = cells[:, :4].T
    xm, ym = (x0 + x1) / 2, (y0 + y1) / 2
    quads = [(x0, xm, y0, ym), (xm, x1, y0, ym), (x0, xm, ym, y1), (xm, x1, ym, y1)]
    if cells.shape[1] == 6:
        t0, t1 = cells[:, 4], cells[:, 5]
        tm = (t0 + t1) / 2
        quads = [q + h for q in quads for h in ((t0, tm), (tm, t1))]
    return np.stack([np.stack(q, 1) for q in quads], 1).reshape(-1, cells.shape[1])


def pose_cells(cells: np.ndarray, headings: int) -> np.ndarray:
    """Each position cell `(N, 4)` with each of `headings` equal intervals of `[-π, π]`: `(N headings, 6)`, cell
    `i`'s at `headings i .. headings (i + 1) - 1`."""
    edges = np.linspace(-np.pi, np.pi, int(headings) + 1)
    sectors = np.column_stack([edges[:-1], edges[1:]])
    return np.concatenate([np.repeat(cells, len(sectors), 0), np.tile(sectors, (len(cells), 1))], 1)


def _bound_all(prep: Prepared, cells: np.ndarray, mode: str, batch: int, bar):
    lower, upper, heading = np.empty((len(cells), 2)), np.empty((len(cells), 2)), np.full(len(cells), np.nan)
    with torch.no_grad():
        for s in range(0, len(cells), batch):
            b = certified_error_bound(prep, torch.as_tensor(cells[s:s + batch]), mode)
            lower[s:s + batch], upper[s:s + batch] = b.lower.double().numpy(), b.upper.double().numpy()
            if b.heading is not None:
                heading[s:s + batch] = b.heading.double().numpy()
            bar.update(min(batch, len(cells) - s))
    return lower, upper, heading


def eps_of(lower: np.ndarray, upper: np.ndarray) -> np.ndarray:
    return np.sqrt((np.maximum(np.abs(lower), np.abs(upper)) ** 2).sum(-1))


def _levels(prep: Prepared, cells: np.ndarray, mode: str, tolerance: float, max_depth: int, batch: int, bar):
    """The splitting, level by level: per level `(cells, owner, lower, upper, heading, done)`, `done` the cells that
    are leaves (their bound within the tolerance, or the depth reached)."""
    current, owner = np.asarray(cells, dtype=np.float64), np.arange(len(cells))
    for d in range(max_depth + 1):
        lo, hi, head = _bound_all(prep, current, mode, batch, bar)
        split = (eps_of(lo, hi) > tolerance) if d < max_depth else np.zeros(len(current), dtype=bool)
        yield current, owner, lo, hi, head, ~split
        if not split.any():
            return
        current, owner = _children(current[split]), np.repeat(owner[split], 8 if current.shape[1] == 6 else 4)
        bar.total += len(current)
        bar.refresh()


def certify_cells(prep: Prepared, cells: np.ndarray, mode: str = "crown", tolerance: float = np.inf,
                  max_depth: int = 0, batch: int = 1024, progress: bool = True, desc: str = "certify", bar=None):
    """Per cell: `(lower (N, 2), upper (N, 2), depth (N,), leaves (N,), heading (N,))`: the per-coordinate bounds
    over its leaves (a cell split into sub-cells holds the worst of theirs), the depth and number of leaves it took,
    and a pose cell's heading bound (radians; NaN for a position map's cells). `bar`: a progress bar to advance
    (one of the caller's, over several calls); none: its own."""
    n = len(cells)
    lower, upper, heading = np.full((n, 2), np.inf), np.full((n, 2), -np.inf), np.full(n, -np.inf)
    depth, leaves = np.zeros(n, dtype=np.int64), np.zeros(n, dtype=np.int64)
    own = progress_bar(total=n, desc=desc, unit="cell", enabled=progress) if bar is None else contextlib.nullcontext(bar)
    with own as bar:
        for d, (_, owner, lo, hi, head, done) in enumerate(_levels(prep, cells, mode, tolerance, max_depth, batch, bar)):
            np.minimum.at(lower, owner[done], lo[done])
            np.maximum.at(upper, owner[done], hi[done])
            np.fmax.at(heading, owner[done], head[done])
            np.add.at(leaves, owner[done], 1)
            depth[owner[~done]] = d + 1
    return lower, upper, depth, leaves, np.where(np.isfinite(heading), heading, np.nan)


def leaf_cells(prep: Prepared, cells: np.ndarray, mode: str = "crown", tolerance: float = np.inf, max_depth: int = 0,
               batch: int = 1024) -> tuple[np.ndarray, np.ndarray]:
    """The leaves :func:`certify_cells` bounds `cells` on (the same splitting, recomputed): `(leaf boxes, owner)`,
    `owner[i]` the index in `cells` of leaf `i`. A split cell's bound is the union of its leaves' bounds, each over
    its own relaxation of the renderer: what an attack on the bound must search (the cell's own relaxation, wider,
    admits images no leaf's does)."""
    boxes, owners = [], []
    with progress_bar(total=len(cells), desc="leaves", unit="cell", enabled=False) as bar:
        for current, owner, *_, done in _levels(prep, cells, mode, tolerance, max_depth, batch, bar):
            boxes.append(current[done])
            owners.append(owner[done])
    return np.concatenate(boxes), np.concatenate(owners)


def sampled_errors(predict, camera, cells: np.ndarray, lower: np.ndarray, upper: np.ndarray, n: int, seed: int,
                   batch: int = 4096, progress: bool = True, heading: np.ndarray | None = None, stream: int = 0,
                   bar=None):
    """`eps_emp (N,)`: the largest error among `n` uniform positions per cell (a pose cell: poses, drawn with the
    marker at a heading of its interval); `violations`: how many sampled errors leave their cell's per-coordinate
    bound (or a pose cell's heading bound `heading (N,)`); `worst`: the largest excess and where (a counterexample);
    `head_emp (N,)`: a pose cell's largest sampled heading error (radians; None for position cells). The positions
    are the random stream `(seed, stream)`'s (the stage draws one per chunk of cells); `bar`: as in
    :func:`certify_cells`."""
    rng = np.random.default_rng([int(seed), 104729, int(stream)])
    pose = cells.shape[1] == 6
    emp, head_emp = np.zeros(len(cells)), (np.zeros(len(cells)) if pose else None)
    violations, worst = 0, (-np.inf, None)
    per = max(1, batch // n)
    own = (progress_bar(total=len(cells), desc="sampled positions", unit="cell", enabled=progress) if bar is None
           else contextlib.nullcontext(bar))
    with own as bar:
        for s in range(0, len(cells), per):
            c = cells[s:s + per]
            t = rng.uniform(size=(len(c), n, 3 if pose else 2))
            p = np.stack([c[:, None, 0] + t[..., 0] * (c[:, None, 1] - c[:, None, 0]),
                          c[:, None, 2] + t[..., 1] * (c[:, None, 3] - c[:, None, 2])], -1)
            th = c[:, None, 4] + t[..., 2] * (c[:, None, 5] - c[:, None, 4]) if pose else None
            out = np.asarray(predict(camera.render(p.reshape(-1, 2), heading=None if th is None else th.ravel())),
                             dtype=np.float64)
            e = out[:, :2].reshape(p.shape) - p
            emp[s:s + per] = np.linalg.norm(e, axis=-1).max(1)
            excess = np.maximum(lower[s:s + per, None] - e, e - upper[s:s + per, None]).max(-1)  # (n_c, n)
            if pose:
                he = np.abs(np.remainder(out[:, 2].reshape(th.shape) - th + np.pi, 2 * np.pi) - np.pi)
                head_emp[s:s + per] = he.max(1)
                excess = np.maximum(excess, he - heading[s:s + per, None])
            violations += int((excess > 0).sum())
            k = np.unravel_index(np.argmax(excess), excess.shape)
            if excess[k] > worst[0]:
                worst = (float(excess[k]), {"p": p[k].tolist(), "e": e[k].tolist(), "cell": c[k[0]].tolist(),
                                            **({"heading": float(th[k]), "estimate": out[k[0] * n + k[1]].tolist()}
                                               if pose else {})})
            bar.update(len(c))
    return emp, violations, worst, head_emp
