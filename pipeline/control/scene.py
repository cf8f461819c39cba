"""The scene of SPEC §1/§3.1/§3.6: the target, the obstacles (discs) with their coverings, the barrier, the arena.

`Scene(target, obstacles, barrier, arena)` is what `conf/scene/*.yaml` says, key for key: `obstacles` a list of
discs (`center`, `radius`, optional covering `apex` and barrier scale), `barrier` the barrier `B` and its
parameters, `arena` the rectangle the camera sees. Each obstacle `i` has its covering `O_1, O_2`
(:class:`Covering`: its frame `(a, b)` with origin `c_i` and axis `e_a` towards `p_T`, apex `c`, barrier scale
`ℓ`), and the scene gathers them in arrays for the batched controllers. A single-obstacle scene (`M = 1`) also
answers the single-obstacle names (`scene.p_0`, `scene.c`, `scene.to_frame`, ...) of its obstacle.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field, fields
from typing import Annotated, Literal

import numpy as np

from pipeline.errors import ConfigError
from pipeline.schema import Interval, NonEmpty, Pair, Positive, checked

BarrierKind = Literal["squared", "authors_code"]


@checked("obstacle")
@dataclass(frozen=True)
class Obstacle:
    """A disc `N_i` (SPEC §3.6): centre, radius; its covering's apex `c` (null: `2 sqrt(2) r`) and barrier scale
    `ℓ` (null: the scene's `barrier.scale`, else `r`)."""

    center: Pair
    radius: Positive
    apex: float | None = None
    barrier_scale: Positive | None = None


@checked("scene.barrier")
@dataclass(frozen=True)
class Barrier:
    """`B(s) = (s - rho)^2 log(1/s)` on `d_q / ℓ^2` (`squared`, SPEC §3), or the authors' release
    `(d - rho)^2 log(rho / d)` on the Euclidean distance with `1/2 |p - p_T|^2` (`authors_code`, SPEC §1);
    `gain` multiplies `B` (docs/control.md); `scale` is the default `ℓ` (null: each obstacle's radius)."""

    rho: Positive = 0.5
    scale: Positive | None = None
    kind: BarrierKind = "squared"
    gain: Positive = 1.0


@checked("scene.arena")
@dataclass(frozen=True)
class Arena:
    """The rectangle the camera sees, world units."""

    x: Interval = field(default_factory=lambda: [-50.0, 50.0])
    y: Interval = field(default_factory=lambda: [-30.0, 30.0])

    @property
    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return (float(self.x[0]), float(self.x[1])), (float(self.y[0]), float(self.y[1]))


def _as(cls, value):
    """A nested config node (a mapping) as its dataclass; the keys were checked with the config."""
    return value if isinstance(value, cls) else cls(**dict(value))


class Covering:
    """The covering `O_1, O_2` of one obstacle (SPEC §3.1) with what its potentials need (SPEC §3.2).

    The obstacle frame has origin `p_0`, axis `e_a` from `p_0` towards `p_T` and `e_b` its left-hand normal;
    `c` is the apex, `ell` the barrier's length scale. Read by `pipeline.control.covering` and
    `pipeline.control.potentials` (a single-obstacle :class:`Scene` has the same attributes).
    """

    def __init__(self, p_T, p_0, radius: float, c: float, ell: float, barrier: Barrier):
        self.p_T = np.asarray(p_T, dtype=float)
        self.p_0 = np.asarray(p_0, dtype=float)
        self.obstacle_radius = float(radius)
        self.c = float(c)
        self.ell = float(ell)
        self.barrier_rho = float(barrier.rho)
        self.barrier_kind = barrier.kind
        self.barrier_gain = float(barrier.gain)
        self.phi_weight = 0.5 if barrier.kind == "authors_code" else 1.0
        delta = self.p_T - self.p_0
        dist = float(np.hypot(*delta))
        self.distance_to_target = dist
        self.e_a = delta / dist
        self.e_b = np.array([-self.e_a[1], self.e_a[0]])

    @property
    def target(self) -> tuple[float, float]:
        return tuple(self.p_T.tolist())

    @property
    def obstacle_center(self) -> tuple[float, float]:
        return tuple(self.p_0.tolist())

    @property
    def barrier_reach(self) -> float:
        """Euclidean distance from a set's boundary beyond which the barrier vanishes."""
        if self.barrier_kind == "authors_code":
            return self.barrier_rho
        return math.sqrt(self.barrier_rho) * self.ell

    @property
    def influence_radius(self) -> float:
        """`R = c + sqrt(2) rho` (SPEC §3.6): outside `disc(p_0, R)` both barriers vanish."""
        return self.c + math.sqrt(2.0) * self.barrier_reach

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


@checked("scene")
@dataclass(eq=False)
class Scene:
    """Target, obstacles and barrier of the paper (Section III; SPEC §3.1, §3.6), and the arena.

    Checked on construction (the keys, types and ranges are declared on the fields and checked with the config, and
    by :func:`pipeline.schema.checked` when built from Python; the cross-field rules here): every apex `c > sqrt(2) r` (the diamond contains the disc), `rho` in (0, 1] for the squared
    barrier, the target outside every obstacle's wedges by more than the barrier's reach (`|p_T - c_i| > R_i`,
    SPEC §3.1 and V1 of §3.6) and beyond the smooth baseline's reach of its margin disc, target and obstacles
    inside the arena. The conditions that involve the controller and the camera (V2, V3) are checked where those
    are known (`pipeline.control.hybrid`).
    """

    target: Pair = field(default_factory=lambda: [40.0, 0.0])
    obstacles: Annotated[list[Obstacle], NonEmpty()] = field(
        default_factory=lambda: [Obstacle(center=[0.0, 0.0], radius=4.0)])
    barrier: Barrier = field(default_factory=Barrier)
    arena: Arena = field(default_factory=Arena)
    name: str = "default"  # conf/scene/default.yaml: the default scene

    def __post_init__(self):
        self._coverings: dict[int, Covering] = {}
        self.obstacles = [_as(Obstacle, o) for o in self.obstacles]
        self.barrier = _as(Barrier, self.barrier)
        self.arena = _as(Arena, self.arena)
        b = self.barrier
        if b.kind == "squared" and not b.rho <= 1:
            raise ConfigError("scene.barrier.rho", f"must be in (0, 1] for the squared barrier (SPEC §3), got {b.rho!r}")
        for i, o in enumerate(self.obstacles):
            self._check_obstacle(i, o)

    def _check_obstacle(self, i: int, o: Obstacle) -> None:
        f = f"scene.obstacles[{i}]"
        (x0, x1), (y0, y1) = self.arena.bounds
        if np.hypot(self.target[0] - o.center[0], self.target[1] - o.center[1]) == 0:
            raise ConfigError("scene.target", f"must differ from the centre of obstacle {i}")
        cov = self.covering(i)
        r = o.radius
        if not cov.c > math.sqrt(2.0) * r:
            raise ConfigError(f"{f}.apex", f"the diamond |a| + |b| <= c must contain the obstacle: need c > sqrt(2) r "
                                           f"= {math.sqrt(2) * r:.3g}, got {cov.c!r}")
        for name, (x, y) in (("scene.target", self.target), (f"{f}.center", o.center)):
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                raise ConfigError(name, f"({x:g}, {y:g}) lies outside the arena x in [{x0:g}, {x1:g}], "
                                        f"y in [{y0:g}, {y1:g}]")
        dist = cov.distance_to_target
        # the target outside both wedges by more than the barrier's reach (SPEC §3.1; V1 of §3.6): otherwise
        # V_q(p_T) > 0 and the minimum of V_q moves away from the target
        wedge_dist = dist / math.sqrt(2.0) - cov.c / math.sqrt(2.0)  # distance from (a_T, 0) to W_q, a_T > c
        if dist <= cov.c or wedge_dist <= cov.barrier_reach:
            raise ConfigError(
                "scene.target",
                f"lies inside a covering wedge of obstacle {i} or within the barrier's reach ({cov.barrier_reach:.3g}) "
                f"of one: distance to the wedges {max(wedge_dist, 0):.3g}; move the target away from the obstacle "
                f"(|p_T - c_{i}| = {dist:.3g}, apex c = {cov.c:.3g}) or shrink its radius / apex / barrier",
            )
        if dist - 2 * r <= cov.barrier_reach:
            raise ConfigError("scene.target", f"lies within the smooth baseline's barrier reach of obstacle {i}'s "
                                              f"disc of radius 2r = {2 * r:.3g}")

    # ---------------------------------------------------------------------------- the obstacles
    @property
    def n_obstacles(self) -> int:
        return len(self.obstacles)

    def covering(self, i: int) -> Covering:
        """The covering of obstacle `i` (its frame, apex and barrier scale)."""
        if i not in self._coverings:
            o = self.obstacles[i]
            c = 2.0 * math.sqrt(2.0) * o.radius if o.apex is None else float(o.apex)
            ell = o.barrier_scale if o.barrier_scale is not None else (
                self.barrier.scale if self.barrier.scale is not None else o.radius)
            self._coverings[i] = Covering(self.target, o.center, o.radius, c, float(ell), self.barrier)
        return self._coverings[i]

    @functools.cached_property
    def coverings(self) -> list[Covering]:
        return [self.covering(i) for i in range(self.n_obstacles)]

    @functools.cached_property
    def arrays(self) -> dict[str, np.ndarray]:
        """Per-obstacle arrays for the batched controllers: `center (M, 2)`, `radius`, `c` (apex), `ell`, `reach`,
        `R` (influence radius), `e_a`, `e_b` `(M, 2)`, `target_a`, `target_b` (the target in each frame)."""
        covs = self.coverings
        tf = np.array([cv._target_frame for cv in covs])
        return {"center": np.array([cv.p_0 for cv in covs]), "radius": np.array([cv.obstacle_radius for cv in covs]),
                "c": np.array([cv.c for cv in covs]), "ell": np.array([cv.ell for cv in covs]),
                "reach": np.array([cv.barrier_reach for cv in covs]),
                "R": np.array([cv.influence_radius for cv in covs]),
                "e_a": np.array([cv.e_a for cv in covs]), "e_b": np.array([cv.e_b for cv in covs]),
                "target_a": tf[:, 0], "target_b": tf[:, 1]}

    @functools.cached_property
    def p_T(self) -> np.ndarray:
        return np.asarray(self.target, dtype=float)

    @property
    def bounds(self) -> tuple[tuple[float, float], tuple[float, float]]:
        return self.arena.bounds

    def inflated(self, d: float) -> Scene:
        """Every disc grown by `d` (the unicycle's look-ahead point steers around `r + d`, SPEC §3.7); an explicit
        apex or barrier scale grows in proportion (the covering keeps its shape)."""
        def grow(v, r):
            return None if v is None else v * (r + d) / r

        grown = [Obstacle(center=list(o.center), radius=o.radius + d, apex=grow(o.apex, o.radius),
                          barrier_scale=grow(o.barrier_scale, o.radius)) for o in self.obstacles]
        return Scene(target=list(self.target), obstacles=grown, barrier=self.barrier, arena=self.arena,
                     name=f"{self.name}+{d:g}")

    def nearest_obstacle(self, points: np.ndarray) -> np.ndarray:
        """Index of the obstacle whose centre is nearest to each point `(N,)` (the disturbances' frame)."""
        if self.n_obstacles == 1:
            return np.zeros(len(points), dtype=np.int64)
        c = self.arrays["center"]
        d2 = ((np.asarray(points, float)[:, None, :] - c[None]) ** 2).sum(-1)
        return d2.argmin(axis=1)

    def config(self) -> dict:
        """The scene as its config node says it (plain containers; for manifests)."""
        return {f.name: _plain(getattr(self, f.name)) for f in fields(self)}

    # ------------------------------------------------- the single-obstacle names (M = 1)
    def _single(self) -> Covering:
        if self.n_obstacles != 1:
            raise ValueError(f"scene {self.name!r} has {self.n_obstacles} obstacles: use scene.covering(i)")
        return self.covering(0)

    p_0 = property(lambda self: self._single().p_0)
    e_a = property(lambda self: self._single().e_a)
    e_b = property(lambda self: self._single().e_b)
    c = property(lambda self: self._single().c)
    ell = property(lambda self: self._single().ell)
    obstacle_radius = property(lambda self: self._single().obstacle_radius)
    obstacle_center = property(lambda self: self._single().obstacle_center)
    barrier_reach = property(lambda self: self._single().barrier_reach)
    _target_frame = property(lambda self: self._single()._target_frame)
    phi_weight = property(lambda self: 0.5 if self.barrier.kind == "authors_code" else 1.0)
    barrier_rho = property(lambda self: float(self.barrier.rho))
    barrier_kind = property(lambda self: self.barrier.kind)
    barrier_gain = property(lambda self: float(self.barrier.gain))

    def to_frame(self, points):
        return self._single().to_frame(points)

    def from_frame(self, a, b):
        return self._single().from_frame(a, b)


def _plain(v):
    if isinstance(v, list):
        return [_plain(x) for x in v]
    if hasattr(v, "__dataclass_fields__"):
        return {f.name: _plain(getattr(v, f.name)) for f in fields(v)}
    return v
