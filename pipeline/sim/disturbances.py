"""Measurement disturbances of SPEC §3.5, applied per camera frame: `m = measurement + e`."""

from __future__ import annotations

import numpy as np

from pipeline.schema import NonNegative, Pair, checked


def frame_b(p: np.ndarray, scene) -> tuple[np.ndarray, np.ndarray]:
    """`(b, e_b)`: each point's coordinate `b` in the frame of its nearest obstacle, and that frame's `e_b`
    (SPEC §3.6: the disturbances use the frame of the obstacle nearest to the true state)."""
    if scene.n_obstacles == 1:
        _, b = scene.to_frame(p)
        return b, np.broadcast_to(scene.e_b, p.shape)
    i = scene.nearest_obstacle(p)
    arr = scene.arrays
    d = p - arr["center"][i]
    return np.einsum("ij,ij->i", d, arr["e_b"][i]), arr["e_b"][i]


class Disturbance:
    """`e = disturbance(p_true, frame, rng, scene)`, shape `(N, 2)`."""

    name = "none"
    per_agent = False  # True: called with `idx`, the batch indices of the agents measured (a subset at a lost frame)

    def __call__(self, p: np.ndarray, frame: int, rng: np.random.Generator, scene) -> np.ndarray:
        return np.zeros_like(p)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items())
        return f"{type(self).__name__}({args})"


class NoDisturbance(Disturbance):
    """`e = 0`."""


@checked("disturbance")
class Gaussian(Disturbance):
    """`n ~ N(0, sigma^2 I)` (the paper's N(0, 0.5) read as std 0.5)."""

    name = "gaussian"

    def __init__(self, sigma: NonNegative = 0.5):
        self.sigma = float(sigma)

    def __call__(self, p, frame, rng, scene):
        return rng.normal(0.0, self.sigma, size=p.shape) if self.sigma > 0 else np.zeros_like(p)


@checked("disturbance")
class Alternating(Disturbance):
    """`e = ±eps e_b`, the sign flipping every frame (`(0, ±eps)` in the paper's axis-aligned frame)."""

    name = "alternating"

    def __init__(self, eps: NonNegative = 0.5):
        self.eps = float(eps)

    def __call__(self, p, frame, rng, scene):
        sign = 1.0 if frame % 2 == 0 else -1.0
        if scene.n_obstacles == 1:
            return np.broadcast_to(sign * self.eps * scene.e_b, p.shape).copy()
        return sign * self.eps * frame_b(p, scene)[1]


@checked("disturbance")
class Adversarial(Disturbance):
    """Proposition 1's attack: `e = -eps sign(b(p)) e_b`, pushing the perceived position across `b = 0`."""

    name = "adversarial"

    def __init__(self, eps: NonNegative = 0.5):
        self.eps = float(eps)

    def __call__(self, p, frame, rng, scene):
        b, e_b = frame_b(p, scene)
        sign = np.where(b >= 0, 1.0, -1.0)
        return -self.eps * sign[:, None] * e_b



@checked("disturbance")
class WorldAlternating(Disturbance):
    """The hybrid-RL benchmark's noise: `e = s m (d_x, d_y)` in a world-fixed direction, `s = ±1` flipping every
    frame; with `direction = (1, -1)` this is its `s (m, -m)` (norm `sqrt(2) m`)."""

    name = "world_alternating"

    def __init__(self, m: NonNegative = 0.05, direction: Pair = (1.0, -1.0)):
        self.m = float(m)
        self.direction = [float(x) for x in direction]

    def __call__(self, p, frame, rng, scene):
        sign = 1.0 if frame % 2 == 0 else -1.0
        return np.broadcast_to(sign * self.m * np.asarray(self.direction), p.shape).copy()


class PerAgent(Disturbance):
    """Several conditions in one batch (issue 30): agents `[s_k, s_k + sizes[k])` get `parts[k]`, as if each group
    ran alone. Exact for deterministic parts (every agent's arc is its own: the solvers step each agent by its own
    step); a random part draws from the shared stream in another order than a run of its own.
    `idx` (the loop passes it): the batch indices of the agents in `p`, where a sampled loop measures only some."""

    name = "per_agent"
    per_agent = True  # the loop passes the batch indices of the agents it measures

    def __init__(self, parts: list[Disturbance], sizes: list[int]):
        if len(parts) != len(sizes):
            raise ValueError(f"{len(parts)} disturbances for {len(sizes)} groups")
        self.parts = list(parts)
        self.owner = np.repeat(np.arange(len(parts)), np.asarray(sizes, dtype=int))

    def __call__(self, p, frame, rng, scene, idx: np.ndarray | None = None):
        owner = self.owner if idx is None else self.owner[idx]
        if len(owner) != len(p):
            raise ValueError(f"{len(p)} positions for {len(owner)} agents of the batch")
        out = np.zeros_like(p, dtype=float)
        for k, part in enumerate(self.parts):
            mine = owner == k
            if mine.any():
                out[mine] = part(p[mine], frame, rng, scene)
        return out



class Played(Disturbance):
    """An error signal set from outside before each frame (`e` `(N, 2)`, one row per agent of the batch): the
    bracket's falsifier plays its adversaries through the simulator's own loop with it."""

    name = "played"
    per_agent = True

    def __init__(self):
        self.e = None

    def __call__(self, p, frame, rng, scene, idx: np.ndarray | None = None):
        return self.e if idx is None else self.e[idx]
