"""Fields of several obstacles (SPEC §3.6): derived quantities, the validity conditions V1–V3, random valid
fields, and the authors' 12-disc field.

Pure numpy on plain arrays, no Hydra, no I/O; the multi-obstacle scene calls these functions.

Per obstacle `i` (0-based, as in the config list `scene.obstacles`): centre `c_i`, radius `r_i`, covering
apex `c^a_i` (default `2 sqrt(2) r_i`, which must exceed `sqrt(2) r_i` so that the diamond
`|a| + |b| <= c^a_i` contains the disc), barrier reach `rho_i = sqrt(rho_b) l_i` (`l_i` the barrier scale,
default `r_i`) and influence radius `R_i = c^a_i + sqrt(2) rho_i`: outside `disc(c_i, R_i)` both of obstacle
`i`'s barriers vanish. The obstacle frame has origin `c_i`, axis `e_a` from `c_i` towards `p_T` and `e_b` its
left-hand normal (SPEC §3.1).

Conditions (SPEC §3.6), reported by `field_violations` in this order:

- `arena`: every obstacle disc (radius `r_i`, not inflated) lies in the arena (closed); so do the target and
  every start;
- `V1`: `|p_T - c_i| > R_i` (the target outside obstacle `i`'s influence disc);
- `V2`: `|c_i - c_j| > R_i + R_j + h` for every pair (the cell switching locus outside both influence discs);
- `V3`: `(|c_i - c_j| - R_i - R_j - h) / 2 > u_max T_s` (sampled loop only: a held frame cannot carry the
  vehicle across the hysteresis band);
- `start`: every start lies outside every diamond, by more than `start_clearance` (Euclidean distance).

Unicycle (SPEC §3.7): `inflation = d` builds every covering for the disc of radius `r_i + d` (the apex and
barrier-scale defaults scale with `r_i + d`); the arena check keeps the real disc, and the start clearance
defaults to `d`, so that the look-ahead point `z`, within `d` of the axle point, is outside the diamond
whatever the heading.

Every shortfall is in world units: how far the quantity misses its bound (`>= 0` for a violation; the bound is
strict for V1–V3 and the start, closed for the arena).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError

SQRT2 = math.sqrt(2.0)
DEFAULT_APEX_FACTOR = 2.0 * SQRT2
DEFAULT_BARRIER_RHO = 0.5
DEFAULT_ARENA = ((-50.0, 50.0), (-30.0, 30.0))
CONDITIONS = ("arena", "V1", "V2", "V3", "start")

# Config fields named in errors (SPEC's config layout: conf/controller, conf/camera, conf/init).
OBSTACLES_FIELD = "scene.obstacles"
TARGET_FIELD = "scene.target"
ARENA_FIELD = "scene.arena"
STARTS_FIELD = "init.points"
HYSTERESIS_FIELD = "controller.cell_hysteresis"
U_MAX_FIELD = "controller.u_max"
PERIOD_FIELD = "camera.period"
RANDOM_FIELD = "scene"   # a random field is the `scene` node itself (conf/scene/field.yaml)


# ----------------------------------------------------------------------------- derived quantities
def default_apex(radii, apex=None) -> np.ndarray:
    """Covering apex per obstacle, `(M,)`: `apex` where given, `2 sqrt(2) r_i` where `apex` is None or NaN.
    `apex` may be a scalar (every obstacle) or `(M,)`."""
    r = np.asarray(radii, dtype=float).reshape(-1)
    if apex is None:
        return DEFAULT_APEX_FACTOR * r
    a = np.broadcast_to(np.asarray(apex, dtype=float), r.shape).copy()
    missing = np.isnan(a)
    a[missing] = DEFAULT_APEX_FACTOR * r[missing]
    return a


def barrier_reach(rho_b, scale) -> np.ndarray:
    """Reach of SPEC's squared barrier `B(d_q / l^2)`: `rho = sqrt(rho_b) l` (Euclidean distance from the wedge
    beyond which it vanishes). Broadcasts."""
    return np.sqrt(np.asarray(rho_b, dtype=float)) * np.asarray(scale, dtype=float)


def influence_radius(apex, reach) -> np.ndarray:
    """`R_i = c^a_i + sqrt(2) rho_i` (SPEC §3.6): outside `disc(c_i, R_i)` both barriers of obstacle i vanish
    (the diamond's vertices are at distance `c^a_i`, the wedges' faces meet at 90 degrees, so the reach `rho`
    past the apex is `sqrt(2) rho` along the axis)."""
    return np.asarray(apex, dtype=float) + SQRT2 * np.asarray(reach, dtype=float)


def cell_distance(points, centers, R) -> np.ndarray:
    """`dist_i(p) = |p - c_i| - R_i` for `(N, 2)` points and M obstacles: `(N, M)`."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    return np.hypot(*np.moveaxis(p[:, None, :] - c[None, :, :], -1, 0)) - np.asarray(R, dtype=float)


def obstacle_frames(centers, target) -> tuple[np.ndarray, np.ndarray]:
    """Unit axes `(e_a, e_b)`, each `(M, 2)`: `e_a` from `c_i` towards `p_T`, `e_b` its left-hand normal
    (`e_a = (1, 0)` for an obstacle centred on the target, which V1 rejects anyway)."""
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    d = np.asarray(target, dtype=float).reshape(1, 2) - c
    n = np.hypot(d[:, 0], d[:, 1])
    e_a = np.where(n[:, None] > 0, d / np.where(n > 0, n, 1.0)[:, None], np.array([1.0, 0.0]))
    return e_a, np.stack([-e_a[:, 1], e_a[:, 0]], axis=1)


def to_frames(points, centers, target) -> tuple[np.ndarray, np.ndarray]:
    """Obstacle-frame coordinates `(a, b)` of `(N, 2)` points in every obstacle's frame: each `(N, M)`."""
    p = np.asarray(points, dtype=float).reshape(-1, 2)
    c = np.asarray(centers, dtype=float).reshape(-1, 2)
    e_a, e_b = obstacle_frames(c, target)
    d = p[:, None, :] - c[None, :, :]
    return np.einsum("nmk,mk->nm", d, e_a), np.einsum("nmk,mk->nm", d, e_b)


def diamond_signed_distance(points, centers, apex, target) -> np.ndarray:
    """Euclidean signed distance from `(N, 2)` points to each obstacle's diamond `|a| + |b| <= c^a_i`,
    `(N, M)`: positive outside, negative inside (minus the distance to the boundary), zero on it. In the
    rotated coordinates `u = (a + b)/sqrt(2)`, `v = (b - a)/sqrt(2)` the diamond is the square
    `max(|u|, |v|) <= c^a_i / sqrt(2)`."""
    a, b = to_frames(points, centers, target)
    half = np.asarray(apex, dtype=float) / SQRT2
    ex = np.abs(a + b) / SQRT2 - half
    ey = np.abs(b - a) / SQRT2 - half
    return np.hypot(np.maximum(ex, 0.0), np.maximum(ey, 0.0)) + np.minimum(np.maximum(ex, ey), 0.0)


# ----------------------------------------------------------------------------- inputs
def fmt(x: float) -> str:
    """A number as the validity messages print it: 2 decimals, or 2 significant digits below 0.1."""
    x = float(x)
    return f"{x:.2f}" if abs(x) >= 0.1 or x == 0 else f"{x:.2g}"


def positive(value, name: str, *, allow_none: bool = False) -> float | None:
    """`value` as a float > 0 (None passes when `allow_none`), else one ConfigError naming `name`."""
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(name, f"must be a number > 0, got {value!r}") from None
    if not (math.isfinite(v) and v > 0):
        raise ConfigError(name, f"must be > 0{' (or null)' if allow_none else ''}, got {value!r}")
    return v


def arena_box(arena) -> np.ndarray | None:
    """The arena `((x_min, x_max), (y_min, y_max))` as a checked `(2, 2)` array (None stays None)."""
    if arena is None:
        return None
    try:
        a = np.asarray(arena, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(ARENA_FIELD, f"must be ((x_min, x_max), (y_min, y_max)), got {arena!r}") from None
    if a.shape != (2, 2) or not np.all(np.isfinite(a)) or not np.all(a[:, 0] < a[:, 1]):
        raise ConfigError(ARENA_FIELD, f"must be ((x_min, x_max), (y_min, y_max)) with min < max, got {arena!r}")
    return a


def as_points(value, name: str) -> np.ndarray:
    """`value` as finite `(N, 2)` points, else one ConfigError naming `name`."""
    try:
        p = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise ConfigError(name, f"must be a list of [x, y] points, got {value!r}") from None
    p = p.reshape(-1, 2) if p.size % 2 == 0 and p.ndim <= 2 and (p.ndim < 2 or p.shape[-1] == 2) else None
    if p is None or not np.all(np.isfinite(p)):
        raise ConfigError(name, f"must be a list of finite [x, y] points, got {value!r}")
    return p


@dataclass(frozen=True, eq=False)
class FieldGeometry:
    """Validated arrays of a field: centres `(M, 2)`, radii `r_i (M,)`, the covering radii `r_i + inflation`,
    apex `(M,)`, reach `(M,)`, `R (M,)` and the target `(2,)`."""

    centers: np.ndarray
    radii: np.ndarray
    cover_radii: np.ndarray
    apex: np.ndarray
    reach: np.ndarray
    R: np.ndarray
    target: np.ndarray


def field_geometry(centers, radii, target, *, apex=None, reach=None, inflation: float = 0.0) -> FieldGeometry:
    """Validate a field's arrays and derive apex, reach and `R` (ConfigError on malformed input).

    `apex`: None, a scalar or `(M,)` with NaN for the default `2 sqrt(2) (r_i + inflation)`; it must exceed
    `sqrt(2) (r_i + inflation)`. `reach`: None for SPEC's default `sqrt(0.5) (r_i + inflation)` (rho_b = 0.5,
    l_i = r_i + inflation; see `barrier_reach`), a scalar or `(M,)`, > 0."""
    c = np.asarray(centers, dtype=float)
    if c.ndim != 2 or c.shape[1] != 2 or c.shape[0] < 1 or not np.all(np.isfinite(c)):
        raise ConfigError(OBSTACLES_FIELD, f"centres must be a non-empty (M, 2) array of finite numbers, got shape {c.shape}")
    M = c.shape[0]
    r = np.asarray(radii, dtype=float).reshape(-1)
    if r.shape != (M,):
        raise ConfigError(OBSTACLES_FIELD, f"need one radius per obstacle ({M}), got {r.size}")
    bad = np.flatnonzero(~(np.isfinite(r) & (r > 0)))
    if bad.size:
        raise ConfigError(f"{OBSTACLES_FIELD}[{bad[0]}]", f"radius must be > 0, got {r[bad[0]]!r}")
    p_T = as_points(target, TARGET_FIELD)
    if p_T.shape != (1, 2):
        raise ConfigError(TARGET_FIELD, f"must be one point [x, y], got {target!r}")
    d = float(inflation)
    if not (math.isfinite(d) and d >= 0):
        raise ConfigError("vehicle.lookahead", f"the inflation d must be >= 0, got {inflation!r}")
    rc = r + d
    try:
        a = default_apex(rc, apex)
    except ValueError:
        raise ConfigError(OBSTACLES_FIELD, f"need one apex per obstacle ({M}) or a single one, got {apex!r}") from None
    bad = np.flatnonzero(~(np.isfinite(a) & (a > SQRT2 * rc)))
    if bad.size:
        i = bad[0]
        raise ConfigError(
            f"{OBSTACLES_FIELD}[{i}]",
            f"apex {a[i]!r} must exceed sqrt(2) r_{i} = {fmt(SQRT2 * rc[i])} (the diamond |a| + |b| <= c must "
            f"contain the disc{' inflated by d' if d else ''})",
        )
    try:
        rho = barrier_reach(DEFAULT_BARRIER_RHO, rc) if reach is None else np.broadcast_to(
            np.asarray(reach, dtype=float), (M,)).copy()
    except ValueError:
        raise ConfigError(OBSTACLES_FIELD, f"need one barrier reach per obstacle ({M}) or a single one, got {reach!r}") from None
    bad = np.flatnonzero(~(np.isfinite(rho) & (rho > 0)))
    if bad.size:
        raise ConfigError(f"{OBSTACLES_FIELD}[{bad[0]}]", f"barrier reach sqrt(rho_b) l must be > 0, got {rho[bad[0]]!r}")
    return FieldGeometry(c, r, rc, a, rho, influence_radius(a, rho), p_T[0])


# ----------------------------------------------------------------------------- validity
@dataclass(frozen=True)
class Violation:
    """One violated condition: the config `field` it concerns (`scene.obstacles[i]`, `scene.obstacles[i,j]`,
    `scene.target`, `init.points[k]`), the `condition` (one of CONDITIONS), the `shortfall` (world units, >= 0)
    and a one-line `message` (without the field). `obstacles` are the obstacle indices involved."""

    field: str
    condition: str
    shortfall: float
    message: str
    obstacles: tuple[int, ...] = ()

    @property
    def line(self) -> str:
        return f"{self.field}: {self.message}"

    def error(self) -> ConfigError:
        return ConfigError(self.field, self.message)


def loop_params(h, u_max, T_s) -> tuple[float, float]:
    """`(h, u_max T_s)`; the step is 0 for a continuous loop (T_s or u_max None)."""
    h = positive(h, HYSTERESIS_FIELD)
    u = positive(u_max, U_MAX_FIELD, allow_none=True)
    t = positive(T_s, PERIOD_FIELD, allow_none=True)
    return h, (u * t if u is not None and t is not None else 0.0)


def field_violations(
    centers,
    radii,
    target,
    *,
    apex=None,
    reach=None,
    h: float = 1.0,
    u_max: float | None = None,
    T_s: float | None = None,
    arena=None,
    starts=None,
    inflation: float = 0.0,
    start_clearance: float | None = None,
    margin: float = 0.0,
) -> list[Violation]:
    """Every violated condition of SPEC §3.6, in the order arena, V1, V2, V3, start (within one condition by
    obstacle index, pair `(i, j)` with `i < j`, or start index). Empty: the field is valid.

    `apex`, `reach`, `inflation`: see `field_geometry`. `h`: the cell hysteresis. V3 is checked only when
    `u_max` and `T_s` are both given (a sampled loop). `arena`: `((x_min, x_max), (y_min, y_max))` or None
    (not checked). `starts`: `(K, 2)` or None; `start_clearance` (default: `inflation`) is the Euclidean
    distance every start keeps from every diamond. `margin` >= 0 asks every obstacle condition to hold with
    that slack (world units; V3 per side; the target and the starts need only lie in the arena), and is
    included in the shortfalls.
    """
    g = field_geometry(centers, radii, target, apex=apex, reach=reach, inflation=inflation)
    h, step = loop_params(h, u_max, T_s)
    sampled = u_max is not None and T_s is not None
    box = arena_box(arena)
    P = np.zeros((0, 2)) if starts is None else as_points(starts, STARTS_FIELD)
    clear = float(inflation) if start_clearance is None else float(start_clearance)
    margin = float(margin)
    if not (math.isfinite(clear) and clear >= 0):
        raise ConfigError(STARTS_FIELD, f"start clearance must be >= 0, got {start_clearance!r}")
    if not (math.isfinite(margin) and margin >= 0):
        raise ConfigError(RANDOM_FIELD + ".margin", f"must be >= 0, got {margin!r}")
    c, r, R, p_T = g.centers, g.radii, g.R, g.target
    out: list[Violation] = [] if box is None else _arena_violations(c, r, p_T, P, box, margin)
    out += _v1_violations(c, R, p_T, margin)
    out += _pair_violations(c, R, h, step if sampled else None, margin)
    if len(P):
        out += _start_violations(P, c, g.apex, p_T, clear, margin)
    return out


def _arena_violations(c, r, p_T, P, box, margin: float) -> list[Violation]:
    """`arena`: the discs, the target and the starts in the (closed) arena box; the discs by `margin`."""
    out = []
    lo, hi = box[:, 0], box[:, 1]
    names = ("x_min", "y_min", "x_max", "y_max")

    def overflow(pts: np.ndarray, rad: np.ndarray) -> np.ndarray:  # (N, 4): how far past each side
        return np.concatenate([lo - (pts - rad[:, None]), (pts + rad[:, None]) - hi], axis=1) + margin

    bounds = np.concatenate([lo, hi])
    over = overflow(c, r)
    for i in np.flatnonzero(over.max(axis=1) > 0):
        s = int(np.argmax(over[i]))
        out.append(Violation(
            f"{OBSTACLES_FIELD}[{i}]", "arena", float(over[i, s]),
            f"arena: obstacle {i}'s disc (centre ({fmt(c[i, 0])}, {fmt(c[i, 1])}), r = {fmt(r[i])}) reaches "
            f"{fmt(over[i, s])} past the arena's {names[s]} = {fmt(bounds[s])}"
            f"{f' (margin {fmt(margin)})' if margin else ''}; move it inside or shrink it", (int(i),)))
    over_t = overflow(p_T[None], np.zeros(1))[0] - margin
    if over_t.max() > 0:
        s = int(np.argmax(over_t))
        out.append(Violation(TARGET_FIELD, "arena", float(over_t[s]),
                             f"arena: the target lies {fmt(over_t[s])} past the arena's {names[s]} = {fmt(bounds[s])}"))
    if len(P):
        over_p = overflow(P, np.zeros(len(P))) - margin
        for k in np.flatnonzero(over_p.max(axis=1) > 0):
            s = int(np.argmax(over_p[k]))
            out.append(Violation(f"{STARTS_FIELD}[{k}]", "arena", float(over_p[k, s]),
                                 f"arena: the start lies {fmt(over_p[k, s])} past the arena's {names[s]} = {fmt(bounds[s])}"))
    return out


def _v1_violations(c, R, p_T, margin: float) -> list[Violation]:
    """`V1`: the target outside every influence disc."""
    dT = np.hypot(*(p_T - c).T)
    short1 = R + margin - dT
    return [Violation(
        f"{OBSTACLES_FIELD}[{i}]", "V1", float(short1[i]),
        f"V1: the target is {fmt(short1[i])} units too close (|p_T - c_{i}| = {fmt(dT[i])}, needs > R_{i} = "
        f"{fmt(R[i])}{f' + margin {fmt(margin)}' if margin else ''}); move the target or shrink obstacle "
        f"{i}'s apex or barrier scale", (int(i),)) for i in np.flatnonzero(short1 >= 0)]


def _pair_violations(c, R, h: float, step: float | None, margin: float) -> list[Violation]:
    """`V2` for every pair, then `V3` (a sampled loop: `step = u_max T_s`, None for a continuous one), vectorised."""
    ii, jj = np.triu_indices(len(R), 1)
    dij = np.hypot(*(c[ii] - c[jj]).T)
    need2 = R[ii] + R[jj] + h
    short2 = need2 + margin - dij
    out = [Violation(
        f"{OBSTACLES_FIELD}[{i},{j}]", "V2", float(s),
        f"V2: centres {fmt(d)} apart, need > R_{i} + R_{j} + h = {fmt(n)}{f' + margin {fmt(margin)}' if margin else ''} "
        f"(short by {fmt(s)}); move them apart or shrink their apex or barrier scale", (int(i), int(j)))
        for i, j, d, n, s in zip(ii, jj, dij, need2, short2) if s >= 0]
    if step is not None:
        side = (dij - need2) / 2.0
        short3 = step + margin - side
        out.extend(Violation(
            f"{OBSTACLES_FIELD}[{i},{j}]", "V3", float(s),
            f"V3: the gap between their influence discs leaves (|c_{i} - c_{j}| - R_{i} - R_{j} - h)/2 = "
            f"({fmt(d)} - {fmt(n)})/2 = {fmt(sd)} per side, need > u_max T_s = {fmt(step)}"
            f"{f' + margin {fmt(margin)}' if margin else ''} (short by {fmt(s)})", (int(i), int(j)))
            for i, j, d, n, sd, s in zip(ii, jj, dij, need2, side, short3) if s >= 0)
    return out


def _start_violations(P, c, apex, p_T, clear: float, margin: float) -> list[Violation]:
    """`start`: every start outside every diamond, by more than the clearance."""
    out = []
    sd = diamond_signed_distance(P, c, apex, p_T)
    short_s = clear + margin - sd
    for k, i in zip(*np.nonzero(short_s >= 0)):
        inside = sd[k, i] <= 0
        where = (f"lies inside obstacle {i}'s diamond |a| + |b| <= c_{i} = {fmt(apex[i])} ({fmt(-sd[k, i])} "
                 f"from its boundary)" if inside else
                 f"is {fmt(sd[k, i])} from obstacle {i}'s diamond (c_{i} = {fmt(apex[i])})")
        need = f"; needs > {fmt(clear + margin)}" if clear + margin > 0 else ""
        out.append(Violation(
            f"{STARTS_FIELD}[{k}]", "start", float(short_s[k, i]),
            f"start: ({fmt(P[k, 0])}, {fmt(P[k, 1])}) {where}{need} (short by {fmt(short_s[k, i])}); move the "
            f"start or shrink obstacle {i}'s apex", (int(i),)))
    return out


def check_field(*args, **kwargs) -> None:
    """`field_violations(*args, **kwargs)`, raising ConfigError for the first violation in its documented
    order (arena, V1, V2, V3, start) and counting the others in the same line."""
    found = field_violations(*args, **kwargs)
    if found:
        v = found[0]
        sampled = kwargs.get("u_max") is not None and kwargs.get("T_s") is not None
        which = "V1-V3" if sampled else "V1-V2 (V3 is checked once the frame period is known)"
        more = f" [{len(found) - 1} more violation(s) of SPEC §3.6's {which}]" if len(found) > 1 else ""
        raise ConfigError(v.field, v.message + more)


# ----------------------------------------------------------------------------- random valid fields
