"""The errormap stage's settings (the root keys of conf/errormap.yaml), typed; docs/errormap.md describes each."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class Grid:
    step: float = 0.5  # world units

    def __post_init__(self):
        if not self.step > 0:
            raise ConfigError("grid.step", f"must be a number > 0 (world units), got {self.step!r}")


@dataclass(frozen=True)
class Coverage:
    """Assumption 1's coverage set: radius `r_cov` (null: unlimited), which estimate of `L` enters it, the ε sweep
    and the ε values whose coverage sets are drawn."""

    r_cov: float | None = 1.0
    lipschitz: Literal["max", "p99"] = "max"
    eps: list[float] | None = None
    eps_marks: list[float] | None = None

    def __post_init__(self):
        if self.r_cov is not None and not self.r_cov > 0:
            raise ConfigError("coverage.r_cov", f"must be > 0 or null (unlimited), got {self.r_cov!r}")
        for k in ("eps", "eps_marks"):
            v = getattr(self, k)
            if v is not None and (any(x < 0 for x in v) or (k == "eps" and not v)):
                raise ConfigError(f"coverage.{k}", f"must be a list of numbers >= 0, got {v!r}")


@dataclass(frozen=True)
class Dean:
    """The error model of Dean et al.: `|e|_inf <= eps_C |p|_inf + eps_eta` from the origin or the target."""

    center: Literal["origin", "target"] | list[float] = "origin"
    eps_C: list[float] = field(default_factory=lambda: [0.0, 0.005, 0.01, 0.02, 0.05, 0.1])

    def __post_init__(self):
        if isinstance(self.center, list) and len(self.center) != 2:
            raise ConfigError("dean.center", f"must be origin, target or a pair [x, y], got {self.center!r}")
        if any(c < 0 for c in self.eps_C):
            raise ConfigError("dean.eps_C", f"must be a list of numbers >= 0, got {self.eps_C!r}")


@dataclass(frozen=True)
class ErrorMapSettings:
    maps: str | list[str] = field(default_factory=lambda: ["clean", "occluded"])
    occlusion_levels: str | list[str] = field(default_factory=lambda: ["none", "heavy"])
    grid: Grid = field(default_factory=Grid)
    operational_margin: Literal["auto"] | float = "auto"
    near_target_radius: float = 5.0
    draws: int = 1
    headings: int = 8
    clouds: Literal["independent", "shared"] = "independent"
    seed: int = 0
    batch: int = 2048
    train_samples: int | None = 24000
    coverage: Coverage = field(default_factory=Coverage)
    dean: Dean = field(default_factory=Dean)
    distance_bins: int = 12
    formats: list[Literal["png", "pdf", "svg"]] = field(default_factory=lambda: ["png", "pdf"])
    force: bool = False
    device: str = "auto"
    progress: bool = True

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        for k, cls in (("grid", Grid), ("coverage", Coverage), ("dean", Dean)):
            v = getattr(self, k)
            if isinstance(v, dict):
                set_(k, cls(**v))
        levels = [self.occlusion_levels] if isinstance(self.occlusion_levels, str) else list(self.occlusion_levels)
        if not levels or len(set(levels)) != len(levels):
            raise ConfigError("occlusion_levels", f"must be a non-empty list of distinct level names, got {levels!r}")
        set_("occlusion_levels", levels)
        if isinstance(self.maps, list) and not self.maps:
            raise ConfigError("maps", "needs at least one perception map")
        for k in ("draws", "headings", "batch", "distance_bins"):
            if getattr(self, k) < 1:
                raise ConfigError(k, f"must be an integer >= 1, got {getattr(self, k)!r}")
        if self.train_samples is not None and self.train_samples < 1:
            raise ConfigError("train_samples", f"must be an integer >= 1 or null (all), got {self.train_samples!r}")
        if not self.near_target_radius > 0:
            raise ConfigError("near_target_radius", f"must be a number > 0 (world units), got {self.near_target_radius!r}")
        if self.operational_margin != "auto" and not self.operational_margin >= 0:
            raise ConfigError("operational_margin", f"must be auto (half the robot) or a number >= 0, "
                                                    f"got {self.operational_margin!r}")
        if not self.formats:
            raise ConfigError("formats", "must be a non-empty list of png/pdf/svg")
