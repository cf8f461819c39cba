"""What a dataset recipe says (`conf/data/*.yaml`, the `data` node): typed, key for key as in its YAML.

The keys and types are checked with the config (the signature is the schema); the ranges and cross-field rules
here. :mod:`pipeline.data.sampling` draws what a recipe means; docs/data.md describes every key.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from pipeline.errors import ConfigError

SPLITS = ("train", "val", "test")
SamplingMode = Literal["uniform", "grid", "closed_loop"]
Device = str  # auto | cpu | cuda | cuda:N (checked below; the device itself where a map runs)


def _as(cls, value):
    return value if value is None or isinstance(value, cls) else cls(**dict(value))


@dataclass(frozen=True)
class Splits:
    """Images per split."""

    train: int
    val: int
    test: int

    def __post_init__(self):
        for s in SPLITS:
            if getattr(self, s) < 1:
                raise ConfigError(f"data.splits.{s}", f"must be an integer >= 1, got {getattr(self, s)!r}")

    def items(self):
        return ((s, getattr(self, s)) for s in SPLITS)

    def __getitem__(self, split: str) -> int:
        return getattr(self, split)

    def __contains__(self, split: str) -> bool:
        return split in SPLITS


@dataclass(frozen=True)
class ClosedLoopSampling:
    """Where the simulated closed loop spends its time (`sampling.mode: closed_loop`, conf/sampling/closed_loop.yaml),
    and (`map`) whose perception map is in the loop that collects the train split's positions (docs/dagger.md)."""

    controller: dict
    disturbance: dict
    share: float = 0.5
    starts: int = 200
    horizon: float = 30.0
    dt: float = 0.01
    camera_period: float | None = 0.05
    stop_at_target: bool = False
    jitter: float = 2.0
    seed: int = 0
    map: str | None = None
    error_weighted: bool = False
    min_error: float = 0.0
    error_floor: float = 0.05
    device: Device = "cpu"

    def __post_init__(self):
        f = "data.sampling.closed_loop"
        if not 0 <= self.share <= 1:
            raise ConfigError(f"{f}.share", f"must be a number >= 0 and <= 1, got {self.share!r}")
        if self.starts < 1:
            raise ConfigError(f"{f}.starts", f"must be an integer >= 1, got {self.starts!r}")
        for k in ("horizon", "dt"):
            if not getattr(self, k) > 0:
                raise ConfigError(f"{f}.{k}", f"must be a number > 0, got {getattr(self, k)!r}")
        if self.camera_period is not None and not self.camera_period > 0:
            raise ConfigError(f"{f}.camera_period", f"must be a number > 0 (or null), got {self.camera_period!r}")
        for k in ("jitter", "min_error"):
            if not getattr(self, k) >= 0:
                raise ConfigError(f"{f}.{k}", f"must be a number >= 0, got {getattr(self, k)!r}")
        if self.seed < 0:
            raise ConfigError(f"{f}.seed", f"must be an integer >= 0, got {self.seed!r}")
        if not self.error_floor > 0:
            raise ConfigError(f"{f}.error_floor", f"must be a number > 0, got {self.error_floor!r}")
        if self.error_weighted and self.map is None:
            raise ConfigError(f"{f}.error_weighted", f"weighs positions by a map's error: needs {f}.map (a perception map)")
        if not (self.device in ("auto", "cpu", "cuda") or self.device.startswith("cuda:")):
            raise ConfigError(f"{f}.device", f"must be auto, cpu, cuda or cuda:N, got {self.device!r}")
        for k in ("controller", "disturbance"):
            if "_target_" not in getattr(self, k):
                raise ConfigError(f"{f}.{k}", "needs a composed node with `_target_` (conf/controller/, conf/disturbance/)")


@dataclass(frozen=True)
class Sampling:
    """Where the leader's positions are drawn: `uniform`, a `grid`, or where a `closed_loop` spends its time (half of
    them by default); `parent`: a dataset whose train split this one's extends (DAgger, docs/dagger.md)."""

    mode: SamplingMode = "uniform"
    margin: float | None = None
    exclude_obstacle: bool = False
    closed_loop: ClosedLoopSampling | None = None
    parent: str | None = None

    def __post_init__(self):
        object.__setattr__(self, "closed_loop", _as(ClosedLoopSampling, self.closed_loop))
        if self.margin is not None and not self.margin >= 0:
            raise ConfigError("data.sampling.margin", f"must be a number >= 0 (or null), got {self.margin!r}")
        if self.mode == "closed_loop" and self.closed_loop is None:
            raise ConfigError("data.sampling.closed_loop", "mode closed_loop needs this node (conf/sampling/closed_loop.yaml)")
        if self.parent is not None and (not self.parent.strip() or self.parent != self.parent.strip()):
            raise ConfigError("data.sampling.parent", f"must name a tracked output or be null, got {self.parent!r}")


@dataclass(frozen=True)
class Follower:
    """The follower drawn as a distractor: on a share `probability` of the images, at least `min_distance` from the
    leader (within `max_distance`, null: anywhere); then `near_share` of them within `near_distance`."""

    probability: float = 0.5
    min_distance: float = 5.0
    max_distance: float | None = None
    near_share: float = 0.0
    near_distance: float = 5.0

    def __post_init__(self):
        for k in ("probability", "near_share"):
            if not 0 <= getattr(self, k) <= 1:
                raise ConfigError(f"data.follower.{k}", f"must be a number >= 0 and <= 1, got {getattr(self, k)!r}")
        if not self.min_distance >= 0:
            raise ConfigError("data.follower.min_distance", f"must be a number >= 0, got {self.min_distance!r}")
        if self.max_distance is not None and not self.max_distance > self.min_distance:
            raise ConfigError("data.follower.max_distance",
                              f"must be a number > {self.min_distance:g} (or null), got {self.max_distance!r}")
        if not self.near_distance > 0:
            raise ConfigError("data.follower.near_distance", f"must be a number > 0, got {self.near_distance!r}")


@dataclass(frozen=True)
class Recipe:
    """A dataset recipe (the `data` node): name, cloud level, split sizes, seed, sampling, follower, preview."""

    name: str
    splits: Splits
    occlusion: str = "none"
    seed: int = 0
    sampling: Sampling = field(default_factory=Sampling)
    follower: Follower = field(default_factory=Follower)
    preview: int = 32
    chunk_size: int = 4096
    vehicle: dict | None = None  # a plant node (conf/vehicle/); a unicycle is drawn with its heading, labelled (x, y, θ)

    def __post_init__(self):
        object.__setattr__(self, "splits", _as(Splits, self.splits))
        object.__setattr__(self, "sampling", _as(Sampling, self.sampling))
        object.__setattr__(self, "follower", _as(Follower, self.follower))
        n = self.name
        if not n or "/" in n or n.startswith(".") or n != n.strip():
            raise ConfigError("data.name", f"must be a non-empty folder-safe name, got {n!r}")
        if not 0 <= self.seed <= 2**63 - 1:
            raise ConfigError("data.seed", f"must be an integer in [0, 2**63 - 1], got {self.seed!r}")
        if not 1 <= self.preview <= 256:
            raise ConfigError("data.preview", f"must be an integer in [1, 256], got {self.preview!r}")
        if self.chunk_size < 1:
            raise ConfigError("data.chunk_size", f"must be an integer >= 1, got {self.chunk_size!r}")

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
        return self.vehicle is not None and str(self.vehicle.get("_target_", "")).endswith("Unicycle")

    def check_arena(self, arena) -> None:
        """A follower annulus that fits nowhere in the arena is an impossible recipe (issue 21)."""
        (x0, x1), (y0, y1) = arena
        diag = math.hypot(x1 - x0, y1 - y0)
        if self.follower.probability > 0 and self.follower.min_distance >= diag:
            raise ConfigError("data.follower.min_distance", f"{self.follower.min_distance:g} is longer than the "
                                                            f"arena's diagonal ({diag:.4g}): no follower fits")
