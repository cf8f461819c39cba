"""The certify stage's settings (the root keys of conf/certify.yaml), typed; docs/certify.md describes each."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from pipeline.errors import ConfigError
from pipeline.schema import NonEmpty, NonNegative, NonNegativeInt, Positive, PositiveInt, checked


@checked("")
@dataclass(frozen=True)
class CertifySettings:
    maps: str = "clean_keypoint"
    cell: Positive = 0.25
    mode: Literal["ibp", "forward", "crown"] = "crown"
    kappas: Annotated[list[NonNegative], NonEmpty(distinct=True)] = field(default_factory=lambda: [0.0, 1.0])
    tolerance: Positive = 1.0
    max_depth: NonNegativeInt = 0
    headings: PositiveInt = 36
    samples: PositiveInt = 16
    pgd_cells: NonNegativeInt = 256
    pgd_steps: PositiveInt = 25
    operational_margin: Literal["auto"] | NonNegative = "auto"
    diamond: Literal["exclude", "include"] = "exclude"
    region: list[list[float]] | None = None
    batch: PositiveInt = 1024
    dtype: Literal["float32", "float64"] = "float32"
    float_margin: NonNegative = 0.002
    threads: PositiveInt = 1
    seed: NonNegativeInt = 0
    formats: Annotated[list[Literal["png", "pdf", "svg"]], NonEmpty()] = field(default_factory=lambda: ["png"])
    force: bool = False
    progress: bool = True
    shards: PositiveInt = 1
    shard: NonNegativeInt | None = None

    def __post_init__(self):
        if self.shard is not None and self.shard >= self.shards:
            raise ConfigError("shard", f"must be below shards ({self.shards}): shards are 0 .. {self.shards - 1}, "
                                       f"got {self.shard}")
        if self.region is not None:
            ok = len(self.region) == 2 and all(len(r) == 2 and r[0] < r[1] for r in self.region)
            if not ok:
                raise ConfigError("region", f"must be [[x0, x1], [y0, y1]] with x0 < x1 and y0 < y1, got {self.region!r}")
