"""What every feedback law shares: a pure map from perceived positions to velocities, with logic variables.

A feedback law is the controller part of a hybrid system (SPEC §3.3; the Hybrid Equations Toolbox's names),
pure: its logic state `xd` (a dict of `(N,)` integer arrays, e.g. the mode `q`) is passed in and returned,
never kept in the object. For perceived positions `m` `(N, 2)` (and a moving target, SPEC §4):

- `initial_state(m0, target)`: the logic state at the first measurement;
- `flow_map(m, xd, target)`: the velocity `u` `(N, 2)`, saturated at `u_max`, never NaN (the fallback of SPEC
  §3.3 outside `C ∪ D`);
- `jump_map(m, xd, target)`, `flow_set(m, xd, target)`, `jump_set(m, xd, target)`.

`evaluate(m, xd, target)` computes once what all four read at `m` (the fused hot path); each map takes it as
`ev=` so that a sampled loop's frame evaluates the controller once (`covers(ev, xd)` says whether an
evaluation also serves a logic state reached from it by a jump).
"""

from __future__ import annotations

import numpy as np

from pipeline.control.scene import Scene
from pipeline.schema import Positive, checked


def saturate(u: np.ndarray, u_max: float | None) -> np.ndarray:
    """Scale rows of `u` down to norm `u_max` (the vehicle's speed limit); `None` = no limit."""
    if u_max is None:
        return u
    norm = np.hypot(u[:, 0], u[:, 1])
    scale = np.minimum(1.0, u_max / np.maximum(norm, 1e-300))
    return u * scale[:, None]


@checked("controller")
class Feedback:
    """Base of the feedback laws: `k`, the speed limit `u_max` and the push-out speed of SPEC §3.3's fallback."""

    name = "controller"
    hybrid = False
    logic: tuple[str, ...] = ("q",)  # logic variables (a law without modes keeps q = 1)

    def __init__(self, scene: Scene, k: Positive = 1.0, u_max: Positive | None = 10.0,
                 push_speed: Positive | None = None):
        if not isinstance(scene, Scene):
            raise TypeError(f"scene must be a pipeline.control.Scene, got {type(scene).__name__}")
        self.scene = scene
        self.k = float(k)
        self.u_max = None if u_max is None else float(u_max)
        # speed used to leave a set the controller cannot be in (u_max, or 10 units/s without a limit)
        self.push_speed = self.u_max if push_speed is None and self.u_max is not None else (push_speed or 10.0)

    # ---- the four maps (a law without modes: flow everywhere it is defined, never jump) -----------------
    def initial_state(self, m0: np.ndarray, target=None) -> dict[str, np.ndarray]:
        return {"q": np.ones(len(m0), dtype=np.int8)}

    def evaluate(self, m: np.ndarray, xd: dict, target=None):
        """The law at `m` once: `(u, fallback rows)` of `_flow`, which `flow_set` and `flow_map` read (a sampled
        loop's frame solves a CBF's QP once, not twice); None for a law that writes its four maps itself."""
        if type(self)._flow is Feedback._flow:
            return None
        return self._flow(np.asarray(m, dtype=float), target)

    def covers(self, ev, xd_from: dict, xd: dict) -> bool:
        return True

    def jump_set(self, m, xd, target=None, ev=None) -> np.ndarray:
        return np.zeros(len(m), dtype=bool)

    def jump_map(self, m, xd, target=None, ev=None) -> dict[str, np.ndarray]:
        return dict(xd)

    def flow_set(self, m, xd, target=None, ev=None) -> np.ndarray:
        """Where the flow map is the law itself (not its fallback): where it is finite."""
        return ~(self.evaluate(m, xd, target) if ev is None else ev)[1]

    def flow_map(self, m, xd, target=None, ev=None) -> np.ndarray:
        return (self.evaluate(m, xd, target) if ev is None else ev)[0].copy()  # a copy: `ev` may serve again

    def hold(self, u: np.ndarray, m, xd, ev, period: float) -> tuple[np.ndarray, np.ndarray]:
        """The velocity a sampled loop holds between frames (the law's own: no guard), and the guarded rows."""
        return u, np.zeros(len(u), dtype=bool)

    def check_loop(self, period: float | None) -> None:
        """Conditions that involve the loop's frame period (none)."""

    def _flow(self, m: np.ndarray, target) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - interface
        """`(u, fallback rows)`."""
        raise NotImplementedError

    def _finalise(self, u: np.ndarray, bad: np.ndarray, m: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Replace rows that cannot be evaluated by the push-out `radial(m) * push_speed` (computed on those rows
        only), saturate; `(u, replaced rows)`."""
        bad = bad | ~np.isfinite(u).all(axis=1)
        if bad.any():
            u[bad] = radial(self.scene, m[bad]) * self.push_speed
        return saturate(u, self.u_max), bad


def radial(scene: Scene, m: np.ndarray) -> np.ndarray:
    """Unit vectors from the nearest obstacle's centre (its `e_b` at the centre itself): the baselines' push-out."""
    i = scene.nearest_obstacle(m)
    arr = scene.arrays
    rel = m - arr["center"][i]
    norm = np.hypot(rel[:, 0], rel[:, 1])
    out = arr["e_b"][i].copy()
    ok = norm > 0
    out[ok] = rel[ok] / norm[ok, None]
    return out
