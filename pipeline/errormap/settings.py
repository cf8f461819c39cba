"""The errormap stage's settings (the root keys of conf/errormap.yaml), typed; docs/errormap.md describes each."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from pipeline.schema import (
    Device,
    NonEmpty,
    NonNegative,
    NonNegativeInt,
    Pair,
    Positive,
    PositiveInt,
    checked,
)


@checked("grid")
@dataclass(frozen=True)
class Grid:
    step: Positive = 0.5  # world units


@checked("coverage")
@dataclass(frozen=True)
class Coverage:
    """Assumption 1's coverage set: radius `r_cov` (null: unlimited), which estimate of `L` enters it, the ε sweep
    and the ε values whose coverage sets are drawn."""

    r_cov: Positive | None = 2.0
    lipschitz: Literal["max", "p99"] = "max"
    eps: Annotated[list[NonNegative], NonEmpty()] | None = None
    eps_marks: list[NonNegative] | None = None


@checked("dean")
@dataclass(frozen=True)
class Dean:
    """The error model of Dean et al.: `|e|_inf <= eps_C |p|_inf + eps_eta` from the origin or the target."""

    center: Literal["origin", "target"] | Pair = "origin"
    eps_C: list[NonNegative] = field(default_factory=lambda: [0.0, 0.005, 0.01, 0.02, 0.05, 0.1])


@checked("")
@dataclass(frozen=True)
class ErrorMapSettings:
    maps: str | Annotated[list[str], NonEmpty()] = field(default_factory=lambda: ["clean_keypoint", "occluded_keypoint"])
    occlusion_levels: str | Annotated[list[str], NonEmpty(distinct=True)] = field(
        default_factory=lambda: ["none", "heavy"])
    grid: Grid = field(default_factory=Grid)
    operational_margin: Literal["auto"] | NonNegative = "auto"
    near_target_radius: Positive = 5.0
    draws: PositiveInt = 1
    headings: PositiveInt = 8
    clouds: Literal["independent", "shared"] = "independent"
    seed: NonNegativeInt = 0
    batch: PositiveInt = 2048
    train_samples: PositiveInt | None = 24000
    coverage: Coverage = field(default_factory=Coverage)
    dean: Dean = field(default_factory=Dean)
    distance_bins: PositiveInt = 12
    formats: Annotated[list[Literal["png", "pdf", "svg"]], NonEmpty()] = field(default_factory=lambda: ["png", "pdf"])
    force: bool = False
    device: Device = "auto"
    progress: bool = True

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        for k, cls in (("grid", Grid), ("coverage", Coverage), ("dean", Dean)):
            v = getattr(self, k)
            if isinstance(v, dict):
                set_(k, cls(**v))
        set_("occlusion_levels", [self.occlusion_levels] if isinstance(self.occlusion_levels, str)
             else list(self.occlusion_levels))
