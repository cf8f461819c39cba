"""Gymnasium environments over the project's scene, plants, camera and clouds (SPEC §6; docs/learned.md).

- :class:`NavigateEnv`: one agent (`gymnasium.Env`); :class:`NavigateVectorEnv`: N agents stepped in one call of
  the batched plant and renderer (`gymnasium.vector.VectorEnv`, same-step autoreset: the final frame and true
  state of an agent that stopped are in `info["final_obs"]`, `info["final_state"]`). Both run
  :class:`~pipeline.envs.core.NavigationCore`, so one agent of either is the same loop. The action is
  normalised, `Box(-1, 1, (2,))`: the core scales it by `EnvObjects.scale` (`u_max`, the unicycle's
  `(u_max, ω_max)`) into the velocity.
- :func:`objects` builds everything from the composed config `env` (conf/env.yaml) with `hydra.utils.instantiate`
  through :func:`pipeline.config.build`; a bad override is one :class:`~pipeline.errors.ConfigError` line.
"""

from __future__ import annotations

from dataclasses import dataclass

import gymnasium as gym
import numpy as np
from gymnasium import spaces
from gymnasium.vector import AutoresetMode, VectorEnv
from omegaconf import DictConfig

from pipeline.config import build, compose
from pipeline.envs.core import ENDED, OUTCOMES, RUNNING, TIMED_OUT, EnvSettings, NavigationCore, action_scale
from pipeline.errors import ConfigError
from pipeline.sim.composed import loop_parts
from pipeline.sim.metrics import Outcome
from pipeline.sim.settings import frame_steps


@dataclass
class EnvObjects:
    """What an environment is made of, built from one composed config."""

    cfg: DictConfig
    scene: object
    plant: object
    camera: object
    controller: object
    occlusion: object
    sim: object
    camera_settings: object
    init: object
    settings: EnvSettings

    @property
    def scale(self) -> np.ndarray:
        """The velocity of the unit action per component (:func:`pipeline.envs.core.action_scale`)."""
        return action_scale(self.plant, self.controller.u_max)

    def core(self, n: int) -> NavigationCore:
        every = frame_steps(self.sim.dt, self.camera_settings.period)
        frames = -(-self.sim.n_steps // every)
        return NavigationCore(n, scene=self.scene, plant=self.plant, camera=self.camera, scale=self.scale,
                              dt=self.sim.dt, every=every, frames=frames, delta=self.sim.delta,
                              occlusion=self.occlusion, p_fail=self.camera_settings.p_fail, settings=self.settings)

    def starts(self, n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray | None]:
        """`n` starts of the `init` distribution drawn from `rng` (and the vehicle's initial headings)."""
        node = dict(self.cfg.init)
        node.update(n=int(n)) if "n" in node else None
        if "seed" in node:
            node["seed"] = int(rng.integers(2**31 - 1))
        p = build(node, "init")(self.scene)
        if len(p) < n:  # a fixed list of points: cycle through it
            p = p[np.arange(n) % len(p)]
        p = p[:n]
        heading = None
        if self.plant.heading:
            heading = rng.uniform(-np.pi, np.pi, n) if self.plant.heading0 == "random" else \
                self.plant.initial_heading(p, self.scene)
        return p, heading


def compose_env(overrides=None) -> DictConfig:
    """conf/env.yaml with `overrides`; a composition error is one ConfigError line."""
    return compose("env", list(overrides or []))


def objects(overrides=None) -> EnvObjects:
    """The objects of conf/env.yaml composed with `overrides`."""
    return objects_from(compose_env(overrides))


def objects_from(cfg: DictConfig) -> EnvObjects:
    """The objects of a composed config holding the env's nodes (conf/env.yaml's, or a stage's that includes them)."""
    parts = loop_parts(cfg)
    scene, plant, sim, cam = parts.scene, parts.plant, parts.sim, parts.camera
    controller = parts.law(cfg.controller)
    action_scale(plant, controller.u_max)  # the action's unit: a finite u_max (one ConfigError line, preflight)
    return EnvObjects(cfg=cfg, scene=scene, plant=plant, camera=build(cfg.render, "render", scene=scene),
                      controller=controller, occlusion=build(cfg.occlusion, "occlusion"), sim=sim,
                      camera_settings=cam, init=build(cfg.init, "init"), settings=build(cfg.env, "env"))


def _spaces(obj: EnvObjects, core: NavigationCore):
    """The frame (or the unicycle's Dict of it and its heading), and the normalised action `Box(-1, 1, (2,))`:
    the velocity (or `(v, ω)`) is the action times `core.scale` (issue 46: SB3's recommended space)."""
    h, w = obj.camera.shape
    image = spaces.Box(0, 255, (h, w, 3), dtype=np.uint8)
    obs = image
    if obj.plant.heading and obj.settings.observe_heading:
        obs = spaces.Dict({"image": image, "heading": spaces.Box(-1.0, 1.0, (2,), dtype=np.float32)})
    return obs, spaces.Box(-1.0, 1.0, (core.plant.inputs,), dtype=np.float32)


def _observe(obj: EnvObjects, core: NavigationCore, idx=None):
    idx = slice(None) if idx is None else idx
    images = core.images[idx]
    if obj.plant.heading and obj.settings.observe_heading:
        th = core.c[idx, 2]
        return {"image": images.copy(), "heading": np.stack([np.cos(th), np.sin(th)], -1).astype(np.float32)}
    return images.copy()


def _start(obj: EnvObjects, n: int, rng, options: dict | None):
    """Starts from `options` (`start` (n, 2) or (2,), `heading`) or drawn from `init`."""
    options = options or {}
    if "start" in options:
        p = np.asarray(options["start"], dtype=float).reshape(-1, 2)
        p = p[np.arange(n) % len(p)]
        heading = options.get("heading")
        if obj.plant.heading:
            heading = (np.full(n, float(heading)) if np.ndim(heading) == 0 and heading is not None else
                       obj.plant.initial_heading(p, obj.scene) if heading is None else np.asarray(heading, float))
        return obj.plant.lift(p, heading)
    p, heading = obj.starts(n, rng)
    return obj.plant.lift(p, heading)


class NavigateEnv(gym.Env):
    """One vehicle, one camera frame per step (see the module docstring and docs/learned.md)."""

    metadata = {"render_modes": ["rgb_array"], "render_fps": 20}

    def __init__(self, overrides=None, render_mode: str | None = None, objects_: EnvObjects | None = None):
        if render_mode not in (None, "rgb_array"):
            raise ConfigError("render_mode", f"must be rgb_array or None, got {render_mode!r}")
        self.objects = objects_ or objects(overrides)
        self.core = self.objects.core(1)
        self.observation_space, self.action_space = _spaces(self.objects, self.core)
        self.render_mode = render_mode
        self.metadata = {**self.metadata, "render_fps": round(1.0 / self.core.period)}

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.core.reset(np.arange(1), _start(self.objects, 1, self.np_random, options), self.np_random)
        return _observe(self.objects, self.core, 0), self._info(RUNNING)

    def step(self, action):
        reward, code = self.core.step(np.asarray(action).reshape(1, -1), self.np_random)
        c = int(code[0])
        return (_observe(self.objects, self.core, 0), float(reward[0]), c in ENDED, c == TIMED_OUT, self._info(c))

    def _info(self, code: int) -> dict:
        info = {k: v[0] for k, v in self.core.info().items()}
        info["outcome"] = OUTCOMES[code]
        info["is_success"] = code == Outcome.REACHED
        return info

    def render(self):
        return self.core.images[0].copy() if self.render_mode == "rgb_array" else None


class NavigateVectorEnv(VectorEnv):
    """`num_envs` vehicles stepped in one call of the batched plant and renderer (same-step autoreset)."""

    metadata = {"render_modes": ["rgb_array"], "autoreset_mode": AutoresetMode.SAME_STEP}

    def __init__(self, num_envs: int, overrides=None, render_mode: str | None = None,
                 objects_: EnvObjects | None = None, autoreset: bool = True):
        if int(num_envs) < 1:
            raise ConfigError("num_envs", f"must be a positive integer, got {num_envs!r}")
        self.objects = objects_ or objects(overrides)
        self.num_envs = int(num_envs)
        self.core = self.objects.core(self.num_envs)
        self.single_observation_space, self.single_action_space = _spaces(self.objects, self.core)
        self.observation_space = gym.vector.utils.batch_space(self.single_observation_space, self.num_envs)
        self.action_space = gym.vector.utils.batch_space(self.single_action_space, self.num_envs)
        self.render_mode, self.autoreset = render_mode, autoreset
        self.done = np.zeros(self.num_envs, dtype=bool)

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        super().reset(seed=seed)
        self.done[:] = False
        self.core.reset(np.arange(self.num_envs), _start(self.objects, self.num_envs, self.np_random, options),
                        self.np_random)
        return _observe(self.objects, self.core), {**self.core.info(),
                                                   "outcome": np.zeros(self.num_envs, dtype=np.int8)}

    def step(self, actions):
        actions = np.array(actions, dtype=float).reshape(self.num_envs, -1)
        actions[self.done] = 0.0  # agents stopped without autoreset stay where they stopped
        reward, code = self.core.step(actions, self.np_random)
        code[self.done] = 0
        reward[self.done] = 0.0
        term, trunc = np.isin(code, ENDED), code == TIMED_OUT
        info = {**self.core.info(), "outcome": code}
        ended = term | trunc
        if ended.any():
            info["final_obs"], info["_final_obs"] = _observe(self.objects, self.core), ended
            info["final_state"] = info["state"].copy()
            if self.autoreset:
                idx = np.flatnonzero(ended)
                self.core.reset(idx, _start(self.objects, len(idx), self.np_random, None), self.np_random)
                info.update(self.core.info())
            else:
                self.done |= ended
        return _observe(self.objects, self.core), reward, term, trunc, info

    def render(self):
        return self.core.images.copy() if self.render_mode == "rgb_array" else None
