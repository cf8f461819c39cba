"""What the closed loop watches along its arcs: arrival at the target, collision with an obstacle, clearance, stall.

:class:`ArrivalCollision` is the :class:`~pipeline.hybrid.system.Monitor` of a closed loop (SPEC §4): stop set 1
is the success disc `|p - p_T| <= delta` (it ends the run with `stop_on_success`, else only its first entry
time is kept), stop set 2 any obstacle `|p - c_i| < r_i`; it keeps the smallest squared distance to each
obstacle and to the target seen along the arc, and the positions of the last `stall_time` seconds
(:class:`~pipeline.sim.metrics.StallMonitor`). Positions are the plant's (`plant.position(c)`). With an `arena`
(the environments: the camera's view), leaving it is stop set 3. The codes are :class:`~pipeline.sim.metrics.Outcome`'s.
"""

from __future__ import annotations

import numpy as np

from pipeline.hybrid.system import Monitor
from pipeline.sim.metrics import Outcome, StallMonitor

TARGET, COLLISION, LEFT_VIEW = Outcome.REACHED, Outcome.COLLIDED, Outcome.LEFT_VIEW


def _sq(X, c):
    """Squared distances of the rows of `X` `(k, 2)` to the point `c`."""
    dx, dy = X[:, 0] - c[0], X[:, 1] - c[1]
    return dx * dx + dy * dy


class ArrivalCollision(Monitor):
    codes = ("target", "collision")
    precedence = (COLLISION, TARGET)  # a step that ends in an obstacle is a collision, whatever else

    def __init__(self, scene, plant, n: int, *, delta: float, stop_on_success: bool, stall: StallMonitor,
                 arena: tuple | None = None):
        self.plant = plant
        arr = scene.arrays
        self.centers, self.r2 = arr["center"], arr["radius"] ** 2
        self.radii = arr["radius"]
        self.pT = scene.p_T
        self.delta2 = delta * delta
        self.stops = (bool(stop_on_success), True)
        self.stall = stall
        self.t_hit = np.full(n, np.nan)
        self.min_d2 = np.full((n, len(self.centers)), np.inf)
        self.min_e2 = np.full(n, np.inf)
        self.conditions = (self._arrived, self._collides)
        self.arena = arena  # ((x0, x1), (y0, y1)): leaving it ends a run (stop set 3)
        if arena is not None:
            self.codes, self.stops = (*self.codes, "left_view"), (*self.stops, True)
            self.conditions = (*self.conditions, self._left)

    # the stop sets ------------------------------------------------------------------------------------
    def _d2(self, p: np.ndarray) -> np.ndarray:
        """Squared distances to every obstacle centre `(k, M)` (the same operations as :func:`_sq`, all centres at once)."""
        dx, dy = p[:, 0, None] - self.centers[None, :, 0], p[:, 1, None] - self.centers[None, :, 1]
        return dx * dx + dy * dy

    def _collides(self, c: np.ndarray) -> np.ndarray:
        return (self._d2(self.plant.position(c)) < self.r2).any(axis=1)

    def _arrived(self, c: np.ndarray) -> np.ndarray:
        return _sq(self.plant.position(c), self.pT) <= self.delta2

    def _left(self, c: np.ndarray) -> np.ndarray:
        p = self.plant.position(c)
        (x0, x1), (y0, y1) = self.arena
        return (p[:, 0] < x0) | (p[:, 0] > x1) | (p[:, 1] < y0) | (p[:, 1] > y1)

    # the sampled loop ----------------------------------------------------------------------------------
    def start(self, c):
        p = self.plant.position(c)
        d2 = self._d2(p)
        self.min_d2 = d2.copy()
        self.min_e2 = _sq(p, self.pT)
        self.t_hit[:] = np.nan  # a new run (the environments start one per frame)
        self.stall.sample(p)
        return np.where((d2 < self.r2).any(axis=1), COLLISION, 0).astype(np.int8)

    def step(self, k, t, c, active):
        p = self.plant.position(c)
        d2 = self._d2(p)
        np.minimum(self.min_d2, d2, out=self.min_d2)
        e2 = _sq(p, self.pT)
        np.minimum(self.min_e2, e2, out=self.min_e2)
        hit = (d2 < self.r2).any(axis=1) if d2.shape[1] > 1 else d2[:, 0] < self.r2[0]
        arrived = e2 <= self.delta2
        events = (hit | arrived) & active
        codes = np.zeros(len(c), dtype=np.int8)
        if events.any():  # rare: collisions and arrivals in detail
            hit &= events
            codes[hit] = COLLISION
            reached = events & ~hit & arrived & np.isnan(self.t_hit)
            self.t_hit[reached] = t
            if self.stops[0]:
                codes[reached] = TARGET
        if self.arena is not None:
            left = active & (codes == 0) & self._left(c)
            codes[left] = LEFT_VIEW
        if (k + 1) % self.stall.every == 0:
            self.stall.sample(p)
        return codes

    # the continuous solver -----------------------------------------------------------------------------
    def graze(self, c0, c1):
        p0, p1 = self.plant.position(c0), self.plant.position(c1)
        d_ends = (np.sqrt(np.minimum(self._d2(p0), self._d2(p1))) - self.radii).min(axis=1)
        return d_ends < np.hypot(*(p1 - p0).T) + 1e-9

    def observe(self, idx, c, ends):
        p = self.plant.position(c)
        self.min_d2[idx] = np.minimum(self.min_d2[idx], self._d2(p))
        if ends:
            self.min_e2[idx] = np.minimum(self.min_e2[idx], _sq(p, self.pT))

    def entered(self, code, idx, t):
        if code == TARGET:
            self.t_hit[idx] = t

    def sample_grid(self):
        return self.stall.period, self.stall.buf

    def finish(self, t_end):
        self.stall.count = int(np.floor(t_end / self.stall.period + 1e-9)) + 1

    # results ---------------------------------------------------------------------------------------
    def min_clearance(self) -> np.ndarray:
        """The smallest distance to any obstacle's edge along the arc `(N,)`."""
        return (np.sqrt(self.min_d2) - self.radii[None]).min(axis=1)
