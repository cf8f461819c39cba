"""What a dataset recipe means: validated recipe, positions of leader and follower, per-image cloud choices.

Everything random is drawn here, per split, from `np.random.SeedSequence(seed).spawn(3)` (train, val,
test) in a fixed order (leader, follower presence, follower, clouds), before any rendering, so the bytes
depend on the recipe and seed only (not on the chunk size). With a parent dataset (`sampling.parent`, the
DAgger aggregation) the new train draws use a stream keyed by the parent too, so they never repeat the
parent's; val and test are drawn as without parent. Draws that belong to no split (`STREAMS`: "gate", the fresh
clean positions a map's flag gate is fitted on, `pipeline.train.evaluate.gate_frames`) take the next children of
the same sequence, so they never repeat a split's draws and never change them.
"""

from __future__ import annotations

import hashlib
import math
from dataclasses import dataclass

import numpy as np

from pipeline.data.closed_loop import Pool
from pipeline.data.closed_loop import pool as cached_pool
from pipeline.data.recipe import SPLITS, Recipe
from pipeline.errors import ConfigError
from pipeline.render import Camera, CloudSample, Occlusion

STREAMS = (*SPLITS, "gate")  # a split's draws, or fresh draws from the recipe's distribution for no split
_MAX_ROUNDS = 64  # rejection-sampling rounds (each vectorised over the rejected rows)


def _closed_loop_positions(rng: np.random.Generator, n: int, camera: Camera, recipe: Recipe, pool: Pool):
    """`share` of `n` positions from the pool (jittered, inside the box), the rest uniform, shuffled. Pool
    entries are drawn uniformly, or by the map's error there (`Pool.probabilities`, `error_weighted`)."""
    lo, hi = _box(camera, recipe)
    cl = recipe.closed_loop
    m = int(round(cl.share * n))
    out = np.empty((n, 2))
    out[m:] = _uniform(rng, n - m, camera, recipe)
    prob = pool.probabilities(cl)
    bad = np.arange(m)
    for _ in range(_MAX_ROUNDS):
        if bad.size == 0:
            break
        idx = rng.integers(0, len(pool), bad.size) if prob is None else rng.choice(len(pool), bad.size, p=prob)
        out[bad] = pool.positions[idx] + rng.normal(0.0, cl.jitter, (bad.size, 2))
        inside = np.all((out[bad] >= lo) & (out[bad] <= hi), axis=1) & _allowed(out[bad], camera, recipe)
        bad = bad[~inside]
    out[bad] = np.clip(out[bad], lo, hi)
    return out[rng.permutation(n)]


@dataclass
class SplitPlan:
    """Everything random about one split, drawn before rendering."""

    leader: np.ndarray  # float32 (n, 2), world units (the label)
    follower: np.ndarray  # float32 (n, 2), NaN rows = no follower
    clouds: CloudSample
    heading: np.ndarray | None = None  # float32 (n,) radians: a vehicle with a heading (the label's θ)

    def __len__(self) -> int:
        return len(self.leader)


def _box(camera: Camera, recipe: Recipe) -> tuple[np.ndarray, np.ndarray]:
    """Sampling rectangle: the arena shrunk by the margin (default: half the robot's side)."""
    (x0, x1), (y0, y1) = camera.arena
    m = recipe.sampling.margin if recipe.sampling.margin is not None else camera.robot_size / 2 / camera.scale
    lo, hi = np.array([x0 + m, y0 + m]), np.array([x1 - m, y1 - m])
    if np.any(hi <= lo):
        raise ConfigError("data.sampling.margin", f"{m:g} leaves no room in the arena {camera.arena}")
    return lo, hi


def _allowed(points: np.ndarray, camera: Camera, recipe: Recipe) -> np.ndarray:
    if not recipe.sampling.exclude_obstacle or camera.scene is None:
        return np.ones(len(points), dtype=bool)
    m = recipe.sampling.margin if recipe.sampling.margin is not None else camera.robot_size / 2 / camera.scale
    arr = camera.scene.arrays
    d = np.hypot(points[:, None, 0] - arr["center"][None, :, 0], points[:, None, 1] - arr["center"][None, :, 1])
    return (d > arr["radius"][None] + m).all(axis=1)


def _uniform(rng: np.random.Generator, n: int, camera: Camera, recipe: Recipe) -> np.ndarray:
    lo, hi = _box(camera, recipe)
    out = rng.uniform(lo, hi, size=(n, 2))
    bad = np.flatnonzero(~_allowed(out, camera, recipe))
    for _ in range(_MAX_ROUNDS):
        if bad.size == 0:
            return out
        out[bad] = rng.uniform(lo, hi, size=(bad.size, 2))
        bad = bad[~_allowed(out[bad], camera, recipe)]
    raise ConfigError("data.sampling.exclude_obstacle", "the obstacle leaves (almost) no free space to sample")


def _grid(rng: np.random.Generator, n: int, camera: Camera, recipe: Recipe) -> np.ndarray:
    """A regular lattice with about `n` points over the sampling box, shifted by a random sub-cell offset
    per split (so splits do not share points); the first `n` lattice points of a random permutation."""
    lo, hi = _box(camera, recipe)
    span = hi - lo
    extra = 1.0
    for _ in range(_MAX_ROUNDS):
        cell = math.sqrt(span[0] * span[1] / (n * extra))
        nx, ny = max(1, math.ceil(span[0] / cell)), max(1, math.ceil(span[1] / cell))
        gx = lo[0] + (np.arange(nx) + rng.uniform()) * (span[0] / nx)
        gy = lo[1] + (np.arange(ny) + rng.uniform()) * (span[1] / ny)
        pts = np.stack(np.meshgrid(gx, gy, indexing="xy"), axis=-1).reshape(-1, 2)
        pts = pts[_allowed(pts, camera, recipe)]
        if len(pts) >= n:
            return pts[rng.permutation(len(pts))[:n]]
        extra *= 1.25
    raise ConfigError("data.sampling", "could not place a grid of that size")


def _followers(rng: np.random.Generator, leader: np.ndarray, camera: Camera, recipe: Recipe) -> np.ndarray:
    """Follower positions: uniform over the box (or within `max_distance` of the leader), at least
    `min_distance` from the leader so that the two squares do not overlap; then a share `near_share` of the
    rows moved within `near_distance` of the leader, the distance uniform (so squares that overlap, even
    exactly, are as common as near misses: every leader-follower run ends with the follower on its target,
    and a green fringe around the leader moved a map's estimate by 2 units). No extra draws at share 0."""
    lo, hi = _box(camera, recipe)
    n = len(leader)
    out = np.empty_like(leader)

    def draw(rows: np.ndarray) -> np.ndarray:
        if recipe.follower.max_distance is None:
            return rng.uniform(lo, hi, size=(rows.size, 2))
        r = np.sqrt(rng.uniform(recipe.follower.min_distance**2, recipe.follower.max_distance**2, rows.size))
        ang = rng.uniform(0, 2 * math.pi, rows.size)
        return leader[rows] + np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)

    def ok(rows: np.ndarray) -> np.ndarray:
        p = out[rows]
        inside = np.all((p >= lo) & (p <= hi), axis=1)
        far = np.hypot(*(p - leader[rows]).T) >= recipe.follower.min_distance
        return inside & far & _allowed(p, camera, recipe)

    bad = np.arange(n)
    for _ in range(_MAX_ROUNDS):
        if bad.size == 0:
            break
        out[bad] = draw(bad)
        bad = bad[~ok(bad)]
    out[bad] = np.clip(out[bad], lo, hi)  # a leader in a corner with a tight annulus: clip the few left
    return _near_followers(rng, out, leader, camera, recipe)


def _near_followers(rng: np.random.Generator, out: np.ndarray, leader: np.ndarray, camera: Camera,
                    recipe: Recipe) -> np.ndarray:
    if recipe.follower.near_share <= 0:
        return out
    lo, hi = _box(camera, recipe)
    rows = np.flatnonzero(rng.random(len(leader)) < recipe.follower.near_share)
    r = recipe.follower.near_distance * rng.uniform(0.0, 1.0, rows.size)  # uniform in distance: overlaps are common
    ang = rng.uniform(0, 2 * math.pi, rows.size)
    near = np.clip(leader[rows] + np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1), lo, hi)
    keep = _allowed(near, camera, recipe)  # off the obstacle when the recipe excludes it: the far draw stays
    out[rows[keep]] = near[keep]
    return out


def split_pool(recipe: Recipe, split: str, camera: Camera, occlusion: Occlusion, perception_map=None) -> Pool | None:
    """The pool a split draws its closed-loop share from (None outside closed-loop mode): the train split of a
    recipe with `closed_loop.map` draws from that map's visits (`perception_map`, loaded by the stage); every
    other split from the true-state visitation, so val and test do not depend on the map."""
    if recipe.mode != "closed_loop":
        return None
    if split == "train" and recipe.closed_loop.map is not None:
        if perception_map is None:
            raise ValueError(f"recipe {recipe.name}: closed_loop.map {recipe.closed_loop.map} is not loaded "
                             "(pass perception_map)")
        return cached_pool(recipe, camera, occlusion, perception_map)
    return cached_pool(recipe, camera)


def split_seed(recipe: Recipe, split: str) -> np.random.SeedSequence:
    """The split's random stream: `SeedSequence(seed).spawn(4)[i]`, `i` its place in `STREAMS` (train, val,
    test, gate); a train split that extends a parent
    dataset draws from `SeedSequence([seed, hash(parent)])` instead (never the parent's own draws)."""
    if split == "train" and recipe.parent is not None:
        key = int(hashlib.sha256(recipe.parent.encode()).hexdigest()[:16], 16)
        return np.random.SeedSequence([recipe.seed, key])
    if split not in STREAMS:
        raise ValueError(f"unknown split or stream {split!r}; known: {', '.join(STREAMS)}")
    # spawn(k)[:3] are the same children for every k >= 3: an extra stream changes no split
    return np.random.SeedSequence(recipe.seed).spawn(len(STREAMS))[STREAMS.index(split)]


def plan_split(recipe: Recipe, split: str, camera: Camera, occlusion: Occlusion, perception_map=None,
               n: int | None = None) -> SplitPlan:
    """The positions and cloud choices of one split's new draws (deterministic in recipe + seed, and the map's
    weights when the recipe has `closed_loop.map`; a parent's train positions are copied by the stage). `n`:
    how many (default: the split's size; required for a stream of `STREAMS` that is no split)."""
    if n is None:
        if split not in recipe.splits:
            raise ValueError(f"plan_split({split!r}) needs n: {split!r} is no split of the recipe")
        n = recipe.splits[split]
    rng = np.random.default_rng(split_seed(recipe, split))
    pool = split_pool(recipe, split, camera, occlusion, perception_map)
    if pool is not None:
        leader = _closed_loop_positions(rng, n, camera, recipe, pool)
    else:
        leader = (_uniform if recipe.mode == "uniform" else _grid)(rng, n, camera, recipe)
    present = rng.random(n) < recipe.follower.probability
    follower = _followers(rng, leader, camera, recipe)
    follower[~present] = np.nan
    clouds = occlusion.sample(n, rng, camera.shape)
    # headings last, uniform over the circle (a recipe without a heading draws nothing more: its bytes stay)
    heading = rng.uniform(-math.pi, math.pi, n).astype(np.float32) if recipe.headings else None
    return SplitPlan(leader.astype(np.float32), follower.astype(np.float32), clouds, heading)
