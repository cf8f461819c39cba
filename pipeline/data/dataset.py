"""Reading a tracked camera dataset (memory-mapped splits, labels, the camera that rendered it); docs/data.md."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import lineage, tracking
from pipeline.config import build
from pipeline.errors import DatasetError
from pipeline.render import Occlusion
from pipeline.repo import REPO_ROOT


def default_datasets_dir() -> Path:
    """`paths.datasets_dir` of conf/paths/default.yaml: <repo>/data/datasets."""
    return REPO_ROOT / "data" / "datasets"


def resolve_dataset(ref, datasets_dir=None) -> Path:
    """Folder of a dataset from a path, `name-id`, an id, or a recipe name (the dataset the current
    `conf/data/<name>.yaml` renders, see :mod:`pipeline.lineage`); unknown -> DatasetError."""
    return lineage.resolve_dataset(ref, Path(datasets_dir) if datasets_dir is not None else default_datasets_dir())


class Dataset:
    """A finished dataset folder (read-only)."""

    def __init__(self, path: Path):
        self.path = Path(path)
        self.manifest: dict = tracking.read_manifest(self.path)
        if self.manifest.get("kind", "dataset") != "dataset" or "counts" not in self.manifest:
            raise DatasetError(f"{self.path}: not a dataset (manifest has no counts)")
        self.id: str = self.manifest["id"]
        self.name: str = self.manifest["name"]

    def __repr__(self) -> str:
        return f"Dataset({self.name}-{self.id}, {self.counts})"

    @property
    def recipe(self) -> dict:
        return self.manifest["recipe"]

    @property
    def counts(self) -> dict:
        return dict(self.manifest["counts"])

    @property
    def image_shape(self) -> tuple[int, int, int]:
        return tuple(self.manifest["image_shape"])

    @functools.cached_property
    def labels(self) -> pd.DataFrame:
        """All splits: split, index, x, y, follower_x, follower_y (NaN = no follower), occluded_frac,
        leader_alpha (cloud opacity over the leader's pixel)."""
        path = self.path / self.manifest.get("labels", "labels.csv")
        try:
            df = pd.read_csv(path)
        except FileNotFoundError:
            raise DatasetError(f"{path}: missing") from None
        for col in ("x", "y", "follower_x", "follower_y", "occluded_frac", "leader_alpha", "heading"):
            if col in df:
                df[col] = df[col].astype(np.float32)
        return df

    def _check_split(self, split: str) -> None:
        if split not in self.counts:
            raise DatasetError(f"{self.name}-{self.id}: no split {split!r} (has {', '.join(self.counts)})")

    def _split_labels(self, split: str):
        self._check_split(split)
        df = self.labels[self.labels["split"] == split]
        if len(df) != self.counts[split]:
            raise DatasetError(f"{self.path}: labels have {len(df)} rows for {split!r}, manifest {self.counts[split]}")
        return df

    def images(self, split: str) -> np.ndarray:
        """`uint8 (n, H, W, 3)` RGB images of a split, memory-mapped read-only."""
        self._check_split(split)
        path = self.path / self.manifest.get("shards", {}).get(split, f"images_{split}.npy")
        try:
            arr = np.load(path, mmap_mode="r")
        except FileNotFoundError:
            raise DatasetError(f"{path}: missing") from None
        except ValueError as err:
            raise DatasetError(f"{path}: unreadable shard ({err})") from None
        want = (self.counts[split], *self.image_shape)
        if arr.shape != want or arr.dtype != np.uint8:
            raise DatasetError(f"{path}: {arr.dtype} {arr.shape}, manifest says uint8 {want}")
        return arr

    def positions(self, split: str) -> np.ndarray:
        """`float32 (n, 2)` leader positions (world units): the labels."""
        return self._split_labels(split)[["x", "y"]].to_numpy(np.float32)

    def poses(self, split: str) -> np.ndarray:
        """`float32 (n, 3)` leader poses (x, y, θ): the labels of a dataset with headings."""
        df = self._split_labels(split)
        if "heading" not in df:
            raise DatasetError(f"{self.name}-{self.id}: its images show no heading (no `heading` label)")
        return df[["x", "y", "heading"]].to_numpy(np.float32)

    @property
    def has_headings(self) -> bool:
        return "heading" in self.manifest.get("label_columns", [])

    def follower(self, split: str) -> np.ndarray:
        """`float32 (n, 2)` follower positions, NaN rows where the image has no follower."""
        return self._split_labels(split)[["follower_x", "follower_y"]].to_numpy(np.float32)

    def occluded_frac(self, split: str) -> np.ndarray:
        return self._split_labels(split)["occluded_frac"].to_numpy(np.float32)

    def scene(self):
        """The `pipeline.control.Scene` the dataset was rendered with (from the scene node in its manifest)."""
        return build(self.manifest["scene"], "scene")

    def camera(self):
        """The `pipeline.render.Camera` the dataset was rendered with (same size, arena, colours)."""
        return build(self.manifest["render"], "render", scene=self.scene())

    def occlusion(self):
        """The `pipeline.render.Occlusion` level of the dataset."""
        return Occlusion(**self.manifest["occlusion"])

    def verify(self, full: bool = True) -> list[str]:
        """Problems (one line each, with the file path); empty when every file matches the manifest."""
        return tracking.verify(self.path, full=full)


def open_dataset(ref, datasets_dir=None, verify: bool = False) -> Dataset:
    """Open a dataset by recipe name (the dataset the current recipe renders), id, `name-id` or path.

    Always checks that every file of the manifest is present with its size; `verify=True` re-hashes them.
    Problems raise DatasetError listing them.
    """
    path = resolve_dataset(ref, datasets_dir)
    problems = tracking.verify(path, full=verify)
    if problems:
        raise DatasetError(f"dataset {path.name} fails verification: " + "; ".join(problems))
    return Dataset(path)


