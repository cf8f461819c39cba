"""Config -> objects for the simulator (shared by `pipeline.simulate` and the experiments stage).

Takes plain mappings (Hydra DictConfig or dict); no Hydra run context needed.
"""

from __future__ import annotations

import numpy as np
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from pipeline.control import Scene, in_diamond
from pipeline.control.controllers import Controller
from pipeline.errors import ConfigError, PipelineError
from pipeline.sim.disturbances import Disturbance


def _as_cfg(cfg) -> DictConfig:
    return cfg if isinstance(cfg, DictConfig) else OmegaConf.create(cfg)


def _instantiate(cfg, group: str, **kwargs):
    cfg = _as_cfg(cfg)
    if "_target_" not in cfg:
        raise ConfigError(group, "needs a `_target_` (pick one of the conf/" + group + "/ options)")
    clean = OmegaConf.masked_copy(cfg, [k for k in cfg.keys() if k != "name"]) if "name" in cfg else cfg
    try:
        # partial first: Hydra would turn a dataclass kwarg (the Scene) into a config node
        return instantiate(clean, _partial_=True)(**kwargs)
    except PipelineError:
        raise
    except TypeError as err:
        raise ConfigError(group, f"invalid parameters for {cfg['_target_']}: {err}") from None
    except InstantiationException as err:
        cause = err.__cause__
        while cause is not None and not isinstance(cause, PipelineError):
            cause = cause.__cause__
        if cause is not None:
            raise cause from None
        raise ConfigError(group, str(err).splitlines()[0]) from None


def build_scene(cfg) -> Scene:
    """`Scene` from the `scene` group."""
    return Scene.from_config(_as_cfg(cfg))


def build_controller(cfg, scene: Scene) -> Controller:
    """Controller from the `controller` group (`_target_` + parameters)."""
    ctrl = _instantiate(cfg, "controller", scene=scene)
    if "name" in cfg:
        ctrl.name = str(cfg["name"])
    return ctrl


def build_disturbance(cfg) -> Disturbance:
    """Disturbance from the `disturbance` group."""
    return _instantiate(cfg, "disturbance")


def arena_bounds(scene_cfg) -> tuple[tuple[float, float], tuple[float, float]]:
    arena = _as_cfg(scene_cfg).get("arena") or {"x": [-50.0, 50.0], "y": [-30.0, 30.0]}
    (x0, x1), (y0, y1) = arena["x"], arena["y"]
    if not (x0 < x1 and y0 < y1):
        raise ConfigError("scene.arena", f"needs x = [xmin, xmax], y = [ymin, ymax] with min < max, got {arena}")
    return (float(x0), float(x1)), (float(y0), float(y1))


def initial_conditions(cfg, scene: Scene, scene_cfg=None) -> np.ndarray:
    """Initial positions `(N, 2)` from the `init` group: `points`, `grid`, `random` or `near_k`."""
    cfg = _as_cfg(cfg)
    mode = cfg.get("mode", "points")
    (x0, x1), (y0, y1) = arena_bounds(scene_cfg or {})
    margin = float(cfg.get("margin", 0.0))
    if mode == "points":
        raw = OmegaConf.to_container(cfg.points) if OmegaConf.is_config(cfg.points) else cfg.points
        try:
            pts = np.asarray(raw, dtype=float)
        except (TypeError, ValueError):
            pts = np.zeros((0,))
        if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0 or not np.isfinite(pts).all():
            raise ConfigError("init.points", f"must be a non-empty list of [x, y] pairs, got {raw}")
    elif mode == "grid":
        nx, ny = int(cfg.nx), int(cfg.ny)
        if nx < 1 or ny < 1:
            raise ConfigError("init.nx", f"grid sizes must be >= 1, got nx={nx}, ny={ny}")
        gx = np.linspace(x0 + margin, x1 - margin, nx)
        gy = np.linspace(y0 + margin, y1 - margin, ny)
        pts = np.stack(np.meshgrid(gx, gy), axis=-1).reshape(-1, 2)
    elif mode == "random":
        n = int(cfg.n)
        if n < 1:
            raise ConfigError("init.n", f"must be >= 1, got {n}")
        rng = np.random.default_rng(int(cfg.get("seed", 0)))
        pts = rng.uniform([x0 + margin, y0 + margin], [x1 - margin, y1 - margin], size=(4 * n + 16, 2))
    elif mode == "near_k":
        n = int(cfg.n)
        if n < 1:
            raise ConfigError("init.n", f"must be >= 1, got {n}")
        rng = np.random.default_rng(int(cfg.get("seed", 0)))
        lo, hi = cfg.get("a_range", [-45.0, -15.0])
        band = float(cfg.get("band", 0.5))
        if not band > 0:
            raise ConfigError("init.band", f"must be > 0, got {band}")
        a = rng.uniform(lo, hi, n)
        b = rng.uniform(-band, band, n)
        return scene.from_frame(a, b)
    else:
        raise ConfigError("init.mode", f"must be one of points, grid, random, near_k; got {mode!r}")
    if mode != "points" and cfg.get("exclude_diamond", True):
        keep = ~in_diamond(scene, pts)
        rel = pts - scene.p_0
        keep &= np.hypot(rel[:, 0], rel[:, 1]) > scene.obstacle_radius
        pts = pts[keep]
    if mode == "random":
        pts = pts[: int(cfg.n)]
    if len(pts) == 0:
        raise ConfigError("init", "no initial condition left after excluding the diamond")
    return pts
