"""Stage: render a tracked camera dataset (`python -m pipeline.data data=<recipe>`, `make data`).

Output: `<paths.datasets_dir>/<name>-<id>/` with `images_<split>.npy` (uint8 (n, H, W, 3), memory-mappable),
`labels.csv`, `preview.png` and `manifest.json` (see docs/data.md). The id hashes the recipe (minus
volatile keys), the visible scene, the render and occlusion configs and the render/data code version.

Inputs by id (docs/dagger.md): `data.sampling.parent` (a dataset whose train split this one's extends: its
images and labels are copied first, the new draws appended) and `data.sampling.closed_loop.map` (the
perception map in the loop that collects the train split's closed-loop share) are resolved through
:mod:`pipeline.lineage`; their `name-id`s replace the references in the recipe (so in the id) and are listed
under `parents` in the manifest.
"""

from __future__ import annotations

import dataclasses
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.data.sampling import SPLITS, VOLATILE, Recipe, plan_split, split_pool
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
    parents: dict = field(default_factory=lambda: {"dataset": None, "map": None})  # name-id of each input
    parent_path: Path | None = None
    map_path: Path | None = None
    parent_train: int = 0  # train images copied from the parent (the first rows of the train split)

    @property
    def counts(self) -> dict:
        return {s: n + (self.parent_train if s == "train" else 0) for s, n in self.recipe.splits.items()}

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
            "counts": self.counts,
            "parents": dict(self.parents),
            **({"aggregation": {"parent_train": self.parent_train, "new_train": self.recipe.splits["train"]}}
               if self.parent_path is not None else {}),
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
    """The code that determines a dataset's bytes: closed-loop sampling also runs the simulator, and with a
    map in the loop the camera measurement and the map's inference."""
    if recipe.mode != "closed_loop":
        return CODE
    with_map = ("experiments/measure", "train/predict", "train/model") if recipe.closed_loop["map"] else ()
    return CODE + ("data/closed_loop", "sim", "control", *with_map)


def _visible_scene(scene_cfg: dict) -> dict:
    """The parts of the scene that appear in the image (barrier settings do not change the bytes)."""
    obstacle = scene_cfg.get("obstacle") or {}
    return {"target": scene_cfg.get("target"), "obstacle": {k: obstacle.get(k) for k in ("center", "radius")}}


def _inputs(recipe: Recipe, cfg, camera: Camera, render_cfg: dict, scene_cfg: dict, occlusion: Occlusion) -> dict:
    """Resolve `sampling.parent` and `sampling.closed_loop.map` by id (`pipeline.lineage`) and check that they
    fit this recipe: the parent was rendered by the same camera, scene and clouds; the map reads these images."""
    from pipeline import lineage

    out = {"parents": {"dataset": None, "map": None}, "parent_path": None, "map_path": None, "parent_train": 0}
    if recipe.parent is not None:
        f = "data.sampling.parent"
        try:
            path = lineage.resolve_dataset(recipe.parent, cfg.paths.datasets_dir)
        except DatasetError as err:
            raise ConfigError(f, str(err)) from None
        m = tracking.read_manifest(path)
        if m.get("kind", "dataset") != "dataset" or "counts" not in m:
            raise ConfigError(f, f"{path.name} is not a dataset")
        theirs = {"render": m.get("render"), "occlusion": m.get("occlusion"), "scene": _visible_scene(m.get("scene") or {})}
        mine = {"render": render_cfg, "occlusion": occlusion.config(), "scene": _visible_scene(scene_cfg)}
        other = [k for k in mine if mine[k] != theirs[k]]
        if other:
            raise ConfigError(f, f"{path.name} was rendered with another {' and '.join(other)} than this recipe "
                                 "(an aggregated train split holds one camera's images)")
        out.update(parent_path=path, parent_train=int(m["counts"]["train"]))
        out["parents"]["dataset"] = path.name
    cl = recipe.closed_loop
    if cl is not None and cl["map"] is not None:
        f = "data.sampling.closed_loop.map"
        try:
            path = lineage.resolve_map(cl["map"], cfg.paths.models_dir, field=f)
        except DatasetError as err:
            raise ConfigError(f, str(err)) from None
        m = tracking.read_manifest(path)
        want = {"image_shape": [camera.height, camera.width, 3], "arena": [list(a) for a in camera.arena]}
        got = {k: m.get(k) for k in want}
        if m.get("kind") != "perception_map" or got != want:
            raise ConfigError(f, f"{path.name} does not read this recipe's images (map {got}, camera {want})")
        from pipeline.train.predict import resolve_device

        try:
            resolve_device(cl["device"])
        except ConfigError as err:
            raise ConfigError("data.sampling.closed_loop.device", err.reason) from None
        out["map_path"] = path
        out["parents"]["map"] = path.name
    return out


def plan(cfg: DictConfig) -> Plan:
    """Validate the whole config (raises ConfigError naming the field), resolve the inputs by id and compute
    the dataset id."""
    recipe_cfg = tracking.to_plain(cfg.data)
    recipe = Recipe.from_config(recipe_cfg)
    occlusion = load_occlusion(recipe.occlusion, cfg.occlusions, field="data.occlusion")
    scene_cfg = tracking.to_plain(cfg.scene)
    render_cfg = tracking.to_plain(cfg.render)
    camera = Camera.from_config(render_cfg, build_scene(cfg.scene), arena=None)
    render_cfg = {**render_cfg, "arena": [list(camera.arena[0]), list(camera.arena[1])]}
    inputs = _inputs(recipe, cfg, camera, render_cfg, scene_cfg, occlusion)
    parents = inputs["parents"]
    if recipe.parent is not None:  # the resolved name-id, not the reference, is the recipe (and in the id)
        recipe = dataclasses.replace(recipe, parent=parents["dataset"])
        recipe_cfg["sampling"]["parent"] = parents["dataset"]
    if parents["map"] is not None:
        recipe = dataclasses.replace(recipe, closed_loop={**recipe.closed_loop, "map": parents["map"]})
        recipe_cfg["sampling"]["closed_loop"]["map"] = parents["map"]
    id_ = tracking.content_id(
        {
            "recipe": tracking.strip_keys(recipe_cfg, VOLATILE),
            "scene": _visible_scene(scene_cfg),
            "render": render_cfg,
            "occlusion": occlusion.config(),
            "code": tracking.code_version(*code_modules(recipe)),
        }
    )
    return Plan(recipe, recipe_cfg, scene_cfg, render_cfg, camera, occlusion, id_, Path(cfg.paths.datasets_dir),
                **inputs)


def _progress(total: int, desc: str):
    from tqdm import tqdm

    return tqdm(total=total, desc=desc, unit="img", unit_scale=True, disable=None, file=sys.stderr, leave=False)


def _parent_train(p: Plan):
    """The parent's train images (memory map, re-hashed first: its bytes go into this dataset) and labels."""
    from pipeline.data import open_dataset

    parent = open_dataset(p.parent_path, verify=True)
    labels = parent.labels[parent.labels["split"] == "train"][LABEL_COLUMNS]
    if len(labels) != p.parent_train:
        raise DatasetError(f"{p.parent_path}: {len(labels)} train labels, manifest {p.parent_train}")
    return parent.images("train"), labels.reset_index(drop=True)


def render_into(folder: Path, p: Plan, perception_map=None) -> pd.DataFrame:
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
                                 out=images[n0 + s : n0 + e], return_info=True)
                frac[s:e], lead_alpha[s:e] = res.occluded_frac, res.leader_alpha
                bar.update(e - s)
            if split == "train":  # the new draws (a parent's images are in its own preview)
                preview = np.array(images[n0 : n0 + rec.preview])
            images.flush()
            del images
            tables.append(pd.DataFrame({
                "split": split, "index": np.arange(n0, n),
                "x": sp.leader[:, 0], "y": sp.leader[:, 1],
                "follower_x": sp.follower[:, 0], "follower_y": sp.follower[:, 1],
                "occluded_frac": frac, "leader_alpha": lead_alpha,
            }))
    labels = pd.concat(tables, ignore_index=True)[LABEL_COLUMNS]
    labels.to_csv(folder / LABELS, index=False, float_format="%.9g", lineterminator="\n")
    save_png(folder / PREVIEW, cam.preview_grid(preview, cols=8), upscale=2)
    return labels


def _visits(p: Plan) -> tuple[object, dict]:
    """Load the recipe's map (on `closed_loop.device`) and simulate its closed loop once (the train split's
    pool, cached); returns the map and what the manifest records about its visits."""
    from pipeline.train import load_perception_map

    cl = p.recipe.closed_loop
    pm = load_perception_map(p.map_path, device=cl["device"])
    t0 = time.perf_counter()
    visits = split_pool(p.recipe, "train", p.camera, p.occlusion, pm)
    summary = visits.summary(cl)
    err = summary.get("map_error", {})
    print(f"data: {p.parents['map']} in the loop ({cl['starts']} starts, {cl['horizon']:g} s, occlusion "
          f"{p.occlusion.name}): {summary['frames']} frames, {summary['outside_view_share']:.0%} outside the camera's "
          f"view; in view, map error mean {err.get('mean', float('nan')):.2f} / p95 {err.get('p95', float('nan')):.2f} "
          f"units ({time.perf_counter() - t0:.1f} s)")
    return pm, {"closed_loop_visits": summary}


def run(cfg: DictConfig) -> dict:
    """Render the dataset of `cfg.data` unless a valid one with the same id exists (`force=true` re-renders).

    Returns `{"id", "name", "path", "counts", "parents", "skipped", "seconds"}`.
    """
    t0 = time.perf_counter()
    p = plan(cfg)
    force = cfg.get("force", False)
    if not isinstance(force, bool):
        raise ConfigError("force", f"must be true or false, got {force!r}")
    out = {"id": p.id, "name": p.recipe.name, "path": p.path, "counts": p.counts, "parents": dict(p.parents)}
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
    pm, visits = _visits(p) if p.map_path is not None else (None, {})
    with tracking.tracked_output(p.root, p.recipe.name, p.id, {**p.meta(), **visits}) as tmp:
        render_into(tmp, p, pm)
    secs = time.perf_counter() - t0
    counts = ", ".join(f"{s} {n}" for s, n in p.counts.items())
    kept = f" ({p.parent_train} train images of {p.parents['dataset']})" if p.parent_path is not None else ""
    print(f"data: {p.recipe.name} id {p.id}: {counts} images{kept} ({p.camera.height}x{p.camera.width}, "
          f"occlusion {p.occlusion.name}) in {secs:.1f} s -> {p.path}")
    return {**out, "skipped": False, "seconds": secs}
