"""The settings of a closed-loop run: the time model (`sim`) and the camera's timing (`camera`), typed.

`conf/sim/*.yaml` and `conf/camera/*.yaml` build these (`_target_`); their keys and types are checked with the
config, the ranges and cross-field rules here.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, get_args

from pipeline.errors import ConfigError

TimeModel = Literal["sampled", "continuous"]
Method = Literal["rosenbrock23", "dopri5"]
HeadingSource = Literal["camera", "imu"]


def _at_least(value, low, strict: bool) -> bool:
    """`value > low` (`>=` unless `strict`), False for a value that is no number (a direct call's bad type)."""
    try:
        return bool(value > low) if strict else bool(value >= low)
    except TypeError:
        return False


@dataclass(frozen=True)
class SimSettings:
    """`sim`: the time model, the Euler step / record grid, horizon, success radius, recording, seed, the continuous
    integrator's tolerances and the stall thresholds of the outcome classes (docs/control.md)."""

    model: TimeModel = "sampled"
    dt: float = 0.01
    horizon: float = 30.0
    delta: float = 1.0
    record_every: int = 5
    stop_on_success: bool = True
    seed: int = 0
    method: Method = "rosenbrock23"
    rtol: float = 1e-6
    atol: float = 1e-4
    h_max: float = 0.25
    stall_speed: float = 0.25
    stall_time: float = 5.0

    def __post_init__(self):
        for k, tp in (("model", TimeModel), ("method", Method)):
            if getattr(self, k) not in get_args(tp):
                raise ConfigError(f"sim.{k}", f"must be one of {', '.join(get_args(tp))}, got {getattr(self, k)!r}")
        for k in ("dt", "delta", "rtol", "atol", "h_max", "stall_speed", "stall_time"):
            if not _at_least(getattr(self, k), 0, strict=True):
                raise ConfigError(f"sim.{k}", f"must be > 0, got {getattr(self, k)!r}")
        if not _at_least(self.horizon, self.dt, strict=False):
            raise ConfigError("sim.horizon", f"must be >= sim.dt = {self.dt}, got {self.horizon!r}")
        if not _at_least(self.record_every, 1, strict=False):
            raise ConfigError("sim.record_every", f"must be >= 1, got {self.record_every!r}")
        if not _at_least(self.seed, 0, strict=False):
            raise ConfigError("sim.seed", f"must be >= 0, got {self.seed!r}")

    @property
    def n_steps(self) -> int:
        return int(round(self.horizon / self.dt))


@dataclass(frozen=True)
class CameraSettings:
    """`camera`: a frame every `period` seconds (a multiple of `sim.dt`; null: every step), lost with probability
    `p_fail` (the last estimate is held); with `gate`, a frame whose predicted error (a map with an uncertainty
    head) exceeds `gate` world units is lost too. A vehicle with a heading (the unicycle) reads it from the pose
    map (`heading: camera`) or from an onboard sensor: the true heading plus Gaussian noise of `heading_noise`
    radians (`heading: imu`, the ablation of SPEC §3.7)."""

    period: float | None = 0.05
    p_fail: float = 0.0
    gate: float | None = None
    heading: HeadingSource = "camera"
    heading_noise: float = 0.0

    def __post_init__(self):
        if self.heading not in get_args(HeadingSource):
            raise ConfigError("camera.heading", f"must be one of {', '.join(get_args(HeadingSource))}, "
                                                f"got {self.heading!r}")
        if not _at_least(self.heading_noise, 0, strict=False):
            raise ConfigError("camera.heading_noise", f"must be >= 0 (radians), got {self.heading_noise!r}")
        if self.period is not None and not _at_least(self.period, 0, strict=True):
            raise ConfigError("camera.period", f"must be > 0 (or null), got {self.period!r}")
        if not (_at_least(self.p_fail, 0.0, strict=False) and self.p_fail < 1.0):
            raise ConfigError("camera.p_fail", f"must be in [0, 1), got {self.p_fail!r}")
        if self.gate is not None and not _at_least(self.gate, 0, strict=True):
            raise ConfigError("camera.gate", f"must be > 0 (world units) or null, got {self.gate!r}")


def frame_steps(dt: float, period: float | None) -> int:
    """Steps of `dt` per camera frame: `period` must be a positive multiple of `dt` (null: every step)."""
    if period is None:
        return 1
    every = round(period / dt)
    if every < 1 or abs(every * dt - period) > 1e-9 * max(1.0, period):
        raise ConfigError("camera.period", f"must be a positive multiple of sim.dt = {dt}, got {period!r}")
    return every


def check_vehicle(plant, sim: SimSettings) -> None:
    """A look-ahead point must settle inside the success radius: `vehicle.lookahead < sim.delta` (SPEC §3.7)."""
    d = getattr(plant, "lookahead", None)
    if d is not None and d >= sim.delta:
        raise ConfigError("vehicle.lookahead", f"must be < sim.delta = {sim.delta:g} (the axle settles `lookahead` "
                                               f"from the target, SPEC §3.7), got {d:g}")


def run_keywords(sim: SimSettings, camera: CameraSettings) -> dict:
    """The keywords of :func:`pipeline.sim.simulate` that the two settings nodes give."""
    keys = ("model", "dt", "horizon", "delta", "record_every", "stop_on_success", "seed", "method", "rtol", "atol",
            "h_max", "stall_speed", "stall_time")
    return {**{k: getattr(sim, k) for k in keys}, "camera_period": camera.period, "p_fail": camera.p_fail}
