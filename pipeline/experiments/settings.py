"""The experiments stage's own settings (the root keys of conf/experiments.yaml), typed."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class ExperimentSettings:
    """`perception`: the camera and a learned map in the loop (`cnn`) or a perfect map (`oracle`); `maps` and
    `errormaps`: the inputs by reference (names, ids); `device` where maps run; `scale` multiplies every agent count
    (and coarsens grids below 1); `force` recomputes cached results; `publish` where figures go (false: the side
    folder | true: the paper folder | auto; docs/experiments.md)."""

    perception: Literal["cnn", "oracle"] = "cnn"
    maps: dict[str, str] = field(default_factory=dict)
    errormaps: dict[str, str | None] = field(default_factory=dict)
    device: str = "auto"
    scale: float = 1.0
    force: bool = False
    publish: Literal["auto"] | bool = False

    def __post_init__(self):
        if not self.scale > 0:
            raise ConfigError("scale", f"must be a number > 0, got {self.scale!r}")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError("device", f"must be auto, cpu, cuda or cuda:N, got {self.device!r}")
