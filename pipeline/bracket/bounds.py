"""The error bound `ε̄` the certificate takes (SPEC §5.3-5.4): uniform, or the certified error map's cell table.

A table (CSV or parquet) with one row per cell of positions: `x0, x1, y0, y1, eps_bar` (world units; the
certified error map of `pipeline.certify` writes one per `kappa`, `error_map_kappa<κ>.csv`), or a certify output's
folder (its `kappa = 0` table); `bracket.error_map` also takes the folder's `name-id` under `paths.certified_dir`. A grid cell of the abstraction gets the largest
`eps_bar` of the table cells it meets; a grid cell that no table cell covers gets `inf` (it cannot be
certified), so a map certified only on part of the arena certifies only runs that stay there. Several tables of one
perception map (:class:`Finest`: the whole operational set, and a region certified again with finer splitting)
each bound the error soundly where they cover it, so a grid cell takes the smallest of their bounds.

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
    """`ε̄` from a table of cells (module docstring)."""

    def __init__(self, table):
        import pandas as pd

        if isinstance(table, (str, Path)):
            path = Path(table)
            if path.is_dir():  # a certified error map's folder (pipeline.certify): its table at kappa 0
                path = path / "error_map_kappa0.csv"
            if not path.is_file():
                raise ConfigError("bracket.error_map", f"no such file: {path}" + (
                    " (a certify output's folder holds error_map_kappa0.csv when its kappas include 0)"
                    if path.name == "error_map_kappa0.csv" else ""))
            table = pd.read_parquet(path) if path.suffix == ".parquet" else pd.read_csv(path, float_precision="round_trip")
        missing = [c for c in COLUMNS if c not in table.columns]
        if missing:
            raise ConfigError("bracket.error_map", f"needs columns {list(COLUMNS)}, missing {missing}")
        arr = table[list(COLUMNS)].to_numpy(float)
        if not (np.isfinite(arr[:, :4]).all() and (arr[:, 1] > arr[:, 0]).all() and (arr[:, 3] > arr[:, 2]).all()):
            raise ConfigError("bracket.error_map", "cells need finite x0 < x1 and y0 < y1")
        if (arr[:, 4] < 0).any() or np.isnan(arr[:, 4]).any():
            raise ConfigError("bracket.error_map", "eps_bar must be >= 0 (inf: not certified)")
        self.cells = arr
        self.name = "certified map"
        self._index = None

    def __call__(self, points, boxes=None, frame=None) -> np.ndarray:
        """The largest `eps_bar` over table cells meeting each grid cell (its world bounding box: sound)."""
        if boxes is None:
            raise ValueError("a cell table needs the grid cells")
        C = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], axis=1)
        W = frame.to_world(C.reshape(-1, 2)).reshape(-1, 4, 2) if frame is not None else C
        lo, hi = W.min(axis=1), W.max(axis=1)
        t = self.cells
        out = np.full(len(boxes), -np.inf)
        covered = np.zeros(len(boxes))
        area = (hi[:, 0] - lo[:, 0]) * (hi[:, 1] - lo[:, 1])
        for s in range(0, len(t), 4096):
            tt = t[s:s + 4096]
            ox = np.minimum(hi[:, None, 0], tt[None, :, 1]) - np.maximum(lo[:, None, 0], tt[None, :, 0])
            oy = np.minimum(hi[:, None, 1], tt[None, :, 3]) - np.maximum(lo[:, None, 1], tt[None, :, 2])
            meet = (ox >= 0) & (oy >= 0)
            out = np.maximum(out, np.where(meet, tt[None, :, 4], -np.inf).max(axis=1))
            covered += (np.clip(ox, 0, None) * np.clip(oy, 0, None)).sum(axis=1)
        out[covered < area * (1 - 1e-9)] = np.inf  # part of the cell has no bound
        return out

    def at(self, points: np.ndarray) -> np.ndarray:
        """The bound at each point `(N, 2)`: the smallest `eps_bar` of the cells whose closed box holds it (`inf`:
        none). The cells are bucketed on a grid of their median width, so a point meets only its bucket's cells."""
        if self._index is None:
            self._index = _BucketIndex(self.cells)
        return self._index.smallest(np.asarray(points, float).reshape(-1, 2))


class Finest:
    """`ε̄` from several cell tables of one perception map: per grid cell the smallest of their bounds (each table
    is sound where it covers the cell, `inf` where it does not)."""

    def __init__(self, tables: list[CellTable]):
        self.tables = list(tables)
        self.name = "certified maps"

    @property
    def cells(self) -> np.ndarray:
        """Every table's rows with its index as a sixth column (what the bracket's id hashes)."""
        return np.concatenate([np.column_stack([t.cells, np.full(len(t.cells), i)]) for i, t in enumerate(self.tables)])

    def __call__(self, points, boxes=None, frame=None) -> np.ndarray:
        return np.min([t(points, boxes, frame) for t in self.tables], axis=0)

    def at(self, points: np.ndarray) -> np.ndarray:
        """The smallest of the tables' bounds at each point (`inf`: no table covers it)."""
        return np.min([t.at(points) for t in self.tables], axis=0)


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
