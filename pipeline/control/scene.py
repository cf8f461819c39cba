"""The scene of SPEC §1/§3.1: target, obstacle, covering apex, barrier, and the obstacle frame (a, b)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.errors import ConfigError

BARRIER_KINDS = ("squared", "authors_code")
OBSTACLE_KEYS = ("center", "radius")
BARRIER_KEYS = ("rho", "scale", "kind", "gain")


def _pair(value, name: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        raise ConfigError(name, f"must be a pair of numbers [x, y], got {value!r}") from None
    if arr.shape != (2,) or not np.all(np.isfinite(arr)):
        raise ConfigError(name, f"must be a pair of finite numbers [x, y], got {value!r}")
    return arr


@dataclass(frozen=True, eq=False)
class Scene:
    """Target, obstacle and covering of the paper (Section III, SPEC §3.1), validated on construction.

    The obstacle frame has origin `p_0`, axis `e_a` from `p_0` towards `p_T` and `e_b` its left-hand normal,
    so any target direction works. `apex` is the covering constant `c` (default `2*sqrt(2)*r`); the barrier
    acts on `d_q / barrier_scale**2` (`barrier_scale` defaults to `r`).

    `barrier_kind='authors_code'` reproduces the authors' release: barrier `(d - rho)^2 log(rho/d)` on the
    Euclidean distance `d` and potential `1/2 |p - p_T|^2 + B` (SPEC §1).
    """

    target: tuple[float, float]
    obstacle_center: tuple[float, float] = (0.0, 0.0)
    obstacle_radius: float = 4.0
    barrier_rho: float = 0.5
    barrier_scale: float | None = None
    apex: float | None = None
    barrier_kind: str = "squared"
    barrier_gain: float = 1.0
    name: str = "custom"
    # derived
    p_T: np.ndarray = field(init=False, repr=False)
    p_0: np.ndarray = field(init=False, repr=False)
    e_a: np.ndarray = field(init=False, repr=False)
    e_b: np.ndarray = field(init=False, repr=False)
    c: float = field(init=False, repr=False)
    ell: float = field(init=False, repr=False)
    phi_weight: float = field(init=False, repr=False)

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        p_T = _pair(self.target, "scene.target")
        p_0 = _pair(self.obstacle_center, "scene.obstacle.center")
        r = float(self.obstacle_radius)
        if not math.isfinite(r) or r <= 0:
            raise ConfigError("scene.obstacle.radius", f"must be > 0, got {self.obstacle_radius!r}")
        if self.barrier_kind not in BARRIER_KINDS:
            raise ConfigError("scene.barrier.kind", f"must be one of {BARRIER_KINDS}, got {self.barrier_kind!r}")
        rho = float(self.barrier_rho)
        if self.barrier_kind == "squared" and not (0 < rho <= 1):
            raise ConfigError("scene.barrier.rho", f"must be in (0, 1] (SPEC §3), got {self.barrier_rho!r}")
        if self.barrier_kind == "authors_code" and not rho > 0:
            raise ConfigError("scene.barrier.rho", f"must be > 0, got {self.barrier_rho!r}")
        gain = float(self.barrier_gain)
        if not math.isfinite(gain) or gain <= 0:
            raise ConfigError("scene.barrier.gain", f"must be > 0, got {self.barrier_gain!r}")
        ell = r if self.barrier_scale is None else float(self.barrier_scale)
        if not math.isfinite(ell) or ell <= 0:
            raise ConfigError("scene.barrier.scale", f"must be > 0 (or null for the obstacle radius), got {self.barrier_scale!r}")
        c = 2.0 * math.sqrt(2.0) * r if self.apex is None else float(self.apex)
        if not math.isfinite(c) or c <= math.sqrt(2.0) * r:
            raise ConfigError(
                "scene.apex",
                f"the diamond |a| + |b| <= c must contain the obstacle: need c > sqrt(2) r = {math.sqrt(2) * r:.3g}, got {c!r}",
            )
        delta = p_T - p_0
        dist = float(np.hypot(*delta))
        if dist == 0:
            raise ConfigError("scene.target", "must differ from the obstacle centre")
        e_a = delta / dist
        set_("p_T", p_T)
        set_("p_0", p_0)
        set_("e_a", e_a)
        set_("e_b", np.array([-e_a[1], e_a[0]]))
        set_("c", c)
        set_("ell", ell)
        set_("phi_weight", 0.5 if self.barrier_kind == "authors_code" else 1.0)
        set_("target", tuple(p_T.tolist()))
        set_("obstacle_center", tuple(p_0.tolist()))
        # The target must lie outside both wedges by more than the barrier's reach (SPEC §3.1): otherwise
        # V_q(p_T) > 0 and the minimum of V_q moves away from the target.
        wedge_dist = dist / math.sqrt(2.0) - c / math.sqrt(2.0)  # distance from (a_T, 0) to W_q, a_T > c
        if dist <= c or wedge_dist <= self.barrier_reach:
            raise ConfigError(
                "scene.target",
                f"lies inside a covering wedge or within the barrier's reach ({self.barrier_reach:.3g}) of one: "
                f"distance to the wedges {max(wedge_dist, 0):.3g}; move the target away from the obstacle "
                f"(|p_T - p_0| = {dist:.3g}, apex c = {c:.3g}) or shrink scene.obstacle.radius/scene.barrier",
            )
        if dist - 2 * r <= self.barrier_reach:
            raise ConfigError(
                "scene.target",
                f"lies within the smooth baseline's barrier reach of the disc of radius 2r = {2 * r:.3g}",
            )

    @property
    def barrier_reach(self) -> float:
        """Euclidean distance from a set's boundary beyond which the barrier vanishes."""
        if self.barrier_kind == "authors_code":
            return float(self.barrier_rho)
        return math.sqrt(float(self.barrier_rho)) * self.ell

    @classmethod
    def from_config(cls, cfg) -> Scene:
        """Build from the `scene` config group (conf/scene/*.yaml) or a manifest's copy of it; unknown keys of
        `obstacle` and `barrier` are errors naming them."""
        get = (lambda k, d=None: cfg.get(k, d)) if hasattr(cfg, "get") else (lambda k, d=None: getattr(cfg, k, d))
        obstacle = dict(get("obstacle") or {})
        barrier = dict(get("barrier") or {})
        for part, node, known in (("obstacle", obstacle, OBSTACLE_KEYS), ("barrier", barrier, BARRIER_KEYS)):
            unknown = sorted(set(node) - set(known))
            if unknown:
                raise ConfigError(f"scene.{part}.{unknown[0]}", f"unknown key (known: {', '.join(known)})")
        return cls(
            target=tuple(get("target")),
            obstacle_center=tuple(obstacle.get("center", (0.0, 0.0))),
            obstacle_radius=obstacle.get("radius", 4.0),
            barrier_rho=barrier.get("rho", 0.5),
            barrier_scale=barrier.get("scale", None),
            apex=get("apex"),
            barrier_kind=barrier.get("kind", "squared"),
            barrier_gain=barrier.get("gain", 1.0),
            name=get("name", "custom"),
        )

    @property
    def _target_frame(self) -> tuple[float, float]:
        d = self.p_T - self.p_0
        return float(d @ self.e_a), float(d @ self.e_b)

    def to_frame(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Obstacle-frame coordinates (a, b) of `(N, 2)` world points."""
        d = np.asarray(points, dtype=float) - self.p_0
        return d @ self.e_a, d @ self.e_b

    def from_frame(self, a: np.ndarray, b: np.ndarray) -> np.ndarray:
        """World points `(N, 2)` from obstacle-frame coordinates."""
        return self.p_0 + np.multiply.outer(a, self.e_a) + np.multiply.outer(b, self.e_b)
