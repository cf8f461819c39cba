"""The train stage's preflight: every config value and the dataset the config trains on, without torch.

The model, DataModule, Trainer, callbacks and loggers are `_target_` nodes: their keys are checked with the
config (Lightning's own signatures read from source, :mod:`pipeline.schema`), their values by their constructors
when the job builds them (:func:`pipeline.train.stage.run`, before any training).
"""

from __future__ import annotations

from pipeline.config import build, settings
from pipeline.data import open_dataset
from pipeline.errors import ConfigError
from pipeline.lineage import debug_overrides, resolve_dataset, train_dataset_id
from pipeline.render import occlusion_levels
from pipeline.train.settings import TrainSettings


def check(cfg) -> TrainSettings:
    """Preflight: the stage's settings, the cloud levels it evaluates on, and its dataset (by id) must be built."""
    s = check_settings(cfg)
    name, id_ = train_dataset_id(cfg)
    # resolved with the run's debug level: a missing dataset's hint is the command that renders this one
    open_dataset(resolve_dataset(f"{name}-{id_}", cfg.paths.datasets_dir, debug_overrides(cfg)),
                 datasets_dir=cfg.paths.datasets_dir)
    return s


def check_settings(cfg) -> TrainSettings:
    """Every value of a train config that can be checked before its dataset exists."""
    s = settings(cfg, TrainSettings)
    known = occlusion_levels(cfg.occlusions)
    for lv in s.eval_levels:
        if lv not in known:
            raise ConfigError("eval_levels", f"unknown occlusion level {lv!r}; known: {', '.join(known)}")
    if cfg.get("uncertainty_eval") is not None:
        build(cfg.uncertainty_eval, "uncertainty_eval")
    if cfg.get("certified") is not None:
        build(cfg.certified, "certified")
    me = cfg.trainer.get("max_epochs")
    if me is not None and (isinstance(me, bool) or not isinstance(me, int) or me <= 0):
        raise ConfigError("trainer.max_epochs", f"must be a positive integer, got {me!r}")
    return s
