"""The certify stage's preflight: its settings and the map resolved by id (not loaded)."""

from __future__ import annotations

from omegaconf import DictConfig

from pipeline.certify.settings import CertifySettings
from pipeline.config import settings
from pipeline.errors import DatasetError, ModelError
from pipeline.lineage import debug_overrides, resolve_map


def check(cfg: DictConfig) -> CertifySettings:
    s = settings(cfg, CertifySettings)
    try:
        resolve_map(cfg.maps, cfg.paths.models_dir, overrides=debug_overrides(cfg))
    except DatasetError as err:
        raise ModelError(str(err)) from None
    return s
