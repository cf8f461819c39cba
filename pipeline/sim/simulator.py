"""Batched simulation of N vehicles `p_dot = u` under a feedback law (SPEC §1, §3.3).

Two models (`sim.model`): `sampled` (below; the camera in the loop) and `continuous` (the paper's hybrid
arcs, `pipeline.sim.continuous`). Both read the controller's hybrid data through the same functions
(`flow_map`, `jump_map`, `flow_set`, `jump_set`) and return the same `SimResult`.

Sampled model: each camera frame (every `camera_period`, a multiple of `dt`) a vehicle gets a new measurement with
probability `1 - p_fail` (else the controller holds the last estimate; a measurement hook may also return NaN
rows, frames it rejects itself, e.g. gated by the map's predicted error, which are held alike); the controller is evaluated on
the perceived positions and its velocity is held until the next frame (zero-order hold). The state is
integrated with explicit Euler steps of `dt`. Each agent's hybrid arc `(t, j, p, q, m, u)` is recorded
every `record_every` steps, and each agent ends with a termination cause in the spirit of the Hybrid
Equations Toolbox: reached the target, collision, non-finite state, or the horizon.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from pipeline.control.controllers import Controller
from pipeline.control.scene import Scene
from pipeline.errors import ConfigError
from pipeline.sim.disturbances import Disturbance, NoDisturbance
from pipeline.sim.metrics import StallMonitor, check_stall, outcome

MODELS = ("sampled", "continuous")
TERMINATIONS = ("horizon", "target", "collision", "non_finite")
HORIZON, TARGET, COLLISION, NON_FINITE = range(4)

# measure(p_true (n, 2), idx (n,), frame, rng) -> perceived positions (n, 2), before the disturbance
Measure = Callable[[np.ndarray, np.ndarray, int, np.random.Generator], np.ndarray]
# target_fn(t, frame, p_true (n, 2), idx (n,), rng) -> perceived (moving) targets (n, 2)
TargetFn = Callable[[float, int, np.ndarray, np.ndarray, np.random.Generator], np.ndarray]


def true_state(p: np.ndarray, idx: np.ndarray, frame: int, rng: np.random.Generator) -> np.ndarray:
    """Measurement without a camera: the true position (a disturbance is added on top)."""
    return p.copy()


@dataclass
class SimResult:
    """Hybrid arcs and per-agent metrics of one batched run."""

    controller: str
    x0: np.ndarray  # (N, 2)
    t: np.ndarray  # (T,)
    p: np.ndarray  # (T, N, 2) true positions
    m: np.ndarray  # (T, N, 2) perceived positions
    u: np.ndarray  # (T, N, 2) velocities
    q: np.ndarray  # (T, N) modes (1 for non-hybrid controllers)
    j: np.ndarray  # (T, N) jump counters
    target: np.ndarray | None  # (T, N, 2) perceived targets, moving-target runs only
    metrics: dict = field(default_factory=dict)  # name -> (N,) arrays

    def metrics_frame(self) -> pd.DataFrame:
        """One row per agent: the columns of `metrics.csv`."""
        df = pd.DataFrame({"controller": self.controller, "x0": self.x0[:, 0], "y0": self.x0[:, 1]})
        for k, v in self.metrics.items():
            df[k] = v
        return df

    def save_npz(self, path) -> None:
        arrays = {k: getattr(self, k) for k in ("x0", "t", "p", "m", "u", "q", "j")}
        if self.target is not None:
            arrays["target"] = self.target
        np.savez_compressed(path, **arrays, termination=np.asarray(self.metrics["termination"]))


def check_timing(dt: float, horizon: float, camera_period: float | None) -> int:
    """Validate the time grid; return the number of steps per camera frame."""
    if not (isinstance(dt, int | float) and math.isfinite(dt) and dt > 0):
        raise ConfigError("sim.dt", f"must be > 0, got {dt!r}")
    if not (isinstance(horizon, int | float) and math.isfinite(horizon) and horizon >= dt):
        raise ConfigError("sim.horizon", f"must be >= sim.dt = {dt}, got {horizon!r}")
    if camera_period is None:
        return 1
    every = round(camera_period / dt)
    if every < 1 or abs(every * dt - camera_period) > 1e-9 * max(1.0, camera_period):
        raise ConfigError("camera.period", f"must be a positive multiple of sim.dt = {dt}, got {camera_period!r}")
    return every


def _hold(new: np.ndarray, last: np.ndarray) -> np.ndarray:
    """A measurement hook's NaN rows are failed frames (e.g. gated by the map's own predicted error): the
    controller holds the last estimate for those agents, as for `p_fail`."""
    bad = np.isnan(new).any(axis=1)
    if bad.any():
        new = np.array(new, dtype=float)
        new[bad] = last[bad]
    return new


def simulate(
    scene: Scene,
    controller: Controller,
    x0: np.ndarray,
    *,
    dt: float = 0.01,
    horizon: float = 30.0,
    delta: float = 1.0,
    camera_period: float | None = None,
    p_fail: float = 0.0,
    disturbance: Disturbance | None = None,
    measure: Measure | None = None,
    target_fn: TargetFn | None = None,
    seed: int | np.random.Generator = 0,
    record_every: int = 10,
    record: bool = True,
    stop_on_success: bool = True,
    progress: bool = False,
    model: str = "sampled",
    rtol: float = 1e-6,
    atol: float = 1e-4,
    h_max: float = 0.25,
    method: str = "rosenbrock23",
    stall_speed: float = 0.25,
    stall_time: float = 5.0,
) -> SimResult:
    """Simulate all agents of `x0` `(N, 2)` at once; see the module docstring.

    The first frame is always delivered (a vehicle starts with an estimate). Success: `|p - p_T| <= delta`
    within the horizon without ever entering the obstacle; collision: `|p - p_0| < r` at any step.
    `model='continuous'` integrates the hybrid arcs with a batched adaptive Runge–Kutta scheme
    (`method`: `rosenbrock23` or `dopri5`; tolerances `rtol`, `atol`, largest step `h_max`); `dt` is then the record grid only. It takes the
    true state only: a `measure`/`target_fn` hook or camera failures raise `ConfigError('sim.model')`.
    Outcome per agent (`metrics['outcome']`): `reached`, `collided`, `stalled` (mean speed below
    `stall_speed` over the last `stall_time` seconds, away from the target) or `timed_out`.
    """
    if model not in MODELS:
        raise ConfigError("sim.model", f"must be one of {MODELS}, got {model!r}")
    every = check_timing(dt, horizon, camera_period)
    stall_speed, stall_time = check_stall(stall_speed, stall_time)
    if not (0.0 <= float(p_fail) < 1.0):
        raise ConfigError("camera.p_fail", f"must be in [0, 1), got {p_fail!r}")
    if not delta > 0:
        raise ConfigError("sim.delta", f"must be > 0, got {delta!r}")
    if not (isinstance(record_every, int) and record_every >= 1):
        raise ConfigError("sim.record_every", f"must be an integer >= 1, got {record_every!r}")
    x0 = np.asarray(x0, dtype=float)
    if x0.ndim != 2 or x0.shape[1] != 2 or len(x0) == 0:
        raise ConfigError("init.points", f"initial conditions must be a non-empty (N, 2) array, got shape {x0.shape}")
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    disturbance = disturbance or NoDisturbance()
    stall = StallMonitor(len(x0), stall_speed, stall_time, dt)
    if model == "continuous":
        if (measure is not None and measure is not true_state) or target_fn is not None:
            raise ConfigError("sim.model", "continuous takes the true state only: a camera/perception-map "
                              "measurement or a moving target is sampled per frame (use sim.model=sampled)")
        if p_fail > 0:
            raise ConfigError("sim.model", f"camera failures (camera.p_fail = {p_fail}) hold a frame's "
                              "estimate: sampled-only (use sim.model=sampled)")
        for value, name in ((rtol, "sim.rtol"), (atol, "sim.atol"), (h_max, "sim.h_max")):
            if not (isinstance(value, int | float) and math.isfinite(value) and value > 0):
                raise ConfigError(name, f"must be > 0, got {value!r}")
        from pipeline.sim.continuous import METHODS, simulate_continuous

        if method not in METHODS:
            raise ConfigError("sim.method", f"must be one of {METHODS}, got {method!r}")

        rec, st = simulate_continuous(
            scene, controller, x0, dt=dt, horizon=horizon, delta=delta, every=every, disturbance=disturbance,
            rng=rng, record_every=record_every, record=record, stop_on_success=stop_on_success, stall=stall,
            rtol=rtol, atol=atol, h_max=h_max, method=method)
        return _result(scene, controller, x0, rec, None, st, stall, delta, stop_on_success)
    measure = measure or true_state
    n = len(x0)
    n_steps = int(round(horizon / dt))
    all_idx = np.arange(n)
    r, p0, pT = scene.obstacle_radius, scene.p_0, scene.p_T

    exact = type(disturbance) is NoDisturbance

    def perceive(p_sub, idx, frame):
        m_sub = measure(p_sub, idx, frame, rng)
        return m_sub if exact else m_sub + disturbance(p_sub, frame, rng, scene)

    p = x0.copy()
    m = perceive(p, all_idx, 0)
    target = None if target_fn is None else np.asarray(target_fn(0.0, 0, p, all_idx, rng), dtype=float)
    controller.reset(m, target)
    u = np.zeros_like(p)

    active = np.ones(n, dtype=bool)
    term = np.full(n, HORIZON, dtype=np.int8)
    t_hit = np.full(n, np.nan)
    r2, delta2 = r * r, delta * delta
    px, py = p[:, 0], p[:, 1]  # views: integrating them updates p
    min_d2 = (px - p0[0]) ** 2 + (py - p0[1]) ** 2
    collided = min_d2 < r2
    min_e2 = (px - pT[0]) ** 2 + (py - pT[1]) ** 2
    path = np.zeros(n)
    speed_dt = dpx = dpy = np.zeros(n)

    n_rec = n_steps // record_every + 1 if record else 1
    rec = {
        "t": np.zeros(n_rec), "p": np.zeros((n_rec, n, 2)), "m": np.zeros((n_rec, n, 2)),
        "u": np.zeros((n_rec, n, 2)), "q": np.ones((n_rec, n), dtype=np.int8), "j": np.zeros((n_rec, n), dtype=np.int32),
    }
    rec_target = np.zeros((n_rec, n, 2)) if (record and target is not None) else None
    k_rec = 0

    def store(t):
        nonlocal k_rec
        rec["t"][k_rec] = t
        rec["p"][k_rec], rec["m"][k_rec], rec["u"][k_rec] = p, m, u
        rec["q"][k_rec], rec["j"][k_rec] = controller.q if controller.q.shape == (n,) else 1, controller.jumps
        if rec_target is not None:
            rec_target[k_rec] = target
        k_rec += 1

    # initial collision (started inside the obstacle) ends the run for that agent
    term[collided] = COLLISION
    active &= ~collided
    t = 0.0
    if record:
        store(0.0)
    stall.sample(p)

    steps = range(n_steps)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc=f"simulate {controller.name}", unit="step", leave=False)
    for step in steps:
        if step % every == 0:
            frame = step // every
            if frame > 0:
                fresh = active & (rng.random(n) >= p_fail) if p_fail > 0 else active
                if fresh.all():
                    m = _hold(perceive(p, all_idx, frame), m)
                    if target_fn is not None:
                        target = _hold(np.asarray(target_fn(step * dt, frame, p, all_idx, rng), dtype=float), target)
                elif fresh.any():
                    idx = np.flatnonzero(fresh)
                    m = m.copy()
                    m[idx] = _hold(perceive(p[idx], idx, frame), m[idx])
                    if target_fn is not None:
                        target = target.copy()
                        target[idx] = _hold(np.asarray(target_fn(step * dt, frame, p[idx], idx, rng), dtype=float),
                                            target[idx])
            u = controller(m, target)
            if not active.all():
                u[~active] = 0.0
            speed_dt = dt * np.hypot(u[:, 0], u[:, 1])  # u is held until the next frame
            dpx, dpy = dt * u[:, 0], dt * u[:, 1]
        px += dpx
        py += dpy
        path += speed_dt
        rx, ry = px - p0[0], py - p0[1]
        d2 = rx * rx + ry * ry
        np.minimum(min_d2, d2, out=min_d2)
        t = (step + 1) * dt
        ex, ey = px - pT[0], py - pT[1]
        e2 = ex * ex + ey * ey
        np.minimum(min_e2, e2, out=min_e2)
        events = (d2 < r2) | (e2 <= delta2)
        events &= active
        if events.any():  # rare: handle collisions and arrivals in detail
            hit_obstacle = events & (d2 < r2)
            term[hit_obstacle] = COLLISION
            collided |= hit_obstacle
            active &= ~hit_obstacle
            reached = events & ~hit_obstacle & (e2 <= delta2) & np.isnan(t_hit)
            t_hit[reached] = t
            if stop_on_success:
                term[reached] = TARGET
                active &= ~reached
        if step % every == every - 1 and not np.isfinite(d2.sum()):
            bad = active & ~np.isfinite(p).all(axis=1)
            if bad.any():
                term[bad] = NON_FINITE
                active &= ~bad
        if (step + 1) % stall.every == 0:
            stall.sample(p)
        if record and (step + 1) % record_every == 0:
            store(t)
        if not active.any():
            break
    if not record or (k_rec < n_rec and rec["t"][k_rec - 1] != t):
        store(t)  # the final state (the only one recorded when record=False)
    k = k_rec
    rec = {key: v[:k] for key, v in rec.items()}
    st = {"p": p, "term": term, "t_hit": t_hit, "collided": collided, "min_d2": min_d2, "min_e2": min_e2,
          "path": path, "jumps": controller.jumps.copy(), "pushouts": controller.pushouts.copy()}
    return _result(scene, controller, x0, rec, None if rec_target is None else rec_target[:k], st, stall, delta,
                   stop_on_success)


def _result(scene, controller, x0, rec, target, st, stall, delta, stop_on_success) -> SimResult:
    """Per-agent metrics from the final state `st` of either model, packed with the recorded arc."""
    p, term, collided = st["p"], st["term"], st["collided"]
    pT, r = scene.p_T, scene.obstacle_radius
    success = ~np.isnan(st["t_hit"]) & ~collided
    if not stop_on_success:
        term[success & (term == HORIZON)] = TARGET
    final_error = np.hypot(p[:, 0] - pT[0], p[:, 1] - pT[1])
    stalled = stall.stalled(p) & (term == HORIZON) & (final_error > delta)
    metrics = {
        "success": success,
        "collision": collided,
        "time_to_target": st["t_hit"],
        "min_clearance": np.sqrt(st["min_d2"]) - r,
        "min_target_distance": np.sqrt(st["min_e2"]),
        "jumps": st["jumps"],
        "pushouts": st["pushouts"],
        "path_length": st["path"],
        "final_error": final_error,
        "termination": np.asarray(TERMINATIONS)[term],
        "outcome": outcome(success, collided, stalled),
    }
    return SimResult(
        controller=controller.name, x0=x0, t=rec["t"], p=rec["p"], m=rec["m"], u=rec["u"], q=rec["q"],
        j=rec["j"], target=target, metrics=metrics,
    )
