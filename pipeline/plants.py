"""Vehicles (the plant of the closed loop): state `c` `(N, n)` whose first two columns are the position `p`.

A plant maps the input `w` it is given to its flow `c_dot = flow(c, w)`, and integrates one held input exactly
(`step(c, w, h)`: the zero-order hold of a sampled loop). The controller steers a point of the vehicle
(`point(c)`) with a velocity `u`; `actuate(c_hat, u)` is the input that realises `u` at the (measured) state
`c_hat`.

- :class:`SingleIntegrator`: `p_dot = u` (SPEC §1); the controller's velocity is the input.
- :class:`Unicycle`: `x_dot = v cos θ`, `y_dot = v sin θ`, `θ_dot = ω` (SPEC §3.7): the controller steers the
  look-ahead point `z = p + d (cos θ, sin θ)`, which obeys `z_dot = u` exactly with
  `v = u·(cos θ, sin θ)`, `ω = u·(-sin θ, cos θ) / d`; `|ω| <= omega_max` (saturated inputs are counted by
  the caller with :meth:`Unicycle.saturated`); each held `(v, ω)` is integrated as an exact arc.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np

from pipeline.errors import ConfigError
from pipeline.schema import NonNegativeInt, Positive, PositiveInt, checked


class Plant:
    """Interface of a vehicle (batched over the leading axis)."""

    name = "plant"
    dim = 2          # state dimension n
    inputs = 2       # input dimension
    heading = False  # whether the state holds a heading (column 2)
    smoothing = 1    # commanded velocities averaged by the sampled loop (the unicycle's option)

    def position(self, c: np.ndarray) -> np.ndarray:
        """The vehicle's position `p` `(N, 2)` (success and collision are judged here)."""
        return c[:, :2]

    def point(self, c: np.ndarray) -> np.ndarray:
        """The point the controller steers `(N, 2)`."""
        return c[:, :2]

    def actuate(self, c_hat: np.ndarray, u: np.ndarray) -> np.ndarray:
        """The input `w` that moves `point` with velocity `u` at the (measured) state `c_hat`."""
        raise NotImplementedError

    def flow(self, c: np.ndarray, w: np.ndarray) -> np.ndarray:
        raise NotImplementedError

    def step(self, c: np.ndarray, w: np.ndarray, h: float) -> np.ndarray:
        """`c(t + h)` under the input `w` held on `[t, t + h]` (exact)."""
        raise NotImplementedError

    def speed(self, w: np.ndarray) -> np.ndarray:
        """`|p_dot|` `(N,)` under the held input `w` (constant along a held step)."""
        raise NotImplementedError

    def saturated(self, w: np.ndarray) -> np.ndarray:
        """Rows whose input was clipped by a limit of the vehicle (none by default)."""
        return np.zeros(len(w), dtype=bool)

    def lift(self, p: np.ndarray, heading: np.ndarray | None = None) -> np.ndarray:
        """States `(N, n)` at positions `p` (and headings, for a vehicle that has one)."""
        return np.array(p, dtype=float).reshape(-1, 2)

    def initial_heading(self, p: np.ndarray, scene) -> np.ndarray | None:
        """The initial headings `(N,)` of vehicles starting at `p` (None: a vehicle without one)."""
        return None

    def steering_scene(self, scene):
        """The scene the feedback law steers `point` in (the real one)."""
        return scene


class SingleIntegrator(Plant):
    """`p_dot = u` (SPEC §1). The speed limit `u_max` is the controller's (it saturates its velocity)."""

    name = "integrator"

    def actuate(self, c_hat, u):
        return u

    def flow(self, c, w):
        return w

    def step(self, c, w, h):
        return c + h * w

    def speed(self, w):
        return np.hypot(w[:, 0], w[:, 1])


@checked("vehicle")
class Unicycle(Plant):
    """The unicycle of SPEC §3.7, steered through its look-ahead point `z = p + d (cos θ, sin θ)`.

    `lookahead` is `d` (> 0; SPEC requires `d < δ`, the success radius, checked by the closed loop), `omega_max`
    the turn-rate limit (rad/s, null: none). Its speed `|v| <= |u| <= u_max` follows from the controller's
    saturation. `heading0`: the initial heading of every start: `random` (uniform over the circle, from
    `heading_seed`, the same for the same starts), `target` (facing the target) or a number (radians).

    Two options for a turn-rate limit far below `u_max / d` (docs/dense.md, "The unicycle in clutter"; both off by
    default): `smoothing` (`k >= 1`): the sampled loop realises the mean of the last `k` commanded velocities of
    `z` (this frame's and the `k - 1` before; fewer at a run's start). Under a perception error that flips from
    frame to frame the law's command near a face alternates between the flow and the push-out; the clipped turn
    keeps the first's part along the heading and drops most of the second's, the mean keeps both.
    `turn_lookahead` (`ρ`, null: off): a speed that slows in a turn, `v <- v min(1, omega_max ρ / |u·n|)` (`n` the
    heading's normal): the forward speed at which a look-ahead of `ρ` would turn onto the command within
    `omega_max`, so that at full speed the heading lags the command by at most `asin(omega_max ρ / |u|)`
    (`ρ >= d`: nothing changes where `ω` is not clipped).
    """

    name = "unicycle"
    dim = 3
    heading = True

    def __init__(self, lookahead: Positive = 0.5, omega_max: Positive | None = 4.0 * math.pi,
                 heading0: Literal["random", "target"] | float = "random", heading_seed: NonNegativeInt = 0,
                 smoothing: PositiveInt = 1, turn_lookahead: Positive | None = None):
        if isinstance(heading0, float) and not math.isfinite(heading0):
            raise ConfigError("vehicle.heading0", f"must be random, target or a finite number (radians), got {heading0!r}")
        self.lookahead = float(lookahead)
        self.omega_max = None if omega_max is None else float(omega_max)
        self.heading0, self.heading_seed = heading0, heading_seed
        self.smoothing = int(smoothing)
        if turn_lookahead is not None and omega_max is None:
            raise ConfigError("vehicle.turn_lookahead", "slows the vehicle where its turn rate would pass "
                                                        "omega_max: needs vehicle.omega_max (null here)")
        self.turn_lookahead = None if turn_lookahead is None else float(turn_lookahead)

    def point(self, c):
        d = self.lookahead
        return np.stack([c[:, 0] + d * np.cos(c[:, 2]), c[:, 1] + d * np.sin(c[:, 2])], axis=1)

    def actuate(self, c_hat, u):
        """`v = u·(cos θ, sin θ)`, `ω = u·(-sin θ, cos θ) / d`, `|ω|` clipped at `omega_max` (SPEC §3.7); with
        `turn_lookahead` `ρ` the speed `v` scaled by `min(1, omega_max ρ / |u·(-sin θ, cos θ)|)` first."""
        ct, st = np.cos(c_hat[:, 2]), np.sin(c_hat[:, 2])
        v = u[:, 0] * ct + u[:, 1] * st
        lateral = -u[:, 0] * st + u[:, 1] * ct
        omega = lateral / self.lookahead
        if self.turn_lookahead is not None:
            v = v * np.minimum(1.0, self.omega_max * self.turn_lookahead / np.maximum(np.abs(lateral), 1e-300))
        if self.omega_max is not None:
            omega = np.clip(omega, -self.omega_max, self.omega_max)
        return np.stack([v, omega], axis=1)

    def saturated(self, w):
        if self.omega_max is None:
            return np.zeros(len(w), dtype=bool)
        return np.abs(w[:, 1]) >= self.omega_max * (1.0 - 1e-12)

    def flow(self, c, w):
        v, omega = w[:, 0], w[:, 1]
        return np.stack([v * np.cos(c[:, 2]), v * np.sin(c[:, 2]), omega], axis=1)

    def step(self, c, w, h):
        """The exact arc of a held `(v, ω)`: a circle of radius `v / ω` (a segment where `ω h` is tiny)."""
        v, omega = w[:, 0], w[:, 1]
        th = c[:, 2]
        dth = omega * h
        turning = np.abs(dth) > 1e-9
        safe = np.where(turning, omega, 1.0)
        s0, c0 = np.sin(th), np.cos(th)
        s1, c1 = np.sin(th + dth), np.cos(th + dth)
        # straight-line limit of the arc: the first order of (sin(θ + ωh) - sin θ) / ω in ωh
        dx = np.where(turning, v * (s1 - s0) / safe, v * h * c0)
        dy = np.where(turning, -v * (c1 - c0) / safe, v * h * s0)
        return np.stack([c[:, 0] + dx, c[:, 1] + dy, th + dth], axis=1)

    def speed(self, w):
        return np.abs(w[:, 0])

    def steering_scene(self, scene):
        """Every disc inflated by the look-ahead `d`, so that the axle point, `d` from `z`, stays out of the real
        disc (SPEC §3.7)."""
        return scene.inflated(self.lookahead)

    def initial_heading(self, p, scene):
        """`heading0` at every start `p` `(N, 2)`: seeded uniform, facing the scene's target, or one angle."""
        p = np.asarray(p, dtype=float).reshape(-1, 2)
        if self.heading0 == "random":
            return np.random.default_rng(self.heading_seed).uniform(-math.pi, math.pi, len(p))
        if self.heading0 == "target":
            return np.arctan2(scene.p_T[1] - p[:, 1], scene.p_T[0] - p[:, 0])
        return np.full(len(p), float(self.heading0))

    def lift(self, p, heading=None):
        p = np.array(p, dtype=float).reshape(-1, 2)
        th = np.zeros(len(p)) if heading is None else np.asarray(heading, dtype=float).reshape(-1)
        return np.column_stack([p, th])


def explain_steering(plant: Plant, err: ConfigError) -> ConfigError:
    """`err` (raised on the plant's steering scene) naming what the unicycle changes: its controller steers the
    look-ahead point around every disc grown by `vehicle.lookahead` (SPEC §3.7), so a radius, apex or distance in
    the message is the inflated one."""
    d = getattr(plant, "lookahead", None)
    if d is None or "vehicle.lookahead" in err.reason:
        return err
    return ConfigError(err.field, f"{err.reason} (the unicycle's look-ahead point steers around every disc grown by "
                                  f"vehicle.lookahead = {d:g}: the radii, apexes and distances here are the inflated "
                                  f"ones; a smaller vehicle.lookahead or a sparser scene helps)")


def steering_warnings(plant: Plant, controller) -> list[str]:
    """Lines warning that the unicycle cannot follow its look-ahead steering (SPEC §3.7; docs/multi.md): the law's
    speed limit turns it at up to `u_max / d`, past `omega_max` (unless it slows in a turn, `turn_lookahead`); a
    push-out at `push_speed >= omega_max d / 2` can hold it in a period-2 orbit at a face (unless the loop realises
    the mean of two commands, `smoothing >= 2`: docs/dense.md). Empty for a plant without a look-ahead."""
    d, w = getattr(plant, "lookahead", None), getattr(plant, "omega_max", None)
    if d is None or w is None:
        return []
    out = []
    u_max, push = getattr(controller, "u_max", None), getattr(controller, "push_speed", None)
    if u_max is not None and u_max / d > w and getattr(plant, "turn_lookahead", None) is None:
        out.append(f"vehicle.lookahead: the steering asks |ω| up to controller.u_max / d = {u_max / d:.3g} rad/s, past "
                   f"vehicle.omega_max = {w:.3g}: the unicycle cannot follow it at full speed (saturated frames; "
                   f"vehicle.turn_lookahead slows it in a turn)")
    if (push is not None and getattr(controller, "hybrid", False) and push >= w * d / 2
            and getattr(plant, "smoothing", 1) < 2):
        out.append(f"controller.push_speed: {push:g} >= omega_max d / 2 = {w * d / 2:.3g}: a push-out can hold the "
                   f"unicycle at a face in a period-2 orbit (docs/multi.md, push-out speed; vehicle.smoothing=2 "
                   f"realises the mean of two frames' commands)")
    return out
