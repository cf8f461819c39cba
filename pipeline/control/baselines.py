"""The smooth baselines the hybrid controller is compared with (SPEC §3.4, §3.6): flow maps only (empty jump set).

- :class:`SmoothController`: the gradient flow of `V_s = |p - p_T|^2 + sum_i B(dist(p, D_{2 r_i})^2 / l_i^2)`
  (Eq. (smoothfeedback)); its saddle behind each obstacle is the set `K` of Proposition 1.
- :class:`CBFController`: `u = argmin |u - u_nom|^2 s.t. ∇h_i·u >= -alpha h_i` for every obstacle,
  `u_nom = -k (p - p_T)`, `h_i = |p - c_i|^2 - (2 r_i)^2`, solved exactly (:func:`pipeline.control.cbf.cbf_qp`).

Both are continuous, hence subject to Proposition 1. Inside a margin disc (only through perception error) the
flow map pushes out radially at `push_speed` (SPEC §3.3's rule for the baselines; counted).
"""

from __future__ import annotations

import numpy as np

from pipeline.control.cbf import cbf_qp, disc_constraints
from pipeline.control.feedback import Feedback
from pipeline.control.potentials import smooth_potential_grad
from pipeline.control.scene import Scene
from pipeline.schema import Positive, checked


class SmoothController(Feedback):
    """Gradient flow of `V_s` (SPEC §3.4): `u = sat(-k ∇V_s(m))`."""

    name = "smooth"

    def _flow(self, m, target):
        u = -self.k * smooth_potential_grad(self.scene, m, target)
        inside = ~np.isfinite(u).all(axis=1)
        return self._finalise(u, inside, m)


@checked("controller")
class CBFController(Feedback):
    """CBF safety filter (SPEC §3.4, §3.6) on `u_nom = -k (m - p_T)`, one constraint per obstacle, exact QP."""

    name = "cbf"

    def __init__(self, scene: Scene, k: Positive = 1.0, alpha: Positive = 1.0, u_max: Positive | None = 10.0,
                 push_speed: Positive | None = None):
        super().__init__(scene, k=k, u_max=u_max, push_speed=push_speed)
        self.alpha = float(alpha)

    def _flow(self, m, target):
        tgt = self.scene.p_T if target is None else np.asarray(target, dtype=float)
        u_nom = -self.k * (m - tgt)
        arr = self.scene.arrays
        G, b, _ = disc_constraints(m, arr["center"], 2.0 * arr["radius"], self.alpha)
        sol = cbf_qp(u_nom, G, b)
        u = np.array(sol.u, dtype=float)
        return self._finalise(u, sol.degenerate, m)
