"""Measurement hooks for the simulator: the camera + perception map in the loop (issue 6 §1).

Each camera frame renders `h(p)` for **all** agents that get a frame at once (with the scenario's clouds)
and runs the perception map on the batch. Camera failures (the simulator's `p_fail`) hold the last
estimate. With a `gate` (`camera.gate`), a map with an uncertainty head turns its doubtful frames into
failures: rows whose predicted error exceeds the gate come back as NaN, and the simulator holds the last
estimate for them (never on the first frame: a vehicle starts with an estimate). The leader-follower hook renders the leader and the follower in one image and returns the
map's estimate of the leader, the follower's moving target.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np

from pipeline.errors import ConfigError
from pipeline.profiling import phase
from pipeline.schema import NonNegative, Positive, checked


class OracleMap:
    """A perfect perception map: returns the true leader position of each image it was rendered from.

    Used with `perception: oracle` (no camera, no CNN): the measurement is the true state; the
    disturbances (noise, failures, adversary) still apply. `predict` is never called on images.
    """

    name = "oracle"
    id = "oracle"

    def predict(self, images):  # pragma: no cover - the oracle short-circuits rendering
        raise RuntimeError("OracleMap does not read images")


def check_gate(perception_map, gate) -> None:
    """`camera.gate` needs a map that predicts its own error: one line naming the field otherwise."""
    if gate is not None and not isinstance(perception_map, OracleMap) and \
            not getattr(perception_map, "has_uncertainty", False):
        raise ConfigError("camera.gate", f"perception map {perception_map.name}-{perception_map.id} has no "
                                         "uncertainty head (train it with model.uncertainty=gaussian, or gate=null)")


def gated_predict(perception_map, images, gate: float | None, frame: int) -> tuple[np.ndarray, int]:
    """Estimates, with NaN rows where the predicted error exceeds `gate` (not on frame 0); and their count."""
    if gate is None:
        return perception_map.predict(images), 0
    est, err = perception_map.predicted_error(images)
    if frame == 0:
        return est, 0
    doubt = err > gate
    est[doubt] = np.nan
    return est, int(doubt.sum())


@checked("camera")
@dataclass
class CameraMeasure:
    """`measure(c (n, 2|3), idx, frame, rng) -> l(h(c))`: render every agent's frame, infer in one batch;
    `gate`: rows whose predicted error exceeds it are NaN (held by the simulator), counted in `gated`.

    A vehicle with a heading (`c` = (x, y, θ), the unicycle of SPEC §3.7) is drawn with its oriented marker; its
    measured heading is the pose map's (`heading: camera`) or the true one plus Gaussian noise of
    `heading_noise` radians (`heading: imu`, the ablation)."""

    camera: object
    perception_map: object
    occlusion: object | None = None
    gate: Positive | None = None
    heading: Literal["camera", "imu"] = "camera"
    heading_noise: NonNegative = 0.0
    frames: int = 0
    images: int = 0
    gated: int = 0

    def __post_init__(self):
        check_gate(self.perception_map, self.gate)

    def __call__(self, c: np.ndarray, idx: np.ndarray, frame: int, rng: np.random.Generator) -> np.ndarray:
        if isinstance(self.perception_map, OracleMap):
            return np.array(c, dtype=float)
        posed = c.shape[1] == 3
        with phase("render"):
            imgs = self.camera.render(c[:, :2], None, occlusion=self.occlusion, rng=rng,
                                      heading=c[:, 2] if posed else None)
        with phase("inference"):
            est, n_gated = gated_predict(self.perception_map, imgs, self.gate, frame)
        if posed and (self.heading == "imu" or est.shape[1] == 2):
            est = np.column_stack([est[:, :2], c[:, 2] + rng.normal(0.0, self.heading_noise, len(c))])
        self.frames += 1
        self.images += len(c)
        self.gated += n_gated
        return est


@dataclass
class LeaderTrack:
    """A recorded leader run, sampled at the follower's frames: `position(t) -> (N, 2)`."""

    t: np.ndarray  # (T,)
    p: np.ndarray  # (T, N, 2)

    def position(self, t, idx: np.ndarray | None = None) -> np.ndarray:
        """`(N, 2)` at a time `t`, or `(T, N, 2)` for an array of times."""
        k = np.searchsorted(self.t, np.asarray(t) + 1e-9, side="right") - 1
        k = np.clip(k, 0, len(self.t) - 1)  # after the leader's run ended: it stays where it stopped
        p = self.p[k]
        return p if idx is None else p[..., idx, :]


@dataclass
class FollowerTarget:
    """`target_fn(t, frame, p_follower, idx, rng)`: the follower's camera sees leader and follower; the
    map returns the leader's position (the follower's moving target)."""

    leader: LeaderTrack
    camera: object
    perception_map: object
    occlusion: object | None = None
    gate: float | None = None
    images: int = 0
    gated: int = 0

    def __post_init__(self):
        check_gate(self.perception_map, self.gate)

    def __call__(self, t: float, frame: int, p: np.ndarray, idx: np.ndarray, rng: np.random.Generator):
        lead = self.leader.position(t, idx)
        if isinstance(self.perception_map, OracleMap):
            return np.array(lead, dtype=float)
        with phase("render"):
            imgs = self.camera.render(lead, p, occlusion=self.occlusion, rng=rng)
        with phase("inference"):
            est, n_gated = gated_predict(self.perception_map, imgs, self.gate, frame)
        self.images += len(p)
        self.gated += n_gated
        return est
