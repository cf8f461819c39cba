"""Closed-loop-aware sampling (`data.sampling.mode: closed_loop`): where a simulated closed loop spends its time.

- :func:`visitation_pool`: the positions the configured controller + disturbance visit on the **true state**;
- :func:`map_visitation_pool`: the same loop with the camera and a **perception map** in it (`CameraMeasure`,
  the recipe's clouds drawn on every frame): each position in the camera's view where a frame was taken, with
  the map's error there (the DAgger recipe's collection, docs/dagger.md);
- :class:`Pool`: the candidates and, for a map's visits, the draw probabilities `max(err - min_error, 0) +
  error_floor` (normalised) when `error_weighted`.

The recipe's keys are validated in :mod:`pipeline.data.sampling`, which draws the positions.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass

import numpy as np

from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.perception.measure import CameraMeasure
from pipeline.plants import Plant, SingleIntegrator
from pipeline.sim import CameraSettings, SimSettings, simulate
from pipeline.sim.starts import Random

_F = "data.sampling.closed_loop"


@dataclass(frozen=True)
class Pool:
    """Candidate positions `(M, 2)` of a simulated closed loop; `errors` `(M,)`: the perception map's error
    (world units, Euclidean) on the frame taken at each position (None: the true-state loop)."""

    positions: np.ndarray
    errors: np.ndarray | None = None
    frames: int | None = None  # a map's loop: frames taken, including those outside the camera's view

    def __len__(self) -> int:
        return len(self.positions)

    def probabilities(self, cl) -> np.ndarray | None:
        """Draw probabilities: None (uniform over the entries) unless `error_weighted`."""
        if self.errors is None or not cl.error_weighted:
            return None
        w = np.maximum(self.errors - cl.min_error, 0.0) + cl.error_floor
        return w / w.sum()

    def summary(self, cl) -> dict:
        """What the manifest records about a map's visits: count and error statistics (world units)."""
        out = {"positions": len(self)}
        if self.frames is not None:
            out["frames"] = self.frames
            out["outside_view_share"] = 1.0 - len(self) / max(self.frames, 1)
        if self.errors is not None and len(self):
            e = self.errors
            out["map_error"] = {"mean": float(e.mean()), "p95": float(np.percentile(e, 95)), "max": float(e.max()),
                                "share_above_min_error": float((e > cl.min_error).mean())}
        return out


def vehicle(recipe) -> Plant:
    """The recipe's vehicle (`data.vehicle`, a plant node; none: the single integrator)."""
    return build(recipe.vehicle, "data.vehicle") if recipe.vehicle is not None else SingleIntegrator()


def _simulate(recipe, camera, measure=None):
    """The recipe's closed loop from `starts` random starts (controller, disturbance, timing, seed), with the
    recipe's vehicle (a unicycle: its look-ahead point steered around the inflated discs, SPEC §3.7)."""
    cl = recipe.closed_loop
    scene = camera.scene
    plant = vehicle(recipe)
    ctrl = build(cl.controller, f"{_F}.controller", scene=plant.steering_scene(scene))
    dist = build(cl.disturbance, f"{_F}.disturbance")
    starts = Random(n=cl.starts, seed=cl.seed, margin=2.0)(scene, _F)
    every = max(1, round((cl.camera_period or cl.dt) / cl.dt))
    return simulate(scene, ctrl, starts,
                    sim=SimSettings(dt=cl.dt, horizon=cl.horizon, record_every=every, stop_on_success=cl.stop_at_target),
                    camera=CameraSettings(period=cl.camera_period), disturbance=dist, seed=cl.seed,
                    record=measure is None, measure=measure, plant=plant, heading0=plant.initial_heading(starts, scene))


def visitation_pool(recipe, camera) -> np.ndarray:
    """Positions `(M, 2)` the configured closed loop visits, sampled at every step of every simulated run (so
    the pool's density is the time the loop spends at a place): random starts over the arena, the recipe's
    controller and disturbance, on the true state. Deterministic in `closed_loop.seed`."""
    res = _simulate(recipe, camera)
    p = res.p.reshape(-1, 2)
    if recipe.closed_loop.stop_at_target:  # drop the frozen rows after an agent stopped
        moving = np.ones(res.p.shape[:2], dtype=bool)
        moving[1:] = np.any(res.p[1:] != res.p[:-1], axis=-1)
        p = res.p[moving]
    return p[np.isfinite(p).all(axis=1)]


class _FrameLog:
    """A measurement hook that records every frame's true positions and the map's error on them."""

    def __init__(self, measure):
        self.measure, self.p, self.err = measure, [], []

    def __call__(self, p, idx, frame, rng):
        est = self.measure(p, idx, frame, rng)
        self.p.append(np.array(p[:, :2], dtype=float))
        self.err.append(np.hypot(*(np.asarray(est, dtype=float)[:, :2] - p[:, :2]).T))  # position error
        return est


def map_visitation_pool(recipe, camera, perception_map, occlusion) -> Pool:
    """The recipe's closed loop with the camera and `perception_map` in it (`CameraMeasure`: every agent's
    frame rendered with `occlusion`'s clouds, one batched inference per frame; the disturbance on top): every
    position where a frame was taken inside the camera's view (a vehicle the map drove out of the arena is on
    no image), with the map's error there. Deterministic in `closed_loop.seed` (and the map's weights)."""
    log = _FrameLog(CameraMeasure(camera, perception_map, occlusion))
    _simulate(recipe, camera, measure=log)
    p, err = np.concatenate(log.p), np.concatenate(log.err)
    (x0, x1), (y0, y1) = camera.arena
    with np.errstate(invalid="ignore"):
        keep = (p[:, 0] >= x0) & (p[:, 0] <= x1) & (p[:, 1] >= y0) & (p[:, 1] <= y1) & np.isfinite(err)
    return Pool(p[keep], err[keep], frames=len(p))


_POOLS: dict = {}


def pool(recipe, camera, occlusion=None, perception_map=None) -> Pool:
    """A split's pool, simulated once per (recipe, camera, clouds, map) in a process (the splits share it):
    the map's visits when `perception_map` is given, else the true-state visitation."""
    key = (json.dumps(dataclasses.asdict(recipe.closed_loop), sort_keys=True, default=str),
           json.dumps(recipe.vehicle, sort_keys=True, default=str), repr(camera.arena), repr(camera.scene),
           json.dumps(occlusion.config() if occlusion is not None and perception_map is not None else None,
                      sort_keys=True, default=str), perception_map is not None)
    if key not in _POOLS:
        if len(_POOLS) >= 2:  # a dataset needs at most two: its map's visits (train) and the true-state loop
            _POOLS.clear()
        _POOLS[key] = (map_visitation_pool(recipe, camera, perception_map, occlusion) if perception_map is not None
                       else Pool(visitation_pool(recipe, camera)))
    if not len(_POOLS[key]):
        raise ConfigError(_F, "the simulated closed loop has no frame in the camera's view")
    return _POOLS[key]
