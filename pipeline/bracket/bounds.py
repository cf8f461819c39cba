"""The error bound `ε̄` the certificate takes (SPEC §5.3-5.4): uniform, or the certified error map's cell table.

A table (CSV or parquet) with one row per cell of positions: `x0, x1, y0, y1, eps_bar` (world units; the
certified error map of `pipeline.certify` writes one per `kappa`, `error_map_kappa<κ>.csv`), or a certify output's
folder (its table at `bracket.error_map_kappa`, 0 by default); `bracket.error_map` also takes the folder's `name-id` under `paths.certified_dir`. A grid cell of the abstraction gets the largest
`eps_bar` of the table cells it meets; a grid cell that no table cell covers gets `inf` (it cannot be
certified), so a map certified only on part of the arena certifies only runs that stay there. A grid cell is read
on its part inside the arena (`arena`: the camera sees nothing beyond it, and a run that leaves it has failed,
which the abstraction counts itself). Several tables of one perception map (:class:`Finest`: the whole operational
set, a region certified again with finer splitting, the diamond and the border certified apart) each bound the
error soundly where they cover it, so a grid cell takes the smallest of their bounds, or, where no table covers
it alone but their cells together do (tables that tile the arena), the largest bound of all the cells meeting it.

The falsifier takes the map's bound at a point (`at`): the smallest `eps_bar` of the table cells whose closed box
holds it (every one of them bounds the error there), `inf` where none does.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from pipeline.errors import ConfigError

COLUMNS = ("x0", "x1", "y0", "y1", "eps_bar")


class Uniform:
    """`ε̄(P) = eps` everywhere."""

    def __init__(self, eps: float):
        if not (eps >= 0 and np.isfinite(eps)):
            raise ConfigError("bracket.eps", f"must be a finite number >= 0, got {eps!r}")
        self.eps = float(eps)
        self.name = f"uniform {eps:g}"

    def __call__(self, points, boxes=None, frame=None) -> np.ndarray:
        return np.full(len(points), self.eps)


class CellTable:
    """`ε̄` from a table of cells (module docstring): a path, a DataFrame or an array `(N, 5)` of the columns."""

    def __init__(self, table, arena=None, kappa: float = 0.0):
        import pandas as pd

        if isinstance(table, (str, Path)):
            path = Path(table)
            if path.is_dir():  # a certified error map's folder (pipeline.certify): its table at pixel budget kappa
                path = path / f"error_map_kappa{float(kappa):g}.csv"
                if not path.is_file():
                    have = sorted(p.name[len("error_map_kappa"):-4] for p in path.parent.glob("error_map_kappa*.csv"))
                    raise ConfigError("bracket.error_map_kappa", f"{path.parent.name} has no table at kappa "
                                                                 f"{float(kappa):g} (its kappas: {', '.join(have) or 'none'})")
            if not path.is_file():
                raise ConfigError("bracket.error_map", f"no such file: {path}")
            table = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path, float_precision="round_trip")
        if isinstance(table, np.ndarray):
            table = pd.DataFrame(table, columns=list(COLUMNS))
        missing = [c for c in COLUMNS if c not in table.columns]
        if missing:
            raise ConfigError("bracket.error_map", f"needs columns {list(COLUMNS)}, missing {missing}")
        arr = table[list(COLUMNS)].to_numpy(float)
        if not (np.isfinite(arr[:, :4]).all() and (arr[:, 1] > arr[:, 0]).all() and (arr[:, 3] > arr[:, 2]).all()):
            raise ConfigError("bracket.error_map", "cells need finite x0 < x1 and y0 < y1")
        if (arr[:, 4] < 0).any() or np.isnan(arr[:, 4]).any():
            raise ConfigError("bracket.error_map", "eps_bar must be >= 0 (inf: not certified)")
        self.cells = arr
        self.arena = None if arena is None else np.asarray(arena, float).reshape(2, 2)
        self.name = "certified map"
        self._index = None

    @property
    def index(self) -> _BucketIndex:
        if self._index is None:
            self._index = _BucketIndex(self.cells)
        return self._index

    def __call__(self, points, boxes=None, frame=None) -> np.ndarray:
        """The largest `eps_bar` over table cells meeting each grid cell (its world bounding box, within the arena:
        sound), `inf` where they do not cover it."""
        if boxes is None:
            raise ValueError("a cell table needs the grid cells")
        lo, hi = world_boxes(boxes, frame, self.arena)
        out, covered = self.index.over(lo, hi)
        area = np.prod(np.maximum(hi - lo, 0.0), axis=1)
        out[covered < area * (1 - 1e-9)] = np.inf  # part of the cell has no bound
        out[(hi <= lo).any(axis=1)] = np.inf  # no part inside the arena (the view's rules hold there)
        return out

    def at(self, points: np.ndarray) -> np.ndarray:
        """The bound at each point `(N, 2)`: the smallest `eps_bar` of the cells whose closed box holds it (`inf`:
        none). The cells are bucketed on a grid of their median width, so a point meets only its bucket's cells."""
        return self.index.smallest(np.asarray(points, float).reshape(-1, 2))


def world_boxes(boxes: np.ndarray, frame=None, arena=None) -> tuple[np.ndarray, np.ndarray]:
    """The world bounding boxes `(lo, hi)` of grid cells `(N, 4)` (in `frame`'s coordinates), clipped to `arena`."""
    C = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], axis=1)
    W = frame.to_world(C.reshape(-1, 2)).reshape(-1, 4, 2) if frame is not None else C
    lo, hi = W.min(axis=1), W.max(axis=1)
    if arena is not None:
        lo, hi = np.maximum(lo, arena[:, 0]), np.minimum(hi, arena[:, 1])
        hi = np.maximum(hi, lo)  # wholly outside: an empty box
    return lo, hi


class Finest:
    """`ε̄` from several cell tables of one perception map: per grid cell the smallest of their bounds (each table
    is sound where it covers the cell, `inf` where it does not)."""

    def __init__(self, tables: list[CellTable]):
        self.tables = list(tables)
        self.name = "certified maps"
        self.union = _union(self.tables)

    @property
    def cells(self) -> np.ndarray:
        """Every table's rows with its index as a sixth column (what the bracket's id hashes)."""
        return np.concatenate([np.column_stack([t.cells, np.full(len(t.cells), i)]) for i, t in enumerate(self.tables)])

    def __call__(self, points, boxes=None, frame=None) -> np.ndarray:
        each = [t(points, boxes, frame) for t in self.tables]
        return np.min(each + ([self.union(points, boxes, frame)] if self.union is not None else []), axis=0)

    def at(self, points: np.ndarray) -> np.ndarray:
        """The smallest of the tables' bounds at each point (`inf`: no table covers it)."""
        return np.min([t.at(points) for t in self.tables], axis=0)


def _union(tables: list[CellTable]) -> CellTable | None:
    """All the tables' cells as one table (a box in several: its smallest bound), when they do not overlap but
    where identical (the cells of one certify grid in tables that tile the arena); None otherwise (a grid cell then
    needs one table that covers it alone)."""
    if len(tables) < 2:
        return None
    cells = np.concatenate([t.cells for t in tables])
    boxes, inverse = np.unique(cells[:, :4], axis=0, return_inverse=True)
    eps = np.full(len(boxes), np.inf)
    np.minimum.at(eps, inverse.ravel(), cells[:, 4])
    union = CellTable(np.column_stack([boxes, eps]), arena=tables[0].arena)
    _, covered = union.index.over(boxes[:, [0, 2]], boxes[:, [1, 3]])
    area = (boxes[:, 1] - boxes[:, 0]) * (boxes[:, 3] - boxes[:, 2])
    return union if (covered <= area * (1 + 1e-9)).all() else None  # more: two cells overlap


class _BucketIndex:
    """Table cells bucketed on a uniform grid: `smallest(points)` is the least `eps_bar` over the cells whose closed
    box holds each point, looked up among the cells of the point's bucket only (a cell is listed in every bucket
    its closed box meets)."""

    def __init__(self, cells: np.ndarray):
        self.cells = cells
        self.lo = cells[:, [0, 2]].min(axis=0)
        self.h = float(max(np.median(np.minimum(cells[:, 1] - cells[:, 0], cells[:, 3] - cells[:, 2])), 1e-9))
        self.shape = np.floor((cells[:, [1, 3]].max(axis=0) - self.lo) / self.h).astype(int) + 1
        i0, i1 = self._bucket(cells[:, [0, 2]]), self._bucket(cells[:, [1, 3]])
        nx, ny = i1[:, 0] - i0[:, 0] + 1, i1[:, 1] - i0[:, 1] + 1
        owner = np.repeat(np.arange(len(cells)), nx * ny)
        first = np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        k = np.arange(len(owner)) - first
        bx, by = i0[owner, 0] + k % nx[owner], i0[owner, 1] + k // nx[owner]
        key = bx * self.shape[1] + by
        order = np.argsort(key, kind="stable")
        key, owner = key[order], owner[order]
        start = np.searchsorted(key, np.arange(self.shape[0] * self.shape[1] + 1))
        width = int(np.diff(start).max()) if len(owner) else 0
        slot = np.arange(len(key)) - start[key]
        self.table = np.full((self.shape[0] * self.shape[1], max(width, 1)), -1)
        self.table[key, slot] = owner

    def _bucket(self, xy: np.ndarray) -> np.ndarray:
        return np.clip(np.floor((xy - self.lo) / self.h).astype(int), 0, self.shape - 1)

    def over(self, lo: np.ndarray, hi: np.ndarray, chunk: int = 4096) -> tuple[np.ndarray, np.ndarray]:
        """Per box `[lo, hi]` `(N, 2)`: the largest `eps_bar` of the cells whose closed box meets it (`-inf`: none)
        and the area of the box they cover, each cell counted once (in the bucket of the lower-left corner of its
        part of the box)."""
        out, covered = np.full(len(lo), -np.inf), np.zeros(len(lo))
        for s in range(0, len(lo), chunk):
            out[s:s + chunk], covered[s:s + chunk] = self._over(lo[s:s + chunk], hi[s:s + chunk])
        return out, covered

    def _over(self, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        out, covered = np.full(len(lo), -np.inf), np.zeros(len(lo))
        b0, b1 = self._bucket(lo), self._bucket(hi)
        nx, ny = b1[:, 0] - b0[:, 0] + 1, b1[:, 1] - b0[:, 1] + 1
        box = np.repeat(np.arange(len(lo)), nx * ny)
        k = np.arange(len(box)) - np.repeat(np.cumsum(nx * ny) - nx * ny, nx * ny)
        bx, by = b0[box, 0] + k % nx[box], b0[box, 1] + k // nx[box]
        cand = self.table[bx * self.shape[1] + by]  # (pairs, width), -1: empty slot
        c = self.cells[np.maximum(cand, 0)]
        cx, cy = np.maximum(lo[box, 0, None], c[..., 0]), np.maximum(lo[box, 1, None], c[..., 2])
        ox = np.minimum(hi[box, 0, None], c[..., 1]) - cx
        oy = np.minimum(hi[box, 1, None], c[..., 3]) - cy
        meet = (cand >= 0) & (ox >= 0) & (oy >= 0)
        home = self._bucket(np.stack([cx, cy], -1))
        once = meet & (home[..., 0] == bx[:, None]) & (home[..., 1] == by[:, None])
        np.maximum.at(out, box, np.where(meet, c[..., 4], -np.inf).max(axis=1))
        np.add.at(covered, box, np.where(once, np.clip(ox, 0, None) * np.clip(oy, 0, None), 0.0).sum(axis=1))
        return out, covered

    def smallest(self, points: np.ndarray) -> np.ndarray:
        out = np.full(len(points), np.inf)
        inside = ((points >= self.lo) & (points <= self.lo + self.shape * self.h)).all(axis=1)
        b = self._bucket(points[inside])
        cand = self.table[b[:, 0] * self.shape[1] + b[:, 1]]  # (n, width), -1: empty slot
        c = self.cells[np.maximum(cand, 0)]
        x, y = points[inside, 0, None], points[inside, 1, None]
        holds = (cand >= 0) & (c[..., 0] <= x) & (x <= c[..., 1]) & (c[..., 2] <= y) & (y <= c[..., 3])
        out[inside] = np.where(holds, c[..., 4], np.inf).min(axis=1)
        return out
