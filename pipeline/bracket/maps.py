"""The perception maps the bracket reads (docs/bracket.md): the certified error map's tables as `ε̄`
(`bracket.error_map`, at the pixel budget `bracket.error_map_kappa`) and the camera falsifier's map
(`bracket.camera_map`), resolved as every tracked input and checked before any work: one line naming the field."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from pipeline import lineage, tracking
from pipeline.bracket.bounds import CellTable, Finest
from pipeline.bracket.clouds import check_alone, clouds_folder, clouds_table
from pipeline.config import build
from pipeline.errors import ConfigError, DatasetError


def error_map(cfg: DictConfig, bs, arena=None, camera_folder: Path | None = None):
    """`bracket.error_map` as `ε̄` (None: not set): a cell table, or a certify output (folder, name-id or id)
    resolved as every tracked input, its table at `bracket.error_map_kappa`; several (a list): :class:`Finest`,
    all of one perception map, the map of `camera_folder` when given (`bracket.camera_map`). `arena`: the camera's
    (a grid cell's bound is over its part inside). A clouds output (under `certified_dir/clouds`): its
    `eps_bar_delta`, alone (:mod:`.clouds`)."""
    refs = [bs.error_map] if isinstance(bs.error_map, str) else list(bs.error_map or [])
    tables, models = [], set()
    for item in refs:
        ref = _resolve(Path(cfg.paths.certified_dir), item)
        if (clouds := clouds_folder(ref)) is not None:
            check_alone(len(refs), bs.error_map_kappa, camera_folder)
            gated = bool(getattr(bs, "error_map_gated", False))
            return clouds_table(clouds, arena, gated, cfg.camera.gate if gated else None)
        summary = (ref if ref.is_dir() else ref.parent) / "summary.json"
        if summary.is_file():  # a certify output: the perception map it bounds
            models.add(str(json.loads(summary.read_text())["model"]["id"]))
        if bs.error_map_kappa > 0 and ref.is_file() and ref.name != f"error_map_kappa{bs.error_map_kappa:g}.csv":
            raise ConfigError("bracket.error_map_kappa", f"{ref.name} is not a certify output's table at kappa "
                                                         f"{bs.error_map_kappa:g} (error_map_kappa{bs.error_map_kappa:g}"
                                                         ".csv, or its folder): nothing vouches for the pixel budget")
        tables.append(CellTable(ref, arena=arena, kappa=bs.error_map_kappa))
    if len(models) > 1:
        raise ConfigError("bracket.error_map", f"the tables bound different perception maps ({', '.join(sorted(models))}):"
                                               " the smallest bound per cell holds for one map only")
    if getattr(bs, "error_map_gated", False):
        raise ConfigError("bracket.error_map_gated", "reads a clouds output's gated column (make certify-clouds); "
                                                     "bracket.error_map names none")
    if not tables:
        return None
    if camera_folder is not None and models:  # the camera's κ_lo is the certificate of the map it attacks
        camera_id = str(tracking.read_manifest(camera_folder).get("id"))
        if camera_id not in models:
            raise ConfigError("bracket.error_map", f"bounds perception map {', '.join(sorted(models))}, and "
                                                   f"bracket.camera_map is {camera_folder.name} (id {camera_id}): the "
                                                   "camera's certified budget must be the attacked map's")
    return tables[0] if len(tables) == 1 else Finest(tables)


def _resolve(root: Path, item: str) -> Path:
    """A table file as it is; else a certify output (folder, name-id or id) under `root`, or a clouds output under
    `root/clouds`; one line naming `bracket.error_map` when neither holds it."""
    ref = Path(item)
    if ref.is_file():
        return ref
    try:
        return tracking.resolve(root, item, kind="certified error map", field="bracket.error_map",
                                expected=lambda name: None)
    except DatasetError as err:
        if (root / "clouds").is_dir() and os.sep not in item and not ref.is_dir():
            try:
                return tracking.resolve(root / "clouds", item, kind="certified error map under clouds",
                                        field="bracket.error_map", expected=lambda name: None)
            except DatasetError:
                pass
        raise ConfigError("bracket.error_map", str(err)) from None


def camera_map_folder(cfg: DictConfig, bs, scene) -> Path | None:
    """The folder of `bracket.camera_map` (None: not set), checked: a position map rendering the bracket's scene."""
    if bs.camera_map is None:
        return None
    if scene.n_obstacles != 1:
        raise ConfigError("bracket.camera_map", f"the camera falsifier renders one obstacle; scene {scene.name!r} has "
                                                f"{scene.n_obstacles}: null here")
    try:
        folder = lineage.resolve_map(bs.camera_map, cfg.paths.models_dir, field="bracket.camera_map",
                                     overrides=lineage.debug_overrides(cfg))
    except DatasetError as err:
        raise ConfigError("bracket.camera_map", str(err).splitlines()[0]) from None
    m = tracking.read_manifest(folder)
    if (m.get("model") or {}).get("outputs") == "pose":
        raise ConfigError("bracket.camera_map", f"{folder.name} is a pose map: the bracket's loop is the single "
                                                "integrator (a position map)")
    if "scene" not in m or "render" not in m:
        raise ConfigError("bracket.camera_map", f"{folder.name}'s manifest has no scene or render config")
    seen = build(m["scene"], "scene")
    same = (np.allclose(seen.p_T, scene.p_T) and seen.n_obstacles == scene.n_obstacles
            and np.allclose(seen.p_0, scene.p_0) and np.isclose(seen.obstacle_radius, scene.obstacle_radius)
            and np.allclose(seen.bounds, scene.bounds))
    if not same:
        raise ConfigError("bracket.camera_map", f"{folder.name} renders another scene (target {list(seen.p_T)}, "
                                                f"arena {seen.bounds}) than the bracket's (target {list(scene.p_T)}, "
                                                f"arena {scene.bounds})")
    return folder
