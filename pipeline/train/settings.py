"""The train stage's typed settings: its root keys (conf/train.yaml), the flag evaluation (`uncertainty_eval`), the
batches (`datamodule`, the spec :class:`pipeline.train.datamodule.PerceptionDataModule` takes) and certified training
(`certified`). No torch here, so they are imported, checked and built in the preflight."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from pipeline.errors import ConfigError
from pipeline.schema import (
    Device,
    Name,
    NonNegative,
    NonNegativeInt,
    OpenShare,
    Positive,
    PositiveInt,
    Range,
    checked,
)


@checked("uncertainty_eval")
@dataclass(frozen=True)
class UncertaintyEval:
    """Maps with an uncertainty head: how well "predicted error > gate_px" flags frames whose real error exceeds
    `error_px`, and the gate that flags `clean_false_alarm` of the clean images' good frames, fitted on the
    validation positions and `gate_per_val` fresh positions per validation image with a one-sided upper bound at
    `gate_confidence` (0.5: the plain quantile); docs/train.md."""

    error_px: Positive = 3.0
    gate_px: Positive = 3.0
    clean_false_alarm: OpenShare = 0.1
    gate_per_val: NonNegativeInt = 3
    gate_confidence: Annotated[float, Range(ge=0.5, lt=1)] = 0.99


@checked("")
@dataclass(frozen=True)
class TrainSettings:
    """The root keys of a train config (conf/train.yaml documents each)."""

    dataset: str | None = None
    verify_dataset: bool = True
    name: Name | None = None
    seed: NonNegativeInt = 0
    force: bool = False
    eval_levels: list[str] = field(default_factory=lambda: ["none", "light", "medium", "heavy", "authors"])
    eval_seed: int = 123
    uncertainty_eval: dict | None = None
    certified: dict | None = None
    device: Device = "auto"
    num_threads: PositiveInt | None = None
    optimized_metric: str | None = None


@checked("datamodule")
@dataclass(frozen=True)
class DataModuleSpec:
    """Batches of a tracked dataset (conf/datamodule/default.yaml documents each key; the stage sets `seed`)."""

    batch_size: PositiveInt = 32
    limit_train_samples: PositiveInt | None = None
    limit_val_samples: PositiveInt | None = 2048
    eval_batch_size: PositiveInt = 512
    num_workers: NonNegativeInt = 0
    pin_memory: bool = False
    seed: int = 0


@checked("certified")
@dataclass(frozen=True)
class CertifiedTraining:
    """The certified-training term's settings (conf/certified/on.yaml documents each)."""

    weight: Positive = 5.0e-3
    target: NonNegative = 0.25
    cell: Positive = 0.0625
    cell_start: Positive = 0.01
    warmup_epochs: NonNegative = 1.0
    ramp_epochs: NonNegative = 2.0
    ibp_epochs: NonNegative = 0.0
    mode: Literal["ibp", "forward", "crown"] = "crown"
    cells_per_step: PositiveInt = 16
    kappa: NonNegative = 0.0

    def __post_init__(self):
        if self.cell_start > self.cell:
            raise ConfigError("certified.cell_start", f"must be <= cell ({self.cell!r}), got {self.cell_start!r}")

    def ramp(self, t: float) -> float:
        """The ramp's progress in [0, 1] at epoch `t` (0 during the warm-up)."""
        if t < self.warmup_epochs:
            return 0.0
        if t >= self.warmup_epochs + self.ramp_epochs:  # ramped up (also a ramp too short to add to the warm-up)
            return 1.0
        return min(1.0, (t - self.warmup_epochs) / self.ramp_epochs)

    def schedule(self, t: float) -> tuple[float, float, str]:
        """`(weight, cell side, bound mode)` at epoch `t`; weight 0 during the warm-up."""
        r = self.ramp(t)
        mode = "ibp" if t < self.warmup_epochs + self.ibp_epochs else self.mode
        return self.weight * r, self.cell_start + (self.cell - self.cell_start) * r, mode
