"""Dense fields like the hybrid-RL benchmark's (issue 29; docs/dense.md): discs of one radius 2.5-5 apart around a
goal inside the clutter, starts on a circle about it, with the dense covering (apex `sqrt(2) (r + clearance)`,
barrier reach `reach`) and drawn until SPEC §3.6's V1-V3 and the start rule hold for the loop it will run in.

:func:`benchmark_scene` (issue 45) draws the benchmark's own statistics instead (8-12 discs, centres at least 2.1
apart) and gives each field the largest covering it admits from its discs alone (the covering `fieldcheck
write=FILE` writes), or says in one line why none exists."""

from __future__ import annotations

import math

import numpy as np

from pipeline.control.admitted import checked_covering
from pipeline.control.fields import analyse_field
from pipeline.control.scene import Arena, Barrier, Obstacle, Scene
from pipeline.control.validity import field_violations
from pipeline.errors import ConfigError
from pipeline.schema import NonNegative, Positive, PositiveInt

FIELD = "scene"


def dense_centres(n: int, rng: np.random.Generator, *, spacing: tuple[float, float], extent: float, goal_clear: float,
                  batch: int = 512) -> np.ndarray | None:
    """One sequential draw: each centre within `extent` of the goal (the origin here), at least `spacing[0]` from
    every placed centre and within `spacing[1]` of one of them (the first: of the goal), at least `goal_clear` from
    the goal. `(n, 2)`, or None when a disc finds no place in one batch."""
    lo, hi = spacing
    cs = np.zeros((0, 2))
    for _ in range(n):
        rad = extent * np.sqrt(rng.uniform(0.0, 1.0, batch))
        ang = rng.uniform(0.0, 2.0 * np.pi, batch)
        c = np.stack([rad * np.cos(ang), rad * np.sin(ang)], axis=1)
        ok = rad > goal_clear
        if len(cs):
            d = np.hypot(*np.moveaxis(c[:, None, :] - cs[None], -1, 0))
            ok &= (d.min(axis=1) >= lo) & (d.min(axis=1) <= hi)
        else:
            ok &= rad <= hi
        if not ok.any():
            return None
        cs = np.vstack([cs, c[np.flatnonzero(ok)[0]]])
    return cs


def dense_scene(n_obstacles: PositiveInt = 10, seed: int = 0, radius: Positive = 0.5,
                spacing: tuple[float, float] = (2.5, 5.0), extent: Positive = 5.5, target: list[float] = (0.0, 0.0),
                goal_clearance: Positive = 2.0, start_radius: Positive = 7.0, n_starts: PositiveInt = 100, clearance: NonNegative = 0.1,
                reach: Positive = 0.2, h: Positive = 0.05, u_max: Positive = 1.0, T_s: Positive = 0.05,
                half_width: Positive = 10.0, inflation: NonNegative = 0.0, max_tries: PositiveInt = 200, name: str = "dense") -> Scene:
    """A seeded dense field (`conf/scene/dense.yaml`): `n_obstacles` discs of `radius`, centres `spacing` apart
    within `extent` of the goal `target` and at least `goal_clearance` from it, arena the square of `half_width` about it. Covering: apex
    `sqrt(2) (radius + clearance)`, barrier reach `reach` (rho_b = 0.5, scale `reach / sqrt(0.5)`), so
    `R = apex + sqrt(2) reach`. Redrawn (seed, then seed's stream) until V1-V3 (for `h`, `u_max`, `T_s`) and the
    start rule for the `n_starts` starts on the circle of `start_radius` hold, also with every disc grown by
    `inflation` (the unicycle's look-ahead, as `Scene.inflated` grows it); ConfigError after `max_tries`."""
    lo, hi = (float(x) for x in spacing)
    if not 0 < lo <= hi:
        raise ConfigError(f"{FIELD}.spacing", f"must be 0 < min <= max, got {spacing!r}")
    apex = math.sqrt(2.0) * (radius + clearance)
    R = (apex + math.sqrt(2.0) * reach) * (radius + inflation) / radius
    p_T = np.asarray(target, dtype=float)
    th = 2.0 * np.pi * np.arange(n_starts) / n_starts
    starts = p_T + start_radius * np.stack([np.cos(th), np.sin(th)], axis=1)
    arena = ((p_T[0] - half_width, p_T[0] + half_width), (p_T[1] - half_width, p_T[1] + half_width))
    rng = np.random.default_rng(seed)
    for _ in range(int(max_tries)):
        cs = dense_centres(int(n_obstacles), rng, spacing=(lo, hi), extent=extent, goal_clear=max(goal_clearance, R + 1e-6))
        if cs is None:
            continue
        cs = cs + p_T
        grow = (radius + inflation) / radius  # Scene.inflated: the unicycle's steering scene (SPEC §3.7)
        bad = field_violations(cs, np.full(len(cs), radius + inflation), p_T, apex=apex * grow, reach=reach * grow,
                               h=h, u_max=u_max, T_s=T_s, arena=arena, starts=starts)
        if not bad:
            obstacles = [Obstacle(center=[float(x), float(y)], radius=float(radius), apex=float(apex),
                                  barrier_scale=float(reach / math.sqrt(0.5))) for x, y in cs]
            return Scene(target=[float(x) for x in p_T], obstacles=obstacles, barrier=Barrier(rho=0.5),
                         arena=Arena(x=list(arena[0]), y=list(arena[1])), name=name)
    raise ConfigError(f"{FIELD}.n_obstacles", f"no valid dense field of {n_obstacles} discs of radius {radius} "
                                              f"{lo}-{hi} apart within {extent} of the goal in {max_tries} draws "
                                              f"(R = {R:.3g}, h = {h}, u_max T_s = {u_max * T_s:.3g}): fewer discs, "
                                              f"a larger extent, or a thinner covering")


def benchmark_scene(n_obstacles: tuple[int, int] = (8, 12), seed: int = 0, radius: Positive = 0.5,
                    spacing: Positive = 2.1, extent: Positive = 5.5, target: list[float] = (0.0, 0.0),
                    goal_clearance: Positive = 2.0, start_radius: Positive = 7.0, n_starts: PositiveInt = 100,
                    h: Positive = 0.05, u_max: Positive = 1.0, T_s: Positive = 0.05, half_width: Positive = 10.0,
                    inflation: NonNegative = 0.0, write_margin: Positive = 0.1, max_tries: PositiveInt = 200,
                    name: str = "benchmark") -> Scene:
    """A seeded field with the hybrid-RL benchmark's statistics (`conf/scene/benchmark.yaml`): a number of discs
    drawn uniformly in `n_obstacles` (inclusive), of `radius`, centres at least `spacing` apart, within `extent` of
    the goal `target` and at least `goal_clearance` from it; arena the square of `half_width` about the goal;
    `n_starts` starts on the circle of `start_radius`. The covering is the largest uniform one V1-V3 and the start
    rule admit for the loop it will run in (`h`, `u_max`, `T_s`, the discs grown by `inflation`: the unicycle's
    look-ahead), `write_margin` of the headroom kept back (:func:`pipeline.control.admitted.checked_covering`,
    the covering `fieldcheck write=FILE` writes); a field that admits none: ConfigError naming the pair of discs
    and the shortfall. Only the draw of the centres is retried (`max_tries`: a disc that finds no place)."""
    lo, hi = (int(x) for x in n_obstacles)
    if not 1 <= lo <= hi:
        raise ConfigError(f"{FIELD}.n_obstacles", f"must be [min, max] with 1 <= min <= max, got {list(n_obstacles)!r}")
    p_T = np.asarray(target, dtype=float)
    rng = np.random.default_rng(seed)
    n = int(rng.integers(lo, hi + 1))
    for _ in range(int(max_tries)):
        cs = dense_centres(n, rng, spacing=(float(spacing), 4.0 * float(extent)), extent=extent, goal_clear=goal_clearance)
        if cs is not None:
            break
    else:
        raise ConfigError(f"{FIELD}.n_obstacles", f"{n} discs {spacing} apart do not fit within {extent} of the goal "
                                                  f"in {max_tries} draws: fewer discs or a larger extent")
    cs = cs + p_T
    th = 2.0 * np.pi * np.arange(n_starts) / n_starts
    starts = p_T + start_radius * np.stack([np.cos(th), np.sin(th)], axis=1)
    arena = ((p_T[0] - half_width, p_T[0] + half_width), (p_T[1] - half_width, p_T[1] + half_width))
    rr = np.full(n, radius + inflation)
    ana = analyse_field(cs, rr, p_T, starts=starts, arena=arena, h=h, u_max=u_max, T_s=T_s)
    f, g, _ = checked_covering(ana, cs, rr, p_T, margin=write_margin, starts=starts, h=h, u_max=u_max, T_s=T_s,
                               arena=arena)
    # written for the discs' own radius: the unicycle's steering grows apex and reach by (r + d) / r (Scene.inflated)
    obstacles = [Obstacle(center=[float(x), float(y)], radius=float(radius), apex=float(f * radius),
                          barrier_scale=float(g * radius / math.sqrt(0.5))) for x, y in cs]
    return Scene(target=[float(x) for x in p_T], obstacles=obstacles, barrier=Barrier(rho=0.5),
                 arena=Arena(x=list(arena[0]), y=list(arena[1])), name=name)
