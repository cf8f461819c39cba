"""What a dataset recipe says (`conf/data/*.yaml`, the `data` node): typed, key for key as in its YAML.

The keys, types and ranges are declared on the fields and checked with the config (the signature is the
schema; :func:`pipeline.schema.checked` when built from Python); the cross-field rules here.
:mod:`pipeline.data.sampling` draws what a recipe means; docs/data.md describes every key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Annotated, Literal

from hydra.utils import get_class

from pipeline.errors import ConfigError
from pipeline.schema import (
    Device,
    Name,
    Node,
    NonNegative,
    NonNegativeInt,
    Pattern,
    Positive,
    PositiveInt,
    Range,
    Share,
    checked,
)

SPLITS = ("train", "val", "test")
SamplingMode = Literal["uniform", "grid", "closed_loop"]
Ref = Annotated[str, Pattern(r"\S(?:.*\S)?", "a tracked output (name, name-id, id or path) without surrounding spaces")]


def _as(cls, value):
    return value if value is None or isinstance(value, cls) else cls(**dict(value))


@checked("data.splits")
@dataclass(frozen=True)
class Splits:
    """Images per split."""

    train: PositiveInt
    val: PositiveInt
    test: PositiveInt

    def items(self):
        return ((s, getattr(self, s)) for s in SPLITS)

    def __getitem__(self, split: str) -> int:
        return getattr(self, split)

    def __contains__(self, split: str) -> bool:
        return split in SPLITS


@checked("data.sampling.closed_loop")
@dataclass(frozen=True)
class ClosedLoopSampling:
    """Where the simulated closed loop spends its time (`sampling.mode: closed_loop`, conf/sampling/closed_loop.yaml),
    and (`map`) whose perception map is in the loop that collects the train split's positions (docs/dagger.md)."""

    controller: Annotated[dict, Node()]
    disturbance: Annotated[dict, Node()]
    share: Share = 0.5
    starts: PositiveInt = 200
    horizon: Positive = 30.0
    dt: Positive = 0.01
    camera_period: Positive | None = 0.05
    stop_at_target: bool = False
    jitter: NonNegative = 2.0
    seed: NonNegativeInt = 0
    map: str | None = None
    error_weighted: bool = False
    min_error: NonNegative = 0.0
    error_floor: Positive = 0.05
    device: Device = "cpu"

    def __post_init__(self):
        if self.error_weighted and self.map is None:
            f = "data.sampling.closed_loop"
            raise ConfigError(f"{f}.error_weighted", f"weighs positions by a map's error: needs {f}.map (a perception map)")


@checked("data.sampling")
@dataclass(frozen=True)
class Sampling:
    """Where the leader's positions are drawn: `uniform`, a `grid`, or where a `closed_loop` spends its time (half of
    them by default); `parent`: a dataset whose train split this one's extends (DAgger, docs/dagger.md)."""

    mode: SamplingMode = "uniform"
    margin: NonNegative | None = None
    exclude_obstacle: bool = False
    closed_loop: ClosedLoopSampling | None = None
    parent: Ref | None = None

    def __post_init__(self):
        object.__setattr__(self, "closed_loop", _as(ClosedLoopSampling, self.closed_loop))
        if self.mode == "closed_loop" and self.closed_loop is None:
            raise ConfigError("data.sampling.closed_loop", "mode closed_loop needs this node (conf/sampling/closed_loop.yaml)")


@checked("data.follower")
@dataclass(frozen=True)
class Follower:
    """The follower drawn as a distractor: on a share `probability` of the images, at least `min_distance` from the
    leader (within `max_distance`, null: anywhere); then `near_share` of them within `near_distance`."""

    probability: Share = 0.5
    min_distance: NonNegative = 5.0
    max_distance: float | None = None
    near_share: Share = 0.0
    near_distance: Positive = 5.0

    def __post_init__(self):
        if self.max_distance is not None and not self.max_distance > self.min_distance:
            raise ConfigError("data.follower.max_distance",
                              f"must be a number > {self.min_distance:g} (or null), got {self.max_distance!r}")


@checked("data")
@dataclass(frozen=True)
class Recipe:
    """A dataset recipe (the `data` node): name, cloud level, split sizes, seed, sampling, follower, preview."""

    name: Name
    splits: Splits
    occlusion: str = "none"
    seed: Annotated[int, Range(ge=0, le=2**63 - 1)] = 0
    sampling: Sampling = field(default_factory=Sampling)
    follower: Follower = field(default_factory=Follower)
    preview: Annotated[int, Range(ge=1, le=256)] = 32
    chunk_size: PositiveInt = 4096
    vehicle: dict | None = None  # a plant node (conf/vehicle/); a unicycle is drawn with its heading, labelled (x, y, θ)

    def __post_init__(self):
        object.__setattr__(self, "splits", _as(Splits, self.splits))
        object.__setattr__(self, "sampling", _as(Sampling, self.sampling))
        object.__setattr__(self, "follower", _as(Follower, self.follower))

    # the names the sampling code reads
    @property
    def mode(self) -> str:
        return self.sampling.mode

    @property
    def closed_loop(self) -> ClosedLoopSampling | None:
        return self.sampling.closed_loop if self.sampling.mode == "closed_loop" else None

    @property
    def parent(self) -> str | None:
        return self.sampling.parent

    @property
    def headings(self) -> bool:
        """Whether the images show a heading (a vehicle with one, SPEC §1): labels `(x, y, θ)`."""
        return self.vehicle is not None and bool(getattr(get_class(self.vehicle["_target_"]), "heading", False))

    def check_arena(self, arena) -> None:
        """A follower annulus that fits nowhere in the arena is an impossible recipe (issue 21)."""
        (x0, x1), (y0, y1) = arena
        diag = math.hypot(x1 - x0, y1 - y0)
        if self.follower.probability > 0 and self.follower.min_distance >= diag:
            raise ConfigError("data.follower.min_distance", f"{self.follower.min_distance:g} is longer than the "
                                                            f"arena's diagonal ({diag:.4g}): no follower fits")
