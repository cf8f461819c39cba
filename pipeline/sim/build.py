"""Config -> objects for the simulator (shared by `pipeline.simulate` and the experiments stage).

Every object is built from its config node with `hydra.utils.instantiate` (:func:`pipeline.config.build`);
plain settings nodes (`init`, `camera`) are checked against their schema (:mod:`pipeline.schema`).
"""

from __future__ import annotations

import numpy as np
from omegaconf import DictConfig, OmegaConf

from pipeline.config import build
from pipeline.control import Scene, in_diamond
from pipeline.control.controllers import Controller
from pipeline.errors import ConfigError
from pipeline.schema import load_init
from pipeline.sim.disturbances import Disturbance


def scene(*, target, obstacle, name: str = "custom", apex=None, barrier=None, arena=None) -> Scene:
    """`_target_` of conf/scene/*.yaml: `Scene.from_config` (the one parser of a scene node) plus the check
    that the target and the obstacle lie inside the arena."""
    sc = Scene.from_config({"target": target, "obstacle": obstacle, "name": str(name), "apex": apex,
                            "barrier": barrier})
    if arena is not None:
        (x0, x1), (y0, y1) = arena_bounds({"arena": arena})
        for field, (x, y) in (("scene.target", sc.p_T), ("scene.obstacle.center", sc.p_0)):
            if not (x0 <= x <= x1 and y0 <= y <= y1):
                raise ConfigError(field, f"({x:g}, {y:g}) lies outside the arena x in [{x0:g}, {x1:g}], "
                                         f"y in [{y0:g}, {y1:g}]")
    return sc


def _as_cfg(cfg) -> DictConfig:
    return cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)


def build_scene(cfg, path: str = "scene") -> Scene:
    """`Scene` from a `scene` node (instantiated; a node without `_target_`, e.g. from a manifest, too)."""
    cfg = _as_cfg(cfg)
    if "_target_" not in cfg:
        cfg = OmegaConf.merge({"_target_": "pipeline.sim.build.scene"}, cfg)
    return build(cfg, path)


def build_controller(cfg, scene: Scene, path: str = "controller") -> Controller:
    """Controller from a `controller` node (`_target_` + parameters); `name` labels it."""
    cfg = _as_cfg(cfg)
    ctrl = build(cfg, path, scene=scene)
    if "name" in cfg:
        ctrl.name = str(cfg["name"])
    return ctrl


def build_disturbance(cfg, path: str = "disturbance", **params) -> Disturbance:
    """Disturbance from a `disturbance` node; `params` set the parameters a scenario sweeps (eps, sigma)."""
    return build(_as_cfg(cfg), path, **params)


def sim_model_kwargs(sim_cfg) -> dict:
    """`simulate` keywords of the time model and the outcome classes from the `sim` group (defaults if absent)."""
    keys = ("model", "method", "rtol", "atol", "h_max", "stall_speed", "stall_time")
    return {k: sim_cfg[k] for k in keys if k in sim_cfg}


def arena_bounds(scene_cfg) -> tuple[tuple[float, float], tuple[float, float]]:
    arena = _as_cfg(scene_cfg).get("arena") or {"x": [-50.0, 50.0], "y": [-30.0, 30.0]}
    try:
        (x0, x1), (y0, y1) = arena["x"], arena["y"]
        x0, x1, y0, y1 = (float(v) for v in (x0, x1, y0, y1))
    except (TypeError, ValueError, KeyError):
        raise ConfigError("scene.arena", f"needs x: [xmin, xmax], y: [ymin, ymax] (numbers), got {arena}") from None
    if not (x0 < x1 and y0 < y1):
        raise ConfigError("scene.arena", f"needs x = [xmin, xmax], y = [ymin, ymax] with min < max, got {arena}")
    return (x0, x1), (y0, y1)


def initial_conditions(cfg, scene: Scene, scene_cfg=None, path: str = "init") -> np.ndarray:
    """Initial positions `(N, 2)` from the `init` group: `points`, `grid`, `random` or `near_k`."""
    init = load_init(cfg, path)
    (x0, x1), (y0, y1) = arena_bounds(scene_cfg or {})
    rel = lambda pts: np.hypot(*(pts - scene.p_0).T)  # noqa: E731
    if init.mode == "points":
        pts = np.asarray(init.points, dtype=float)
        inside = rel(pts) < scene.obstacle_radius
        if inside.any():
            i = int(np.flatnonzero(inside)[0])
            raise ConfigError(f"{path}.points", f"start {pts[i].tolist()} lies inside the obstacle "
                                                f"(centre {scene.p_0.tolist()}, radius {scene.obstacle_radius:g})")
        return pts
    if init.mode == "near_k":
        rng = np.random.default_rng(init.seed)
        a = rng.uniform(*init.a_range, init.n)
        b = rng.uniform(-init.band, init.band, init.n)
        return scene.from_frame(a, b)
    margin = init.margin
    if not (x0 + margin < x1 - margin and y0 + margin < y1 - margin):
        raise ConfigError(f"{path}.margin", f"{margin:g} leaves no room in the arena")
    if init.mode == "grid":
        gx = np.linspace(x0 + margin, x1 - margin, init.nx)
        gy = np.linspace(y0 + margin, y1 - margin, init.ny)
        pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    else:
        rng = np.random.default_rng(init.seed)
        pts = rng.uniform([x0 + margin, y0 + margin], [x1 - margin, y1 - margin], size=(4 * init.n + 16, 2))
    if init.exclude_diamond:
        pts = pts[~in_diamond(scene, pts) & (rel(pts) > scene.obstacle_radius)]
    if init.mode == "random":
        pts = pts[: init.n]
    if len(pts) == 0:
        raise ConfigError(path, "no initial condition left after excluding the diamond")
    return pts
