"""Writing a dataset: every split's images rendered into memory-mapped shards, the labels table, the preview.

The positions and cloud choices come from :func:`pipeline.data.sampling.plan_split` (drawn before rendering, so
the bytes depend on the recipe and seed only); the camera renders them in chunks straight into the shard.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.data.dataset import open_dataset
from pipeline.data.recipe import SPLITS
from pipeline.data.sampling import plan_split
from pipeline.errors import DatasetError
from pipeline.progress import progress
from pipeline.render import save_png

LABELS = "labels.csv"
PREVIEW = "preview.png"
LABEL_COLUMNS = ["split", "index", "x", "y", "follower_x", "follower_y", "occluded_frac", "leader_alpha"]


def label_columns(recipe) -> list[str]:
    """The labels table's columns (a recipe with headings adds `heading`, radians)."""
    return LABEL_COLUMNS + (["heading"] if recipe.headings else [])


def shard_name(split: str) -> str:
    return f"images_{split}.npy"


def _progress(total: int, desc: str):
    return progress(total=total, desc=desc, unit="img", unit_scale=True)  # a bar on a terminal, lines in a log


def _parent_train(p):
    """The parent's train images (memory map, re-hashed first: its bytes go into this dataset) and labels."""
    parent = open_dataset(p.parent_path, verify=True)
    labels = parent.labels[parent.labels["split"] == "train"][label_columns(p.recipe)]
    if len(labels) != p.parent_train:
        raise DatasetError(f"{p.parent_path}: {len(labels)} train labels, manifest {p.parent_train}")
    return parent.images("train"), labels.reset_index(drop=True)


def render_into(folder: Path, p, perception_map=None) -> pd.DataFrame:
    """Render every split into `folder` (shards, labels, preview); returns the labels table. With a parent, the
    train split starts with the parent's train images and labels (copied), then the new draws."""
    cam, rec = p.camera, p.recipe
    tables = []
    preview = None
    with _progress(sum(p.counts.values()), f"data {rec.name}") as bar:
        for split in SPLITS:
            sp = plan_split(rec, split, cam, p.occlusion, perception_map)
            n0 = p.parent_train if split == "train" else 0
            n = n0 + len(sp)
            images = np.lib.format.open_memmap(folder / shard_name(split), mode="w+", dtype=np.uint8,
                                               shape=(n, cam.height, cam.width, 3))
            if n0:
                src, old = _parent_train(p)
                for s in range(0, n0, rec.chunk_size):
                    e = min(s + rec.chunk_size, n0)
                    images[s:e] = src[s:e]
                    bar.update(e - s)
                tables.append(old)
                del src
            frac = np.zeros(len(sp), dtype=np.float32)
            lead_alpha = np.zeros(len(sp), dtype=np.float32)
            for s in range(0, len(sp), rec.chunk_size):
                e = min(s + rec.chunk_size, len(sp))
                res = cam.render(sp.leader[s:e], sp.follower[s:e], p.occlusion, clouds=sp.clouds[s:e],
                                 heading=None if sp.heading is None else sp.heading[s:e],
                                 out=images[n0 + s : n0 + e], return_info=True)
                frac[s:e], lead_alpha[s:e] = res.occluded_frac, res.leader_alpha
                bar.update(e - s)
            if split == "train":  # the new draws (a parent's images are in its own preview)
                preview = np.array(images[n0 : n0 + rec.preview])
            images.flush()
            del images
            table = pd.DataFrame({
                "split": split, "index": np.arange(n0, n),
                "x": sp.leader[:, 0], "y": sp.leader[:, 1],
                "follower_x": sp.follower[:, 0], "follower_y": sp.follower[:, 1],
                "occluded_frac": frac, "leader_alpha": lead_alpha,
            })
            if sp.heading is not None:
                table["heading"] = sp.heading
            tables.append(table)
    labels = pd.concat(tables, ignore_index=True)[label_columns(rec)]
    labels.to_csv(folder / LABELS, index=False, float_format="%.9g", lineterminator="\n")
    save_png(folder / PREVIEW, cam.preview_grid(preview, cols=8), upscale=2)
    return labels
