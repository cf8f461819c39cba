"""Stage: render a tracked camera dataset (`python -m pipeline.data data=<recipe>`, `make data`).

Output: `<paths.datasets_dir>/<name>-<id>/` with `images_<split>.npy` (uint8 (n, H, W, 3), memory-mappable),
`labels.csv`, `preview.png` and `manifest.json` (see docs/data.md). The id hashes the recipe (minus
volatile keys), the visible scene, the render and occlusion configs and the render/data code version.
"""

from __future__ import annotations

import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.data.sampling import SPLITS, VOLATILE, Recipe, plan_split
from pipeline.errors import ConfigError, DatasetError
from pipeline.render import Camera, Occlusion, load_occlusion, save_png
from pipeline.sim.build import build_scene

LABELS = "labels.csv"
PREVIEW = "preview.png"
CODE = ("render", "data/sampling", "data/stage")  # the code that determines the bytes
LABEL_COLUMNS = ["split", "index", "x", "y", "follower_x", "follower_y", "occluded_frac", "leader_alpha"]


def shard_name(split: str) -> str:
    return f"images_{split}.npy"


@dataclass
class Plan:
    """A validated dataset request: what to render and where."""

    recipe: Recipe
    recipe_cfg: dict
    scene_cfg: dict
    render_cfg: dict
    camera: Camera
    occlusion: Occlusion
    id: str
    root: Path

    @property
    def folder_name(self) -> str:
        return f"{self.recipe.name}-{self.id}"

    @property
    def path(self) -> Path:
        return self.root / self.folder_name

    def meta(self) -> dict:
        return {
            "kind": "dataset",
            "recipe": self.recipe_cfg,
            "seed": self.recipe.seed,
            "counts": dict(self.recipe.splits),
            "image_shape": [self.camera.height, self.camera.width, 3],
            "scene": self.scene_cfg,
            "render": self.render_cfg,
            "occlusion": self.occlusion.config(),
            "code_version": tracking.code_version(*code_modules(self.recipe)),
            "volatile": list(VOLATILE),
            "shards": {s: shard_name(s) for s in SPLITS},
            "labels": LABELS,
            "label_columns": LABEL_COLUMNS,
            "color_order": "RGB",
        }


def code_modules(recipe: Recipe) -> tuple[str, ...]:
    """The code that determines a dataset's bytes: closed-loop sampling also runs the simulator."""
    return CODE + (("sim", "control") if recipe.mode == "closed_loop" else ())


def _visible_scene(scene_cfg: dict) -> dict:
    """The parts of the scene that appear in the image (barrier settings do not change the bytes)."""
    obstacle = scene_cfg.get("obstacle") or {}
    return {"target": scene_cfg.get("target"), "obstacle": {k: obstacle.get(k) for k in ("center", "radius")}}


def plan(cfg: DictConfig) -> Plan:
    """Validate the whole config (raises ConfigError naming the field) and compute the dataset id."""
    recipe_cfg = tracking.to_plain(cfg.data)
    recipe = Recipe.from_config(recipe_cfg)
    occlusion = load_occlusion(recipe.occlusion, cfg.occlusions, field="data.occlusion")
    scene_cfg = tracking.to_plain(cfg.scene)
    render_cfg = tracking.to_plain(cfg.render)
    camera = Camera.from_config(render_cfg, build_scene(cfg.scene), arena=None)
    render_cfg = {**render_cfg, "arena": [list(camera.arena[0]), list(camera.arena[1])]}
    id_ = tracking.content_id(
        {
            "recipe": tracking.strip_keys(recipe_cfg, VOLATILE),
            "scene": _visible_scene(scene_cfg),
            "render": render_cfg,
            "occlusion": occlusion.config(),
            "code": tracking.code_version(*code_modules(recipe)),
        }
    )
    return Plan(recipe, recipe_cfg, scene_cfg, render_cfg, camera, occlusion, id_, Path(cfg.paths.datasets_dir))


def _progress(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="img", unit_scale=True, disable=None, file=sys.stderr, leave=False)


def render_into(folder: Path, p: Plan) -> pd.DataFrame:
    """Render every split into `folder` (shards, labels, preview); returns the labels table."""
    cam, rec = p.camera, p.recipe
    tables = []
    preview = None
    with _progress(sum(rec.splits.values()), f"data {rec.name}") as bar:
        for split in SPLITS:
            sp = plan_split(rec, split, cam, p.occlusion)
            n = len(sp)
            images = np.lib.format.open_memmap(folder / shard_name(split), mode="w+", dtype=np.uint8,
                                               shape=(n, cam.height, cam.width, 3))
            frac = np.zeros(n, dtype=np.float32)
            lead_alpha = np.zeros(n, dtype=np.float32)
            for s in range(0, n, rec.chunk_size):
                e = min(s + rec.chunk_size, n)
                res = cam.render(sp.leader[s:e], sp.follower[s:e], p.occlusion, clouds=sp.clouds[s:e],
                                 out=images[s:e], return_info=True)
                frac[s:e], lead_alpha[s:e] = res.occluded_frac, res.leader_alpha
                bar.update(e - s)
            if split == "train":
                preview = np.array(images[: rec.preview])
            images.flush()
            del images
            tables.append(pd.DataFrame({
                "split": split, "index": np.arange(n),
                "x": sp.leader[:, 0], "y": sp.leader[:, 1],
                "follower_x": sp.follower[:, 0], "follower_y": sp.follower[:, 1],
                "occluded_frac": frac, "leader_alpha": lead_alpha,
            }))
    labels = pd.concat(tables, ignore_index=True)[LABEL_COLUMNS]
    labels.to_csv(folder / LABELS, index=False, float_format="%.9g", lineterminator="\n")
    save_png(folder / PREVIEW, cam.preview_grid(preview, cols=8), upscale=2)
    return labels


def run(cfg: DictConfig) -> dict:
    """Render the dataset of `cfg.data` unless a valid one with the same id exists (`force=true` re-renders).

    Returns `{"id", "name", "path", "counts", "skipped", "seconds"}`.
    """
    t0 = time.perf_counter()
    p = plan(cfg)
    force = cfg.get("force", False)
    if not isinstance(force, bool):
        raise ConfigError("force", f"must be true or false, got {force!r}")
    out = {"id": p.id, "name": p.recipe.name, "path": p.path, "counts": dict(p.recipe.splits)}
    if p.path.exists() and not force:
        problems = tracking.verify(p.path, full=False)
        if problems:
            raise DatasetError(
                f"{p.path} exists but does not match its manifest ({problems[0]}"
                f"{f' and {len(problems) - 1} more' if len(problems) > 1 else ''}); "
                "delete it or re-render with force=true"
            )
        print(f"data: {p.folder_name} exists and matches its manifest -> {p.path} (nothing to do; force=true re-renders)")
        return {**out, "skipped": True, "seconds": time.perf_counter() - t0}
    with tracking.tracked_output(p.root, p.recipe.name, p.id, p.meta()) as tmp:
        render_into(tmp, p)
    secs = time.perf_counter() - t0
    counts = ", ".join(f"{s} {n}" for s, n in p.recipe.splits.items())
    print(f"data: {p.recipe.name} id {p.id}: {counts} images ({p.camera.height}x{p.camera.width}, "
          f"occlusion {p.occlusion.name}) in {secs:.1f} s -> {p.path}")
    return {**out, "skipped": False, "seconds": secs}
