"""The generic solvers of `pipeline.hybrid` on hybrid systems that are not the paper's closed loop.

A bouncing ball and a timer, each with a closed-form hybrid arc, run through both solvers: the continuous
solver locates their jumps in time (to ~1e-6), the sampled solver jumps at the first frame in the jump set
(within one frame period). Neither system has a controller, a scene or a plant input: the solvers need only
the four maps of a :class:`~pipeline.hybrid.HybridSystem` and its plant's `flow`, `step`, `speed`, `inputs`
and `position` (the arc length is that of `position`).
"""

from __future__ import annotations

import math

import numpy as np
import pytest

from pipeline.hybrid import HybridSystem, State, solve_continuous, solve_sampled

G, E = 9.81, 0.8  # gravity, coefficient of restitution


# ------------------------------------------------------------------------------------------- systems


class FreeFall:
    """The ball's plant: `c = (h, v)`, `c_dot = (v, -g)`, no input; its position is the height."""

    inputs = 0

    def __init__(self, g: float = G):
        self.g = g

    def position(self, c):
        return c[:, :1]

    def flow(self, c, w):
        return np.stack([c[:, 1], np.full(len(c), -self.g)], axis=1)

    def step(self, c, w, h):
        """Exact free fall over `h`."""
        return np.stack([c[:, 0] + h * c[:, 1] - 0.5 * self.g * h * h, c[:, 1] - self.g * h], axis=1)

    def speed(self, w):  # the speed of a held input: there is none (a solver must not need it)
        raise AssertionError("a plant without input has no held speed")


class BouncingBall(HybridSystem):
    """`C = {h >= 0}`, `D = {h <= 0, v < 0}`, `G(h, v) = (h, -e v)`."""

    def __init__(self, g: float = G, e: float = E):
        self.plant, self.e = FreeFall(g), e

    def jump_set(self, x):
        return (x.c[:, 0] <= 0) & (x.c[:, 1] < 0)

    def flow_set(self, x):
        return x.c[:, 0] >= 0

    def jump_map(self, x):
        return x.replace(c=np.stack([x.c[:, 0], -self.e * x.c[:, 1]], axis=1))


class Clock:
    """The timer's plant: `c = (tau,)`, `tau_dot = 1`, no input; its "position" is `tau`."""

    inputs = 0

    def position(self, c):
        return c[:, :1]

    def flow(self, c, w):
        return np.ones_like(c)

    def step(self, c, w, h):
        return c + h

    def speed(self, w):
        raise AssertionError("a plant without input has no held speed")


class Timer(HybridSystem):
    """`tau_dot = 1` on `C = {tau <= T}`; at `tau >= T` (`D`) `tau+ = 0` and the counter `n` (in `d`) counts."""

    recorded = ("n",)

    def __init__(self, period: float):
        self.plant, self.T = Clock(), period

    def initial(self, c0, rng):
        return State(np.array(c0, dtype=float), n=np.zeros(len(c0), dtype=np.int64))

    def jump_set(self, x):
        return x.c[:, 0] >= self.T

    def flow_set(self, x):
        return x.c[:, 0] <= self.T

    def jump_map(self, x):
        return x.replace(c=np.zeros_like(x.c), n=x.n + 1)


# ----------------------------------------------------------------------------------------- closed forms


def ball_bounces(h0: float, v0: float, horizon: float, g: float = G, e: float = E):
    """Bounce times `t_k` and impact speeds `w_k` (upwards after the bounce: `e w_k`) up to `horizon`:
    `t_0 = (v0 + sqrt(v0^2 + 2 g h0)) / g`, `t_{k+1} = t_k + 2 e^{k+1} w_0 / g`."""
    w = math.sqrt(v0 * v0 + 2 * g * h0)
    t = (v0 + w) / g
    times, speeds = [], []
    while t <= horizon:
        times.append(t)
        speeds.append(w)
        w *= e
        t += 2 * w / g
    return np.array(times), np.array(speeds)


def ball_height(t, h0, v0, times, speeds, g: float = G, e: float = E):
    """The height at times `t` (the ideal arc: a jump keeps `h = 0`)."""
    t = np.asarray(t, dtype=float)
    k = np.searchsorted(times, t, side="right")  # bounces at or before t
    h = h0 + v0 * t - 0.5 * g * t * t
    after = k > 0
    tk = times[np.maximum(k - 1, 0)]
    up = e * speeds[np.maximum(k - 1, 0)]
    s = t - tk
    return np.where(after, up * s - 0.5 * g * s * s, h)


def ball_path(h0, v0, horizon, times, speeds, g: float = G, e: float = E) -> float:
    """Distance travelled by the height up to `horizon` (closed form per flight)."""
    def travelled(h_start, v, s):  # free fall from (h_start, v) for s seconds
        t_apex = v / g
        if 0 < t_apex < s:
            apex = h_start + v * v / (2 * g)
            return (apex - h_start) + (apex - (h_start + v * s - 0.5 * g * s * s))
        return abs(v * s - 0.5 * g * s * s)

    starts = [(0.0, h0, v0)] + [(tk, 0.0, e * wk) for tk, wk in zip(times, speeds)]
    total = 0.0
    for i, (t0, hs, v) in enumerate(starts):
        t1 = times[i] if i < len(times) else horizon
        total += travelled(hs, v, t1 - t0)
    return total


def sampled_ball(h0: float, v0: float, period: float, horizon: float, g: float = G, e: float = E):
    """The sample-and-hold ball in closed form, flight by flight: from the state after a frame's jump it falls
    freely; the next jump is at the first frame time at or after its downward crossing of `h = 0`."""
    t, h, v = 0.0, h0, v0
    times = []
    while True:
        if h <= 0 and v < 0:
            times.append(t)
            v = -e * v
        s_cross = (v + math.sqrt(v * v + 2 * g * h)) / g  # the later root of h + v s - g s^2 / 2 = 0
        k = math.ceil((t + s_cross) / period - 1e-9)
        t_next = k * period
        if t_next >= horizon - 1e-12:  # the last frame is before the horizon
            return np.array(times)
        s = t_next - t
        h, v, t = h + v * s - 0.5 * g * s * s, v - g * s, t_next


def jump_times(arc, dt: float = 0.0) -> list[np.ndarray]:
    """Per agent, the recorded times where the jump counter increments (minus `dt`: a sampled frame's jump
    shows in the record after its step)."""
    return [arc.t[1:][np.diff(arc.j[:, i]) > 0] - dt for i in range(arc.j.shape[1])]


# ------------------------------------------------------------------------------------------- the ball

STARTS = np.array([[5.0, 0.0], [2.0, 3.0], [8.0, -4.0]])  # (h0, v0)
HORIZON = 6.0


@pytest.mark.parametrize("method", ["rosenbrock23", "dopri5"])
def test_bouncing_ball_continuous_matches_closed_form(method):
    """Bounce times `t_k = t_0 + sum_j 2 e^j w_0 / g`, the heights at the record times, the number of bounces
    in the horizon and the distance travelled, with the bounces located in time."""
    ball = BouncingBall()
    dt, every = 0.01, 5
    n_steps = round(HORIZON / dt)
    arc = solve_continuous(ball, ball.initial(STARTS, None), dt=dt, n_steps=n_steps, rng=np.random.default_rng(0),
                           record_every=every, method=method)
    assert arc.w is None  # no plant input
    assert (arc.termination == 0).all() and arc.t[-1] == pytest.approx(HORIZON)
    np.testing.assert_allclose(arc.t, np.arange(n_steps // every + 1) * every * dt, atol=1e-12)
    for i, (h0, v0) in enumerate(STARTS):
        times, speeds = ball_bounces(h0, v0, HORIZON)
        assert len(times) >= 3
        assert arc.jumps[i] == len(times)
        # the jump shows at the first record after it (a record at its instant keeps the state before it)
        first = np.array([np.argmax(arc.j[:, i] >= k + 1) for k in range(len(times))])
        np.testing.assert_allclose(arc.t[first] - every * dt, np.floor(times / (every * dt) - 1e-9) * every * dt,
                                   atol=1e-9)
        # each located bounce time, read off the recorded state after it: (h, v) lies on the parabola that
        # left h = 0 at t_k, s = t - t_k = (sqrt(v^2 + 2 g h) - v) / g
        h, v = arc.c[first, i, 0], arc.c[first, i, 1]
        np.testing.assert_allclose(arc.t[first] - (np.sqrt(v * v + 2 * G * h) - v) / G, times, atol=1e-6)
        # each located bounce is late by at most 2^-22 of its step (<= h_max): the heights are off by at most
        # the speed times the accumulated delay
        located = len(times) * 0.25 * 2.0**-22
        np.testing.assert_allclose(arc.c[:, i, 0], ball_height(arc.t, h0, v0, times, speeds),
                                   atol=speeds[0] * located + 1e-9)
        # the final velocity gives the last bounce's time: v(T) = e w_K - g (T - t_K)
        t_last = HORIZON - (E * speeds[-1] - arc.final.c[i, 1]) / G
        assert t_last == pytest.approx(times[-1], abs=1e-6)
        # the arc never goes below the floor by more than the event location's error
        assert arc.c[:, i, 0].min() > -1e-6
        assert arc.outside[i] == 0  # a located jump leaves no state outside C ∪ D
        # arc length of the position: the trapezoid on |h_dot| is exact but over a step holding an apex
        # (a V-shaped |v|: at most g h_max^2 / 4 more)
        exact = ball_path(h0, v0, HORIZON, times, speeds)
        assert exact - 1e-6 <= arc.path[i] <= exact + (len(times) + 1) * G * 0.25**2 / 4


def test_bouncing_ball_sampled_within_its_frame_period():
    """Sample-and-hold: each bounce at the first frame in D (the per-flight closed form, to rounding), the
    first within one frame period after the true one, the same number of bounces in the horizon, and the
    bounce times converging to the ideal ones with the period (a late bounce starts below the floor, faster:
    later bounces may be early or late)."""
    ball = BouncingBall()
    errors = {}
    for dt, every in ((0.002, 5), (0.0002, 5)):
        period = dt * every
        n_steps = round(HORIZON / dt)
        arc = solve_sampled(ball, ball.initial(STARTS, None), dt=dt, n_steps=n_steps, every=every,
                            rng=np.random.default_rng(0), record_every=1)
        assert arc.w is None and (arc.termination == 0).all()
        assert arc.t[-1] == pytest.approx(HORIZON)
        err = []
        for i, (h0, v0) in enumerate(STARTS):
            times, _ = ball_bounces(h0, v0, HORIZON)
            got = jump_times(arc, dt)[i]
            np.testing.assert_allclose(got, sampled_ball(h0, v0, period, HORIZON), atol=1e-9)
            assert arc.jumps[i] == len(times) == len(got)
            assert times[0] <= got[0] + 1e-12 and got[0] - times[0] < period
            err.append(np.abs(got - times).max())
            # the arc length of the position: the chords of the exact steps
            np.testing.assert_allclose(arc.path[i], np.abs(np.diff(arc.c[:, i, 0])).sum(), rtol=1e-12)
        errors[period] = max(err)
    coarse, fine = errors[0.01], errors[0.001]
    assert fine < coarse / 5, errors


# ------------------------------------------------------------------------------------------- the timer

T_TIMER = 0.33


@pytest.mark.parametrize("method", ["rosenbrock23", "dopri5"])
def test_timer_continuous_matches_closed_form(method):
    """Jumps at `t_k = T - tau_0 + k T` (one at t = 0 for tau_0 = T), `tau(t) = (t - t_0) mod T`, the counter
    in `d` counting the jumps, and the arc length of tau the horizon."""
    timer = Timer(T_TIMER)
    tau0 = np.array([[0.0], [0.2], [T_TIMER]])
    dt, every, horizon = 0.01, 1, 3.0
    n_steps = round(horizon / dt)
    arc = solve_continuous(timer, timer.initial(tau0, None), dt=dt, n_steps=n_steps, rng=np.random.default_rng(0),
                           record_every=every, method=method)
    assert arc.w is None and (arc.termination == 0).all()
    first = T_TIMER - tau0[:, 0]
    expected_jumps = np.floor((horizon - first) / T_TIMER + 1e-12).astype(int) + 1
    np.testing.assert_array_equal(arc.jumps, expected_jumps)
    np.testing.assert_array_equal(arc.final.n, expected_jumps)
    np.testing.assert_array_equal(arc.d["n"], arc.j)  # the counter is the solver's own jump count
    phase = np.mod(arc.t[:, None] - first[None, :], T_TIMER)
    near_jump = np.minimum(phase, T_TIMER - phase) < 1e-6
    np.testing.assert_allclose(arc.c[:, :, 0][~near_jump], phase[~near_jump], atol=1e-6)
    t_last = first + (expected_jumps - 1) * T_TIMER
    np.testing.assert_allclose(arc.final.c[:, 0], horizon - t_last, atol=1e-6)
    np.testing.assert_allclose(arc.path, horizon, atol=1e-6)


def test_timer_sampled_jumps_at_frames():
    """Sample-and-hold: a jump at the first frame where tau >= T, then every ceil(T / period) frames."""
    timer = Timer(T_TIMER)
    tau0 = np.array([[0.0], [0.2], [T_TIMER]])
    dt, every, horizon = 0.01, 5, 3.0
    period = dt * every
    n_steps = round(horizon / dt)
    arc = solve_sampled(timer, timer.initial(tau0, None), dt=dt, n_steps=n_steps, every=every,
                        rng=np.random.default_rng(0), record_every=1)
    assert arc.w is None and (arc.termination == 0).all()
    gap = math.ceil(T_TIMER / period - 1e-9)  # frames between two jumps
    n_frames = n_steps // every
    for i, t0 in enumerate(tau0[:, 0]):
        k0 = math.ceil((T_TIMER - t0) / period - 1e-9)  # first frame with tau >= T
        frames = np.arange(k0, n_frames, gap)
        got = jump_times(arc, dt)[i]
        np.testing.assert_allclose(got, frames * period, atol=1e-9)
        # within one frame period of the timer's own (continuous) jump times
        ideal = T_TIMER - t0 + np.arange(len(frames)) * T_TIMER
        assert ((got - ideal >= -1e-9) & (got - ideal < period * (1 + np.arange(len(frames))))).all()
        assert arc.jumps[i] == arc.final.n[i] == len(frames)
        np.testing.assert_allclose(arc.path[i], horizon, rtol=1e-12)
