"""Tracked camera datasets: the recipes, the `data` stage (`python -m pipeline.data`) and the reader.

    from pipeline.data import open_dataset
    ds = open_dataset("clean")              # the current recipe's dataset, or an id, `clean-<id>`, or a path
    x = ds.images("train")                  # uint8 (n, 60, 100, 3) memory map, RGB
    y = ds.positions("train")               # float32 (n, 2) leader positions, world units
    cam = ds.camera()                       # the Camera the dataset was rendered with

Folder layout and recipes: docs/data.md.
"""

from pipeline.data.dataset import Dataset, default_datasets_dir, open_dataset, resolve_dataset
from pipeline.data.recipe import SPLITS, Recipe

__all__ = ["SPLITS", "Dataset", "Recipe", "default_datasets_dir", "open_dataset", "resolve_dataset"]
