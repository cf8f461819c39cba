"""What a dataset request means before anything is rendered: the recipe, its camera and clouds, its inputs by id.

:func:`plan` checks the whole config (one `ConfigError` naming the field), resolves `data.sampling.parent` and
`data.sampling.closed_loop.map` through :mod:`pipeline.lineage` (and checks that they fit the recipe) and computes
the dataset's id; it imports no torch, so it is the data stage's preflight check.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from omegaconf import DictConfig

from pipeline import identity, lineage, tracking
from pipeline.config import build
from pipeline.data.recipe import SPLITS, Recipe
from pipeline.data.render import LABELS, label_columns, shard_name
from pipeline.errors import ConfigError
from pipeline.render import Camera, Occlusion


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
            "kind": "dataset", "recipe": self.recipe_cfg, "seed": self.recipe.seed, "counts": self.counts,
            "parents": dict(self.parents),
            **({"aggregation": {"parent_train": self.parent_train, "new_train": self.recipe.splits["train"]}}
               if self.parent_path is not None else {}),
            "image_shape": [self.camera.height, self.camera.width, 3], "scene": self.scene_cfg,
            "render": self.render_cfg, "occlusion": self.occlusion.config(),
            "code_version": tracking.code_version(*identity.dataset_code(self.recipe_cfg)),
            "volatile": list(identity.DATASET_VOLATILE), "shards": {s: shard_name(s) for s in SPLITS},
            "labels": LABELS, "label_columns": label_columns(self.recipe), "color_order": "RGB",
        }


def _parent(recipe: Recipe, cfg, render_cfg: dict, scene_cfg: dict, occlusion: Occlusion) -> dict:
    """The parent dataset (resolved by :mod:`pipeline.lineage`) must have been rendered by the same camera, scene and
    clouds: an aggregated train split holds one camera's images."""
    f = "data.sampling.parent"
    path = Path(cfg.paths.datasets_dir) / recipe.parent
    m = tracking.read_manifest(path)
    if m.get("kind", "dataset") != "dataset" or "counts" not in m:
        raise ConfigError(f, f"{path.name} is not a dataset")
    theirs = {"render": m.get("render"), "occlusion": m.get("occlusion"),
              "scene": identity.visible_scene(m.get("scene") or {})}
    mine = {"render": render_cfg, "occlusion": occlusion.config(), "scene": identity.visible_scene(scene_cfg)}
    other = [k for k in mine if mine[k] != theirs[k]]
    if other:
        raise ConfigError(f, f"{path.name} was rendered with another {' and '.join(other)} than this recipe "
                             "(an aggregated train split holds one camera's images)")
    return {"parent_path": path, "parent_train": int(m["counts"]["train"])}


def _map(recipe: Recipe, cfg, camera: Camera) -> dict:
    """The map in the loop (resolved by :mod:`pipeline.lineage`) must read this recipe's images."""
    f = "data.sampling.closed_loop.map"
    path = Path(cfg.paths.models_dir) / recipe.closed_loop.map
    m = tracking.read_manifest(path)
    want = {"image_shape": [camera.height, camera.width, 3], "arena": [list(a) for a in camera.arena]}
    got = {k: m.get(k) for k in want}
    if m.get("kind") != "perception_map" or got != want:
        raise ConfigError(f, f"{path.name} does not read this recipe's images (map {got}, camera {want})")
    return {"map_path": path}


def plan(cfg: DictConfig) -> Plan:
    """Validate the whole config (ConfigError naming the field), resolve the inputs by id, compute the id."""
    name, id_, recipe_cfg, occlusion = lineage.dataset_identity(cfg)
    recipe = build(recipe_cfg, "data")  # the parents' references already resolved to name-ids
    scene_cfg, render_cfg = tracking.to_plain(cfg.scene), tracking.to_plain(cfg.render)
    camera = build(render_cfg, "render", scene=build(scene_cfg, "scene"))
    recipe.check_arena(camera.arena)
    if recipe.vehicle is not None:  # the vehicle node (its keys and values) before any work
        build(recipe.vehicle, "data.vehicle")
    inputs: dict = {"parents": {"dataset": recipe.parent, "map": recipe.closed_loop.map if recipe.closed_loop else None}}
    if recipe.parent is not None:
        inputs.update(_parent(recipe, cfg, render_cfg, scene_cfg, occlusion))
    if inputs["parents"]["map"] is not None:
        inputs.update(_map(recipe, cfg, camera))
    return Plan(recipe, recipe_cfg, scene_cfg, render_cfg, camera, occlusion, id_, Path(cfg.paths.datasets_dir),
                **inputs)


def check(cfg: DictConfig) -> Plan:
    """Preflight: the recipe, its scene, camera and clouds, and its inputs by id (nothing rendered); the run
    uses the plan (:func:`pipeline.preflight.prepared`)."""
    return plan(cfg)


