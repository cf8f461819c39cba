"""Policies over the environments' observations (SPEC §6), so one evaluation code runs every agent.

A policy is batched: `reset(obs)` at the first frame of the agents that (re)start, `act(obs) -> actions` at every
frame: `(N, 2)` actions of the environment's normalised action space (issue 46: the velocity `u`, or `(v, ω)`
for the unicycle, divided by the env's `scale`, :func:`pipeline.envs.core.action_scale`; the env multiplies it
back). Observations are the frames `(N, H, W, 3)`.

- :class:`ArchitecturePolicy`: the paper's architecture: the perception map's estimate `m = l(θ)` fed to a
  feedback law of :mod:`pipeline.control` (hybrid, smooth, CBF) through the sampled loop of the simulator
  (:class:`pipeline.sim.closed_loop.SampledLoop` and the solver's own frame update: sample, jump where
  `x ∈ D`, hold the input through the sampled-data guard). It carries the law's logic state (mode `q`,
  active obstacle `i`) per agent; with the same map, camera and starts its trajectories are the simulator's.
  :meth:`ArchitecturePolicy.velocity` is the law's held input, `act` that input as the env's action.
- :class:`RandomPolicy`: uniform actions of the action space (a seeded baseline).
"""

from __future__ import annotations

import numpy as np

from pipeline.envs.core import action_scale, to_action
from pipeline.hybrid.sampled import frame_update
from pipeline.sim.closed_loop import SampledLoop


def frames(obs):
    """The camera frames of an observation (the image of a `Dict` observation)."""
    return obs["image"] if isinstance(obs, dict) else obs


class ArchitecturePolicy:
    """Perception map + feedback law (see the module docstring). `predict(images) -> (N, 2 | 3)` estimates.

    `scale`: the environment's (`env.core.scale`: its action is `velocity / scale`); None: the law's own limits
    (:func:`pipeline.envs.core.action_scale` of `controller.u_max`), the env's when the law is its controller."""

    def __init__(self, perception_map, controller, plant, scene, period: float, name: str | None = None,
                 scale=None):
        self.map, self.controller, self.plant = perception_map, controller, plant
        self.scale = action_scale(plant, controller.u_max) if scale is None else np.asarray(scale, dtype=float)
        self.name = name or f"{controller.name}+map"
        self._est = None
        self.loop = SampledLoop(scene, controller, plant, None, measure=self._measure, dt=period, every=1)
        self.x = None
        self._rng = np.random.default_rng(0)  # unused by the loop (no failures, no disturbance)

    def _measure(self, c, idx, frame, rng):
        return self._est[idx]

    def estimate(self, obs) -> np.ndarray:
        est = np.asarray(self.map.predict(frames(obs)), dtype=float)
        if self.plant.heading and est.shape[1] == 2:
            raise ValueError("a unicycle's architecture policy needs a pose map (x, y, θ)")
        return est[:, : self.plant.dim]

    def reset(self, obs, idx=None) -> None:
        """The law's initial logic state (SPEC §3.3: the mode with the smaller `V_q`) at the agents `idx`' first
        frame (all agents when None)."""
        est = self.estimate(obs)
        self._est = est
        x0 = self.loop.initial(np.zeros((len(est), self.plant.dim)), self._rng)
        if self.x is None or idx is None:
            self.x = x0
        else:
            self.x.put(np.asarray(idx), x0)

    def act(self, obs, restarted: np.ndarray | None = None) -> np.ndarray:
        """The env's action of every agent at this frame: :meth:`velocity` over `scale`."""
        return to_action(self.velocity(obs, restarted), self.scale)

    def velocity(self, obs, restarted: np.ndarray | None = None) -> np.ndarray:
        """The held input of every agent at this frame (world units); `restarted` rows start afresh (an autoreset)."""
        if self.x is None:
            self.reset(obs)
            restarted = None
        est = self.estimate(obs)
        if restarted is not None and np.any(restarted):
            idx = np.flatnonzero(restarted)
            self._est = est[idx]
            self.x.put(idx, self.loop.initial(np.zeros((len(idx), self.plant.dim)), self._rng))
        self._est = est
        x, w, *_ = frame_update(self.loop, self.x, 1, self._rng, np.ones(len(est), dtype=bool))
        self.x = x
        return w

    @property
    def mode(self) -> np.ndarray:
        """The law's mode `q` per agent (1 for a law without modes)."""
        return np.asarray(self.x.d.get("q", np.ones(len(self.x))))


class RandomPolicy:
    """Uniform actions of `action_space` (a single agent's Box: the normalised actions), seeded."""

    name = "random"

    def __init__(self, action_space, seed: int = 0):
        self.low, self.high = action_space.low.astype(float), action_space.high.astype(float)
        self.rng = np.random.default_rng(seed)

    def reset(self, obs, idx=None) -> None:
        pass

    def act(self, obs, restarted=None) -> np.ndarray:
        n = len(frames(obs))
        return self.rng.uniform(self.low, self.high, (n, len(self.low)))
