"""The error bound `ε̄` the certificate takes (SPEC §5.3-5.4): uniform, or the certified error map's cell table.

A table (CSV or parquet) with one row per cell of positions: `x0, x1, y0, y1, eps_bar` (world units; the
certified error map of `pipeline.certify` writes one per `kappa`, `error_map_kappa<κ>.csv`), or a certify output's
folder (its `kappa = 0` table); `bracket.error_map` also takes the folder's `name-id` under `paths.certified_dir`. A grid cell of the abstraction gets the largest
`eps_bar` of the table cells it meets; a grid cell that no table cell covers gets `inf` (it cannot be
certified), so a map certified only on part of the arena certifies only runs that stay there. Several tables of one
perception map (:class:`Finest`: the whole operational set, and a region certified again with finer splitting)
each bound the error soundly where they cover it, so a grid cell takes the smallest of their bounds.
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
