"""What a dataset recipe means: validated recipe, positions of leader and follower, per-image cloud choices.

Everything random is drawn here, per split, from `np.random.SeedSequence(seed).spawn(3)` (train, val,
test) in a fixed order (leader, follower presence, follower, clouds), before any rendering, so the bytes
depend on the recipe and seed only (not on the chunk size).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError
from pipeline.render import Camera, CloudSample, Occlusion

SPLITS = ("train", "val", "test")
VOLATILE = ("chunk_size",)  # recipe keys that do not change the bytes (left out of the id)
RECIPE_KEYS = ("name", "occlusion", "splits", "seed", "sampling", "follower", "preview", "chunk_size")
SAMPLING_MODES = ("uniform", "grid", "closed_loop")
CLOSED_LOOP_KEYS = ("share", "starts", "controller", "disturbance", "horizon", "dt", "camera_period", "jitter",
                    "stop_at_target", "seed")
_MAX_ROUNDS = 64  # rejection-sampling rounds (each vectorised over the rejected rows)


def _int(value, field: str, lo: int, hi: int | None = None) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer) or value < lo or (hi is not None and value > hi):
        rng = f">= {lo}" if hi is None else f"in [{lo}, {hi}]"
        raise ConfigError(field, f"must be an integer {rng}, got {value!r}")
    return int(value)


def _num(value, field: str, lo: float, hi: float = math.inf, *, allow_none: bool = False, open_lo: bool = False):
    if value is None and allow_none:
        return None
    ok = isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > lo if open_lo else value >= lo) and value <= hi
    if not ok:
        lo_s = f"> {lo:g}" if open_lo else f">= {lo:g}"
        rng = lo_s if hi == math.inf else f"{lo_s} and <= {hi:g}"
        raise ConfigError(field, f"must be a number {rng}{' (or null)' if allow_none else ''}, got {value!r}")
    return float(value)


@dataclass(frozen=True)
class Recipe:
    """A validated dataset recipe (the `data` config group)."""

    name: str
    occlusion: str
    splits: dict
    seed: int
    mode: str
    margin: float | None
    exclude_obstacle: bool
    follower_probability: float
    follower_min_distance: float
    follower_max_distance: float | None
    preview: int
    chunk_size: int
    closed_loop: dict | None = None

    @classmethod
    def from_config(cls, cfg: Mapping) -> Recipe:
        cfg = dict(cfg)
        unknown = set(cfg) - set(RECIPE_KEYS)
        if unknown:
            raise ConfigError("data", f"unknown key(s) {sorted(unknown)}; known: {list(RECIPE_KEYS)}")
        name = cfg.get("name")
        if not isinstance(name, str) or not name or "/" in name or name.startswith(".") or name != name.strip():
            raise ConfigError("data.name", f"must be a non-empty folder-safe name, got {name!r}")
        occ = cfg.get("occlusion", "none")
        if not isinstance(occ, str):
            raise ConfigError("data.occlusion", f"must name a level of conf/occlusion/, got {occ!r}")
        splits = cfg.get("splits")
        if not isinstance(splits, Mapping) or set(splits) != set(SPLITS):
            raise ConfigError("data.splits", f"needs exactly the sizes of {list(SPLITS)}, got {splits!r}")
        sizes = {s: _int(splits[s], f"data.splits.{s}", 1) for s in SPLITS}
        sampling = cfg.get("sampling") or {}
        extra = set(sampling) - {"mode", "margin", "exclude_obstacle", "closed_loop"}
        if extra:
            raise ConfigError("data.sampling", f"unknown key(s) {sorted(extra)}; known: mode, margin, exclude_obstacle, "
                                               "closed_loop")
        mode = sampling.get("mode", "uniform")
        if mode not in SAMPLING_MODES:
            raise ConfigError("data.sampling.mode", f"must be one of {SAMPLING_MODES}, got {mode!r}")
        closed_loop = _closed_loop(sampling.get("closed_loop")) if mode == "closed_loop" else None
        excl = sampling.get("exclude_obstacle", False)
        if not isinstance(excl, bool):
            raise ConfigError("data.sampling.exclude_obstacle", f"must be true or false, got {excl!r}")
        fol = cfg.get("follower") or {}
        extra = set(fol) - {"probability", "min_distance", "max_distance"}
        if extra:
            raise ConfigError("data.follower", f"unknown key(s) {sorted(extra)}; known: probability, min_distance, max_distance")
        min_d = _num(fol.get("min_distance", 5.0), "data.follower.min_distance", 0.0)
        max_d = _num(fol.get("max_distance"), "data.follower.max_distance", min_d, allow_none=True, open_lo=True)
        return cls(
            name=name,
            occlusion=occ,
            splits=sizes,
            seed=_int(cfg.get("seed", 0), "data.seed", 0, 2**63 - 1),
            mode=mode,
            margin=_num(sampling.get("margin"), "data.sampling.margin", 0.0, allow_none=True),
            exclude_obstacle=excl,
            follower_probability=_num(fol.get("probability", 0.5), "data.follower.probability", 0.0, 1.0),
            follower_min_distance=min_d,
            follower_max_distance=max_d,
            preview=_int(cfg.get("preview", 32), "data.preview", 1, 256),
            chunk_size=_int(cfg.get("chunk_size", 4096), "data.chunk_size", 1),
            closed_loop=closed_loop,
        )


def _closed_loop(cl) -> dict:
    """Validated `data.sampling.closed_loop`: where the simulated closed loop spends its time."""
    if not isinstance(cl, Mapping):
        raise ConfigError("data.sampling.closed_loop", "mode closed_loop needs this node (see conf/data/closed_loop.yaml)")
    cl = dict(cl)
    extra = set(cl) - set(CLOSED_LOOP_KEYS)
    if extra:
        raise ConfigError(f"data.sampling.closed_loop.{sorted(extra)[0]}", f"unknown key (known: {', '.join(CLOSED_LOOP_KEYS)})")
    f = "data.sampling.closed_loop"
    out = {"share": _num(cl.get("share", 0.5), f"{f}.share", 0.0, 1.0),
           "starts": _int(cl.get("starts", 200), f"{f}.starts", 1),
           "horizon": _num(cl.get("horizon", 30.0), f"{f}.horizon", 0.0, open_lo=True),
           "dt": _num(cl.get("dt", 0.01), f"{f}.dt", 0.0, open_lo=True),
           "camera_period": _num(cl.get("camera_period", 0.05), f"{f}.camera_period", 0.0, allow_none=True, open_lo=True),
           "jitter": _num(cl.get("jitter", 1.0), f"{f}.jitter", 0.0),
           "seed": _int(cl.get("seed", 0), f"{f}.seed", 0),
           "controller": cl.get("controller"), "disturbance": cl.get("disturbance")}
    stop = cl.get("stop_at_target", False)
    if not isinstance(stop, bool):
        raise ConfigError(f"{f}.stop_at_target", f"must be true or false, got {stop!r}")
    out["stop_at_target"] = stop
    for key in ("controller", "disturbance"):
        if not isinstance(out[key], Mapping) or "_target_" not in out[key]:
            raise ConfigError(f"{f}.{key}", "needs a composed node with `_target_` (conf/controller/, conf/disturbance/)")
    return out


def visitation_pool(recipe: Recipe, camera: Camera) -> np.ndarray:
    """Positions `(M, 2)` the configured closed loop visits, sampled at every step of every simulated run (so
    the pool's density is the time the loop spends at a place): random starts over the arena, the recipe's
    controller and disturbance, on the true state. Deterministic in `closed_loop.seed`."""
    from pipeline.sim import simulate
    from pipeline.sim.build import build_controller, build_disturbance, initial_conditions

    cl = recipe.closed_loop
    scene = camera.scene
    f = "data.sampling.closed_loop"
    ctrl = build_controller(cl["controller"], scene, path=f"{f}.controller")
    dist = build_disturbance(cl["disturbance"], f"{f}.disturbance")
    (x0, x1), (y0, y1) = camera.arena
    starts = initial_conditions({"mode": "random", "n": cl["starts"], "seed": cl["seed"], "margin": 2.0}, scene,
                                {"arena": {"x": [x0, x1], "y": [y0, y1]}})
    res = simulate(scene, ctrl, starts, dt=cl["dt"], horizon=cl["horizon"], camera_period=cl["camera_period"],
                   disturbance=dist, seed=cl["seed"], record_every=max(1, round((cl["camera_period"] or cl["dt"]) / cl["dt"])),
                   stop_on_success=cl["stop_at_target"])
    p = res.p.reshape(-1, 2)
    if cl["stop_at_target"]:  # drop the frozen rows after an agent stopped
        moving = np.ones(res.p.shape[:2], dtype=bool)
        moving[1:] = np.any(res.p[1:] != res.p[:-1], axis=-1)
        p = res.p[moving]
    return p[np.isfinite(p).all(axis=1)]


def _closed_loop_positions(rng: np.random.Generator, n: int, camera: Camera, recipe: Recipe, pool: np.ndarray):
    """`share` of `n` positions from the visitation pool (jittered, inside the box), the rest uniform, shuffled."""
    lo, hi = _box(camera, recipe)
    m = int(round(recipe.closed_loop["share"] * n))
    out = np.empty((n, 2))
    out[m:] = _uniform(rng, n - m, camera, recipe)
    jitter = recipe.closed_loop["jitter"]
    bad = np.arange(m)
    for _ in range(_MAX_ROUNDS):
        if bad.size == 0:
            break
        out[bad] = pool[rng.integers(0, len(pool), bad.size)] + rng.normal(0.0, jitter, (bad.size, 2))
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

    def __len__(self) -> int:
        return len(self.leader)


def _box(camera: Camera, recipe: Recipe) -> tuple[np.ndarray, np.ndarray]:
    """Sampling rectangle: the arena shrunk by the margin (default: half the robot's side)."""
    (x0, x1), (y0, y1) = camera.arena
    m = recipe.margin if recipe.margin is not None else camera.robot_size / 2 / camera.scale
    lo, hi = np.array([x0 + m, y0 + m]), np.array([x1 - m, y1 - m])
    if np.any(hi <= lo):
        raise ConfigError("data.sampling.margin", f"{m:g} leaves no room in the arena {camera.arena}")
    return lo, hi


def _allowed(points: np.ndarray, camera: Camera, recipe: Recipe) -> np.ndarray:
    if not recipe.exclude_obstacle or camera.scene is None:
        return np.ones(len(points), dtype=bool)
    m = recipe.margin if recipe.margin is not None else camera.robot_size / 2 / camera.scale
    d = np.hypot(*(points - np.asarray(camera.scene.obstacle_center)).T)
    return d > camera.scene.obstacle_radius + m


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
    `min_distance` from the leader so that the two squares do not overlap."""
    lo, hi = _box(camera, recipe)
    n = len(leader)
    out = np.empty_like(leader)

    def draw(rows: np.ndarray) -> np.ndarray:
        if recipe.follower_max_distance is None:
            return rng.uniform(lo, hi, size=(rows.size, 2))
        r = np.sqrt(rng.uniform(recipe.follower_min_distance**2, recipe.follower_max_distance**2, rows.size))
        ang = rng.uniform(0, 2 * math.pi, rows.size)
        return leader[rows] + np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)

    def ok(rows: np.ndarray) -> np.ndarray:
        p = out[rows]
        inside = np.all((p >= lo) & (p <= hi), axis=1)
        far = np.hypot(*(p - leader[rows]).T) >= recipe.follower_min_distance
        return inside & far & _allowed(p, camera, recipe)

    bad = np.arange(n)
    for _ in range(_MAX_ROUNDS):
        if bad.size == 0:
            return out
        out[bad] = draw(bad)
        bad = bad[~ok(bad)]
    out[bad] = np.clip(out[bad], lo, hi)  # a leader in a corner with a tight annulus: clip the few left
    return out


_POOLS: dict = {}


def _pool(recipe: Recipe, camera: Camera) -> np.ndarray:
    """The visitation pool, simulated once per (recipe, camera) in a process (the three splits share it)."""
    import json

    sc = camera.scene
    key = (json.dumps(recipe.closed_loop, sort_keys=True, default=str), repr(camera.arena), repr(sc))
    if key not in _POOLS:
        _POOLS.clear()
        _POOLS[key] = visitation_pool(recipe, camera)
    return _POOLS[key]


def plan_split(recipe: Recipe, split: str, camera: Camera, occlusion: Occlusion) -> SplitPlan:
    """The positions and cloud choices of one split (deterministic in recipe + seed)."""
    n = recipe.splits[split]
    seq = np.random.SeedSequence(recipe.seed).spawn(len(SPLITS))[SPLITS.index(split)]
    rng = np.random.default_rng(seq)
    if recipe.mode == "closed_loop":
        leader = _closed_loop_positions(rng, n, camera, recipe, _pool(recipe, camera))
    else:
        leader = (_uniform if recipe.mode == "uniform" else _grid)(rng, n, camera, recipe)
    present = rng.random(n) < recipe.follower_probability
    follower = _followers(rng, leader, camera, recipe)
    follower[~present] = np.nan
    clouds = occlusion.sample(n, rng, camera.shape)
    return SplitPlan(leader.astype(np.float32), follower.astype(np.float32), clouds)
