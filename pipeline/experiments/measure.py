"""Measurement hooks for the simulator: the camera + perception map in the loop (issue 6 §1).

Each camera frame renders `h(p)` for **all** agents that get a frame at once (with the scenario's clouds)
and runs the perception map on the batch. Camera failures (the simulator's `p_fail`) hold the last
estimate. The leader-follower hook renders the leader and the follower in one image and returns the
map's estimate of the leader, the follower's moving target.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


class OracleMap:
    """A perfect perception map: returns the true leader position of each image it was rendered from.

    Used with `perception: oracle` (no camera, no CNN): the measurement is the true state; the
    disturbances (noise, failures, adversary) still apply. `predict` is never called on images.
    """

    name = "oracle"
    id = "oracle"

    def predict(self, images):  # pragma: no cover - the oracle short-circuits rendering
        raise RuntimeError("OracleMap does not read images")


@dataclass
class CameraMeasure:
    """`measure(p (n, 2), idx, frame, rng) -> l(h(p))`: render every agent's frame, infer in one batch."""

    camera: object
    perception_map: object
    occlusion: object | None = None
    frames: int = 0
    images: int = 0

    def __call__(self, p: np.ndarray, idx: np.ndarray, frame: int, rng: np.random.Generator) -> np.ndarray:
        if isinstance(self.perception_map, OracleMap):
            return np.array(p, dtype=float)
        imgs = self.camera.render(p, None, occlusion=self.occlusion, rng=rng)
        est = self.perception_map.predict(imgs)
        self.frames += 1
        self.images += len(p)
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

    def __call__(self, t: float, frame: int, p: np.ndarray, idx: np.ndarray, rng: np.random.Generator):
        lead = self.leader.position(t, idx)
        if isinstance(self.perception_map, OracleMap):
            return np.array(lead, dtype=float)
        imgs = self.camera.render(lead, p, occlusion=self.occlusion, rng=rng)
        return self.perception_map.predict(imgs)
