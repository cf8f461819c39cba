"""The train stage's own settings (the root keys of conf/train.yaml) and the flag evaluation (`uncertainty_eval`),
typed: no torch here, so they are checked in the preflight."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

from pipeline.schema import Device, Name, NonNegativeInt, OpenShare, Positive, PositiveInt, Range, checked


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
