"""Initial conditions (`conf/init/*.yaml`): explicit points, a grid, random starts, starts near the set K.

Each is a typed dataclass (`_target_` of its config) called with the scene: `starts(scene) -> (N, 2)`. Grids and
random starts cover the arena minus a margin and, with `exclude_diamond`, minus every obstacle's diamond (and
disc); `NearK` draws within a band of the ray behind an obstacle (the set K of Proposition 1, SPEC §3.4).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated

import numpy as np

from pipeline.control import Scene, in_diamond
from pipeline.errors import ConfigError
from pipeline.schema import (
    Interval,
    NonEmpty,
    NonNegative,
    NonNegativeInt,
    Pair,
    Positive,
    PositiveInt,
    checked,
)


def _in_obstacle(scene: Scene, pts: np.ndarray) -> np.ndarray:
    arr = scene.arrays
    d = np.hypot(pts[:, None, 0] - arr["center"][None, :, 0], pts[:, None, 1] - arr["center"][None, :, 1])
    return (d < arr["radius"][None]).any(axis=1)


def _outside(scene: Scene, pts: np.ndarray) -> np.ndarray:
    """Not in any diamond nor on any obstacle disc (a start the hybrid controller can be given)."""
    arr = scene.arrays
    d = np.hypot(pts[:, None, 0] - arr["center"][None, :, 0], pts[:, None, 1] - arr["center"][None, :, 1])
    return ~in_diamond(scene, pts) & (d > arr["radius"][None]).all(axis=1)


def _box(scene: Scene, margin: float, field_: str):
    (x0, x1), (y0, y1) = scene.bounds
    if not (x0 + margin < x1 - margin and y0 + margin < y1 - margin):
        raise ConfigError(f"{field_}.margin", f"{margin:g} leaves no room in the arena")
    return (x0 + margin, x1 - margin), (y0 + margin, y1 - margin)


def _nonempty(pts: np.ndarray, field_: str) -> np.ndarray:
    if len(pts) == 0:
        raise ConfigError(field_, "no initial condition left after excluding the diamonds")
    return pts


@checked("init")
@dataclass(frozen=True)
class Points:
    """Explicit initial conditions (the paper's two by default)."""

    points: Annotated[list[Pair], NonEmpty()] = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        return _clear_of_diamonds(scene, np.asarray(self.points, dtype=float), f"{field_}.points")


SHOWN_STARTS = 3  # violations of the start rule listed in full; the rest are counted by kind


def _clear_of_diamonds(scene: Scene, pts: np.ndarray, name: str) -> np.ndarray:
    """`pts`, after checking SPEC §3.6's start rule: every start outside every obstacle and every diamond. One
    ConfigError lists the first SHOWN_STARTS violations and counts all of them by kind (issue 45)."""
    inside = _in_obstacle(scene, pts)
    arr = scene.arrays
    rel = pts[:, None, :] - arr["center"][None]
    a = np.einsum("nmk,mk->nm", rel, arr["e_a"])
    b = np.einsum("nmk,mk->nm", rel, arr["e_b"])
    hit = (np.abs(a) + np.abs(b) <= arr["c"][None]) & ~inside[:, None]
    if not (inside.any() or hit.any()):
        return pts

    def at(k) -> str:
        return f"start {k} ({pts[k, 0]:.4g}, {pts[k, 1]:.4g})"

    lines = [(k, f"{at(k)} lies inside an obstacle") for k in np.flatnonzero(inside)]
    lines += [(k, f"{at(k)} lies inside obstacle {i}'s diamond |a| + |b| <= c = {arr['c'][i]:.3g}")
              for k, i in zip(*np.nonzero(hit))]
    lines.sort(key=lambda x: x[0])
    n_obs, n_dia = int(inside.sum()), int(hit.sum())
    more = f"; ... and {len(lines) - SHOWN_STARTS} more" if len(lines) > SHOWN_STARTS else ""
    first = int(np.nonzero(hit)[1][0]) if n_dia else 0
    fix = f"; move them or shrink scene.obstacles[{first}].apex" if n_dia else "; move them"
    raise ConfigError(name, f"{len(lines)} start-rule violation(s) ({n_obs} inside an obstacle, {n_dia} inside a "
                            f"diamond; SPEC §3.6: every start outside every obstacle and every diamond): "
                            + "; ".join(line for _, line in lines[:SHOWN_STARTS]) + more + fix)


@checked("init")
@dataclass(frozen=True)
class Circle:
    """`n` starts evenly spaced on the circle of `radius` about `center` (null: the target), from angle `phase`
    (radians): the hybrid-RL benchmark's starts (radius 7 about the goal). `angles` `[from, to]` (degrees, a span
    of at most 360, both ends included) puts them on that arc instead (from `phase` + from); null: the full circle.
    Every start must lie outside every diamond (SPEC §3.6)."""

    n: PositiveInt = 100
    radius: Positive = 7.0
    center: Pair | None = None
    phase: float = 0.0
    angles: Interval | None = None

    def __post_init__(self):
        if self.angles is not None and self.angles[1] - self.angles[0] > 360.0:
            raise ConfigError("init.angles", f"the arc {list(self.angles)} spans more than 360 degrees")

    def on_circle(self, target) -> np.ndarray:
        """The starts `(n, 2)` about `center` (null: `target`), before the start rule is checked."""
        c = np.asarray(target if self.center is None else self.center, dtype=float)
        if self.angles is None:
            th = self.phase + 2.0 * np.pi * np.arange(self.n) / self.n
        else:
            lo, hi = np.radians(np.asarray(self.angles, dtype=float))
            th = self.phase + lo + (hi - lo) * np.arange(self.n) / max(self.n - 1, 1)
        return c + self.radius * np.stack([np.cos(th), np.sin(th)], axis=1)

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        return _clear_of_diamonds(scene, self.on_circle(scene.p_T), field_)


@checked("init")
@dataclass(frozen=True)
class Grid:
    """A regular grid over the arena minus a margin (and the diamonds)."""

    nx: PositiveInt = 21
    ny: PositiveInt = 13
    margin: NonNegative = 2.0
    exclude_diamond: bool = True

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        (x0, x1), (y0, y1) = _box(scene, self.margin, field_)
        pts = np.stack(np.meshgrid(np.linspace(x0, x1, self.nx), np.linspace(y0, y1, self.ny)), axis=-1).reshape(-1, 2)
        return _nonempty(pts[_outside(scene, pts)] if self.exclude_diamond else pts, field_)


@checked("init")
@dataclass(frozen=True)
class Random:
    """Uniform over the arena minus a margin (and the diamonds), seeded."""

    n: PositiveInt = 1000
    seed: NonNegativeInt = 0
    margin: NonNegative = 2.0
    exclude_diamond: bool = True

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        (x0, x1), (y0, y1) = _box(scene, self.margin, field_)
        rng = np.random.default_rng(self.seed)
        pts = rng.uniform([x0, y0], [x1, y1], size=(4 * self.n + 16, 2))
        if self.exclude_diamond:
            pts = pts[_outside(scene, pts)]
        return _nonempty(pts[: self.n], field_)


@checked("init")
@dataclass(frozen=True)
class NearK:
    """Within `band` of the set K of Proposition 1 behind obstacle `obstacle` (`a` in `a_range` of its frame,
    `|b| < band`); with several obstacles and `obstacle: null`, the starts are dealt out over every obstacle."""

    n: PositiveInt = 200
    seed: NonNegativeInt = 0
    band: Positive = 0.5
    a_range: Interval = field(default_factory=lambda: [-45.0, -15.0])
    obstacle: int | None = None

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        rng = np.random.default_rng(self.seed)
        a = rng.uniform(*self.a_range, self.n)
        b = rng.uniform(-self.band, self.band, self.n)
        if scene.n_obstacles == 1 or self.obstacle is not None:
            return scene.covering(self.obstacle or 0).from_frame(a, b)
        which = np.arange(self.n) % scene.n_obstacles
        out = np.empty((self.n, 2))
        for i in range(scene.n_obstacles):
            rows = which == i
            out[rows] = scene.covering(i).from_frame(a[rows], b[rows])
        return out


@dataclass(frozen=True)
class BehindObstacles:
    """Near the set `K_i` behind the obstacles of a field (SPEC §3.6: Proposition 1 once per obstacle): `n` starts
    on obstacle i's ray away from the target, at `a` in `-(c_i + gap + depth) .. -(c_i + gap)` of its frame (`c_i`
    its apex: just behind its diamond) and `|b| < band`, kept where obstacle i's cell is the nearest
    (`dist_j = |p - c_j| - R_j`), inside the arena by `margin` and outside every disc and diamond (rejection,
    seeded). The starts are dealt out over the obstacles whose K lies in the arena (`obstacles(scene)`: an
    obstacle near the arena's edge with its back to it has none there)."""

    n: int = 200
    seed: int = 0
    band: float = 0.5
    gap: float = 1.0
    depth: float = 10.0
    margin: float = 1.0

    def _candidates(self, scene: Scene, i: int, k: int, rng) -> np.ndarray:
        arr = scene.arrays
        (x0, x1), (y0, y1) = _box(scene, self.margin, "init")
        c = float(arr["c"][i])
        a = -rng.uniform(c + self.gap, c + self.gap + self.depth, k)
        p = scene.covering(i).from_frame(a, rng.uniform(-self.band, self.band, k))
        rel = p[:, None, :] - arr["center"][None]
        dist = np.hypot(rel[..., 0], rel[..., 1]) - arr["R"][None]
        ok = ((dist.argmin(axis=1) == i) & _outside(scene, p) & (p[:, 0] > x0) & (p[:, 0] < x1)
              & (p[:, 1] > y0) & (p[:, 1] < y1))
        return p[ok]

    def obstacles(self, scene: Scene) -> list[int]:
        """The obstacles with room behind them (at least a tenth of a probe batch lands in the allowed region)."""
        rng = np.random.default_rng(self.seed)
        return [i for i in range(scene.n_obstacles) if len(self._candidates(scene, i, 200, rng)) >= 20]

    def __call__(self, scene: Scene, field_: str = "init") -> np.ndarray:
        _box(scene, self.margin, field_)
        which = self.obstacles(scene)
        if not which:
            raise ConfigError(f"{field_}.depth", "no obstacle has room behind it in the arena: lower depth or gap")
        rng = np.random.default_rng(self.seed)
        out = []
        for j, i in enumerate(which):
            want = self.n // len(which) + (j < self.n % len(which))
            got = np.zeros((0, 2))
            while len(got) < want:
                got = np.concatenate([got, self._candidates(scene, i, 8 * want + 16, rng)])
            out.append(got[:want])
        return np.concatenate(out)
