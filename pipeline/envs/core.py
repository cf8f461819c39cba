"""The batched core of the Gymnasium environments (SPEC §6): N agents, one step = one camera frame.

One step of every agent is one frame of the sampled loop of :func:`pipeline.sim.simulate` (SPEC §1, §3.3). The
action is normalised (issue 46): :meth:`NavigationCore.velocity` multiplies it by :func:`action_scale` (`u_max`
per component; the unicycle's `(u_max, ω_max)`) into the velocity `u` (or `(v, ω)`), clips that to the vehicle's
limits as before (the norm of `u` to `u_max`, i.e. the action's norm to 1; `|v| <= u_max`, `|ω| <= ω_max`) and
holds it for the frame; :meth:`NavigationCore.action` is the inverse (`u / scale`), for the agents that compute
a velocity. The frame runs through the simulator's own frame engine (:class:`pipeline.hybrid.sampled.FrameRun`,
the action as the held input): the plant integrates it exactly in `every` steps of `dt`, and the simulator's
monitor (:class:`pipeline.sim.monitor.ArrivalCollision` with the camera's view as a third stop set) checks
collision (`|p - c_i| < r_i`, judged first), arrival (`|p - p_T| <= δ`) and leaving the view after every step;
an agent's run ends at the step it enters one (its outcome, :class:`pipeline.sim.metrics.Outcome`; `TIMED_OUT`
at the frame limit), and it completes the frame under its held input, as in the simulator. Then the camera
renders the next frame of every agent in one batched call (with the clouds; a frame lost with probability
`p_fail` repeats the last image, as the simulator holds the last estimate).

Reward per step (`env.*`, SPEC §6): `progress * (|p_k - p_T| - |p_{k+1} - p_T|) + arrival * [arrived]
- collision * [collided or left the view]`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.errors import ConfigError
from pipeline.hybrid import HybridSystem, State
from pipeline.hybrid.sampled import FrameRun
from pipeline.schema import NonNegative, checked
from pipeline.sim.metrics import NAMES, Outcome, StallMonitor
from pipeline.sim.monitor import ArrivalCollision

OUTCOMES = NAMES  # the outcome names by code (`info["outcome"]` of the single-agent environment)
RUNNING, TIMED_OUT = Outcome.RUNNING, Outcome.TIMED_OUT
ENDED = (Outcome.REACHED, Outcome.COLLIDED, Outcome.LEFT_VIEW)  # the environments' terminations


@checked("env")
@dataclass(frozen=True)
class EnvSettings:
    """`env`: the shaped reward of SPEC §6 and what the agent observes.

    `progress`: reward per world unit gained towards the target; `arrival`: bonus on arrival; `collision`: penalty
    on a collision or on leaving the camera's view; `observe_heading`: the unicycle's observation is a Dict of the
    frame and its true heading (`cos θ, sin θ`) instead of the frame alone."""

    progress: NonNegative = 1.0
    arrival: NonNegative = 10.0
    collision: NonNegative = 10.0
    observe_heading: bool = False


def action_scale(plant, u_max) -> np.ndarray:
    """The velocity of the unit action per component (the action is `velocity / scale`): `(u_max, u_max)` for the
    single integrator, `(u_max, ω_max)` for the unicycle (`u_max / d`, the steering's largest turn rate at full
    speed, when `ω_max` is null: then nothing clips `ω`, as before). `u_max` must be finite."""
    if u_max is None or not np.isfinite(u_max) or u_max <= 0:
        raise ConfigError("controller.u_max", f"the environments' action is the velocity in units of u_max: it must "
                                              f"be a positive number, got {u_max!r}")
    if not plant.heading:
        return np.array([u_max, u_max], dtype=float)
    om = plant.omega_max if plant.omega_max is not None else u_max / plant.lookahead
    return np.array([u_max, om], dtype=float)


def to_action(velocity, scale) -> np.ndarray:
    """The env's normalised action of a velocity `u` (or `(v, ω)`): `u / scale` (the one conversion every agent
    that computes a velocity uses; :meth:`NavigationCore.velocity` maps it back)."""
    return np.asarray(velocity, dtype=float) / scale


class HeldAction(HybridSystem):
    """The loop of an agent that acts from outside (a policy): its input is the velocity set for the frame."""

    def __init__(self, plant):
        self.plant, self.u = plant, None

    def input(self, x: State) -> np.ndarray:
        return self.u


class NavigationCore:
    """N agents of the sampled loop (see the module docstring); no Gymnasium API here."""

    def __init__(self, n: int, *, scene, plant, camera, scale, dt: float, every: int, frames: int,
                 delta: float, occlusion=None, p_fail: float = 0.0, settings: EnvSettings | None = None):
        self.n, self.scene, self.plant, self.camera = n, scene, plant, camera
        self.scale = np.asarray(scale, dtype=float).reshape(plant.inputs)  # :func:`action_scale`
        self.u_max, self.dt, self.every, self.frames, self.delta = float(self.scale[0]), dt, every, frames, delta
        self.occlusion = occlusion if occlusion is not None and getattr(occlusion, "active", False) else None
        self.p_fail, self.settings = float(p_fail), settings or EnvSettings()
        self.period = dt * every
        # the simulator's stop sets (arrival, collision) and the camera's view, on the plant's position
        self._monitor = ArrivalCollision(scene, plant, n, delta=delta, stop_on_success=True,
                                         stall=StallMonitor(n, 1.0, 1.0, dt), arena=scene.bounds)
        self._system = HeldAction(plant)
        self.c = np.zeros((n, plant.dim))
        self.k = np.zeros(n, dtype=np.int64)
        self.images = np.zeros((n, *camera.shape, 3), dtype=np.uint8)

    # ------------------------------------------------------------------------------------ helpers
    def position(self, c=None) -> np.ndarray:
        return self.plant.position(self.c if c is None else c)

    def distance(self, c=None) -> np.ndarray:
        p = self.position(c)
        return np.hypot(p[:, 0] - self.scene.p_T[0], p[:, 1] - self.scene.p_T[1])

    def render(self, c: np.ndarray, rng: np.random.Generator) -> np.ndarray:
        """The camera's frames of the states `c` (one batched call, clouds drawn from `rng`)."""
        heading = c[:, 2] if self.plant.heading else None
        return self.camera.render(self.position(c), None, occlusion=self.occlusion, rng=rng, heading=heading)

    def action(self, velocity) -> np.ndarray:
        """The normalised action of a velocity `u` (or `(v, ω)`): :func:`to_action` with this env's scale."""
        return to_action(velocity, self.scale)

    def velocity(self, action) -> np.ndarray:
        """The held input of a normalised action: `action * scale`, then the vehicle's limits (:meth:`clip`)."""
        return self.clip(np.asarray(action, dtype=float).reshape(self.n, self.plant.inputs) * self.scale)

    def clip(self, u) -> np.ndarray:
        """The vehicle's limits on a velocity: `|u| <= u_max` by scaling (the controllers' saturation; the action's
        norm clipped to 1); `(v, ω)`: each clipped (`|v| <= u_max`, `|ω| <= ω_max` unless null)."""
        a = np.asarray(u, dtype=float).reshape(self.n, self.plant.inputs)
        a = np.where(np.isfinite(a), a, 0.0)
        if self.plant.heading:
            om = getattr(self.plant, "omega_max", None)
            return np.column_stack([np.clip(a[:, 0], -self.u_max, self.u_max),
                                    a[:, 1] if om is None else np.clip(a[:, 1], -om, om)])
        norm = np.hypot(a[:, 0], a[:, 1])
        scale = np.where(norm > self.u_max, self.u_max / np.maximum(norm, 1e-300), 1.0)
        return a * scale[:, None]

    # --------------------------------------------------------------------------------------- API
    def reset(self, idx: np.ndarray, c0: np.ndarray, rng: np.random.Generator) -> None:
        """Agents `idx` start at the states `c0` `(len(idx), n)`; their first frame is always delivered."""
        self.c[idx] = c0
        self.k[idx] = 0
        self.images[idx] = self.render(self.c[idx], rng)

    def step(self, action, rng: np.random.Generator):
        """One frame of every agent: `(reward, code)` per agent (`code`: an :class:`Outcome`, why it stopped, if)."""
        self._system.u = self.velocity(action)
        d0 = self.distance()
        run = FrameRun(self._system, State(self.c), dt=self.dt, every=self.every, rng=rng, monitor=self._monitor)
        code = run.advance()
        self.c = run.x.c
        self.k += 1
        code[(code == RUNNING) & (self.k >= self.frames)] = TIMED_OUT
        s = self.settings
        reward = s.progress * (d0 - self.distance()) + s.arrival * (code == Outcome.REACHED) \
            - s.collision * ((code == Outcome.COLLIDED) | (code == Outcome.LEFT_VIEW))
        self._next_frames(code, rng)
        return reward, code

    def _next_frames(self, code, rng) -> None:
        """The next frame of the running agents (a lost frame, `p_fail`, repeats the last image), then the final
        frame of the agents that stopped (drawn after them, so the running agents' clouds are the simulator's)."""
        running = code == RUNNING
        fresh = running & (rng.random(self.n) >= self.p_fail) if self.p_fail > 0 else running
        if fresh.all():
            self.images = self.render(self.c, rng)
        elif fresh.any():
            idx = np.flatnonzero(fresh)
            self.images[idx] = self.render(self.c[idx], rng)
        if not running.all():
            idx = np.flatnonzero(~running)
            self.images[idx] = self.render(self.c[idx], rng)

    def info(self) -> dict[str, np.ndarray]:
        """The true state of every agent (SPEC §6: `info` carries it)."""
        return {"state": self.c.copy(), "position": self.position().copy(), "t": self.k * self.period,
                "distance": self.distance()}
