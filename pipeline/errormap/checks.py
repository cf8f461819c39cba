"""The errormap stage's preflight: its settings, the cloud levels, and every map resolved by id (not loaded)."""

from __future__ import annotations

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.config import settings
from pipeline.errormap.settings import ErrorMapSettings
from pipeline.errors import DatasetError, ModelError
from pipeline.lineage import debug_overrides, resolve_map
from pipeline.render import load_occlusion


def check(cfg: DictConfig) -> ErrorMapSettings:
    s = settings(cfg, ErrorMapSettings)
    for lv in s.occlusion_levels:
        load_occlusion(lv, cfg.occlusions, field="occlusion_levels")
    maps = tracking.to_plain(cfg.get("maps"))
    for ref in maps if isinstance(maps, list) else [maps]:
        try:
            resolve_map(ref, cfg.paths.models_dir, overrides=debug_overrides(cfg))
        except DatasetError as err:
            raise ModelError(str(err)) from None
    return s
