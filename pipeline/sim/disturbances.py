"""Measurement disturbances of SPEC §3.5, applied per camera frame: `m = measurement + e`."""

from __future__ import annotations

import numpy as np

from pipeline.control.scene import Scene
from pipeline.errors import ConfigError


def _nonneg(value, field: str) -> float:
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(field, f"must be a number, got {value!r}") from None
    if not np.isfinite(v) or v < 0:
        raise ConfigError(field, f"must be >= 0, got {value!r}")
    return v


class Disturbance:
    """`e = disturbance(p_true, frame, rng, scene)`, shape `(N, 2)`."""

    name = "none"

    def __call__(self, p: np.ndarray, frame: int, rng: np.random.Generator, scene: Scene) -> np.ndarray:
        return np.zeros_like(p)

    def __repr__(self) -> str:
        args = ", ".join(f"{k}={v}" for k, v in vars(self).items())
        return f"{type(self).__name__}({args})"


class NoDisturbance(Disturbance):
    """`e = 0`."""


class Gaussian(Disturbance):
    """`n ~ N(0, sigma^2 I)` (the paper's N(0, 0.5) read as std 0.5)."""

    name = "gaussian"

    def __init__(self, sigma: float = 0.5):
        self.sigma = _nonneg(sigma, "disturbance.sigma")

    def __call__(self, p, frame, rng, scene):
        return rng.normal(0.0, self.sigma, size=p.shape) if self.sigma > 0 else np.zeros_like(p)


class Alternating(Disturbance):
    """`e = ±eps e_b`, the sign flipping every frame (`(0, ±eps)` in the paper's axis-aligned frame)."""

    name = "alternating"

    def __init__(self, eps: float = 0.5):
        self.eps = _nonneg(eps, "disturbance.eps")

    def __call__(self, p, frame, rng, scene):
        sign = 1.0 if frame % 2 == 0 else -1.0
        return np.broadcast_to(sign * self.eps * scene.e_b, p.shape).copy()


class Adversarial(Disturbance):
    """Proposition 1's attack: `e = -eps sign(b(p)) e_b`, pushing the perceived position across `b = 0`."""

    name = "adversarial"

    def __init__(self, eps: float = 0.5):
        self.eps = _nonneg(eps, "disturbance.eps")

    def __call__(self, p, frame, rng, scene):
        _, b = scene.to_frame(p)
        sign = np.where(b >= 0, 1.0, -1.0)
        return -self.eps * sign[:, None] * scene.e_b


DISTURBANCES = {"none": NoDisturbance, "gaussian": Gaussian, "alternating": Alternating, "adversarial": Adversarial}
