"""The train stage's own settings (the root keys of conf/train.yaml) and the flag evaluation (`uncertainty_eval`),
typed: no torch here, so they are checked in the preflight."""

from __future__ import annotations

from dataclasses import dataclass, field

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class UncertaintyEval:
    """Maps with an uncertainty head: how well "predicted error > gate_px" flags frames whose real error exceeds
    `error_px`, and the gate that flags `clean_false_alarm` of the clean images' good frames, fitted on the
    validation positions and `gate_per_val` fresh positions per validation image with a one-sided upper bound at
    `gate_confidence` (0.5: the plain quantile); docs/train.md."""

    error_px: float = 3.0
    gate_px: float = 3.0
    clean_false_alarm: float = 0.1
    gate_per_val: int = 3
    gate_confidence: float = 0.95

    def __post_init__(self):
        for k in ("error_px", "gate_px", "clean_false_alarm"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"uncertainty_eval.{k}", f"must be a number > 0, got {getattr(self, k)!r}")
        if not self.clean_false_alarm < 1:
            raise ConfigError("uncertainty_eval.clean_false_alarm",
                              f"must be a share in (0, 1), got {self.clean_false_alarm!r}")
        if self.gate_per_val < 0:
            raise ConfigError("uncertainty_eval.gate_per_val", f"must be an integer >= 0, got {self.gate_per_val!r}")
        if not 0.5 <= self.gate_confidence < 1:
            raise ConfigError("uncertainty_eval.gate_confidence",
                              f"must be a confidence in [0.5, 1), got {self.gate_confidence!r}")


@dataclass(frozen=True)
class TrainSettings:
    """The root keys of a train config (conf/train.yaml documents each)."""

    dataset: str | None = None
    verify_dataset: bool = True
    name: str | None = None
    seed: int = 0
    force: bool = False
    eval_levels: list[str] = field(default_factory=lambda: ["none", "light", "medium", "heavy", "authors"])
    eval_seed: int = 123
    uncertainty_eval: dict | None = None
    device: str = "auto"
    num_threads: int | None = None
    optimized_metric: str | None = None

    def __post_init__(self):
        if self.seed < 0:
            raise ConfigError("seed", f"must be an integer >= 0, got {self.seed!r}")
        if self.num_threads is not None and self.num_threads < 1:
            raise ConfigError("num_threads", f"must be an integer >= 1 (or null: all cores), got {self.num_threads!r}")
        n = self.name
        if n is not None and (not n or "/" in n or "\\" in n or n.startswith(".")):
            raise ConfigError("name", f"must be a non-empty name without '/', '\\' or a leading '.', got {n!r}")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError("device", f"must be auto, cpu, cuda or cuda:N, got {self.device!r}")
