"""The settings of a closed-loop run: the time model (`sim`) and the camera's timing (`camera`), typed.

`conf/sim/*.yaml` and `conf/camera/*.yaml` build these (`_target_`); their keys, types and ranges are declared
here and checked with the config (and by :func:`pipeline.schema.checked` when built from Python), the
cross-field rules in the classes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from pipeline.errors import ConfigError
from pipeline.schema import NonNegative, NonNegativeInt, OpenShare, Positive, PositiveInt, Range, checked

TimeModel = Literal["sampled", "continuous"]
Method = Literal["rosenbrock23", "dopri5"]
HeadingSource = Literal["camera", "imu"]
FailureRate = Annotated[float, Range(ge=0, lt=1)]  # a frame is lost with this probability (1: never a frame)


@checked("sim")
@dataclass(frozen=True)
class SimSettings:
    """`sim`: the time model, the Euler step / record grid, horizon, success radius, recording, seed, the continuous
    integrator's tolerances and the stall thresholds of the outcome classes (docs/control.md)."""

    model: TimeModel = "sampled"
    dt: Positive = 0.01
    horizon: Positive = 30.0
    delta: Positive = 1.0
    record_every: PositiveInt = 5
    stop_on_success: bool = True
    seed: NonNegativeInt = 0
    method: Method = "rosenbrock23"
    rtol: Positive = 1e-6
    atol: Positive = 1e-4
    h_max: Positive = 0.25
    stall_speed: Positive | None = None
    stall_share: OpenShare = 0.025
    stall_time: Positive = 5.0

    def __post_init__(self):
        if not self.horizon >= self.dt:
            raise ConfigError("sim.horizon", f"must be >= sim.dt = {self.dt}, got {self.horizon!r}")

    @property
    def n_steps(self) -> int:
        return int(round(self.horizon / self.dt))


@checked("camera")
@dataclass(frozen=True)
class CameraSettings:
    """`camera`: a frame every `period` seconds (a multiple of `sim.dt`; null: every step), lost with probability
    `p_fail` (the last estimate is held); with `gate`, a frame whose predicted error (a map with an uncertainty
    head) exceeds `gate` world units is lost too. A vehicle with a heading (the unicycle) reads it from the pose
    map (`heading: camera`) or from an onboard sensor: the true heading plus Gaussian noise of `heading_noise`
    radians (`heading: imu`, the ablation of SPEC §3.7). A lost frame holds the last estimate (`predict: false`, the
    paper's failure model) or predicts it with the vehicle's own input (`predict: true`, dead reckoning:
    :class:`pipeline.sim.closed_loop.DeadReckoning`, its uncertainty growing by `drift` per unit of distance, the
    vehicle stopping past `max_drift` world units until a frame is used; with `innovation`, a delivered frame farther
    than `innovation` plus that uncertainty from the prediction is rejected, the vehicle stopping until two frames
    agree, docs/attacks.md)."""

    period: Positive | None = 0.05
    p_fail: FailureRate = 0.0
    gate: Positive | None = None
    heading: HeadingSource = "camera"
    heading_noise: NonNegative = 0.0
    predict: bool = False
    drift: NonNegative = 0.1
    max_drift: Positive = 2.0
    innovation: Positive | None = None

    def __post_init__(self):
        if self.innovation is not None and not self.predict:
            raise ConfigError("camera.innovation", "checks a frame against the dead-reckoned prediction: needs "
                                                   "camera.predict=true (or camera.innovation=null)")


def frame_steps(dt: float, period: float | None) -> int:
    """Steps of `dt` per camera frame: `period` must be a positive multiple of `dt` (null: every step)."""
    if period is None:
        return 1
    every = round(period / dt)
    if every < 1 or abs(every * dt - period) > 1e-9 * max(1.0, period):
        raise ConfigError("camera.period", f"must be a positive multiple of sim.dt = {dt}, got {period!r}")
    return every


def check_vehicle(plant, sim: SimSettings) -> None:
    """A look-ahead point must settle inside the success radius: `vehicle.lookahead < sim.delta` (SPEC §3.7); the
    mean of several frames' commands (`vehicle.smoothing`) exists only in the sampled loop."""
    if getattr(plant, "smoothing", 1) > 1 and sim.model != "sampled":
        raise ConfigError("vehicle.smoothing", f"averages the commands of camera frames: the sampled loop only, got "
                                               f"sim.model={sim.model} (sim.model=sampled, or vehicle.smoothing=1)")
    d = getattr(plant, "lookahead", None)
    if d is not None and d >= sim.delta:
        raise ConfigError("vehicle.lookahead", f"must be < sim.delta = {sim.delta:g} (the axle settles `lookahead` "
                                               f"from the target, SPEC §3.7), got {d:g}")

