"""`simulate`: a batch of vehicles under a feedback law, through one of the two solvers (SPEC §1, §3.3).

The closed loop is a hybrid system (:mod:`pipeline.sim.closed_loop`); `sim.model: sampled` runs it through the
sampled-data solver (the camera in the loop: a frame every `camera_period`, the input held in between),
`continuous` through the continuous-time solver (the paper's hybrid arcs; true state only). Both return the
same :class:`SimResult`: the recorded arc `(t, j, p, q, m, u)` and per-agent metrics, each agent ending with a
termination cause in the spirit of the Hybrid Equations Toolbox (reached the target, collision, non-finite
state, or the horizon).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.hybrid import solve_continuous, solve_sampled
from pipeline.plants import Plant, SingleIntegrator, explain_steering
from pipeline.sim.closed_loop import ContinuousLoop, DeadReckoning, Measure, SampledLoop, TargetFn, true_state
from pipeline.sim.metrics import StallMonitor, outcome
from pipeline.sim.monitor import COLLISION, TARGET, ArrivalCollision
from pipeline.sim.settings import CameraSettings, SimSettings, check_vehicle, frame_steps

MODELS = ("sampled", "continuous")
TERMINATIONS = ("horizon", "target", "collision", "non_finite")
HORIZON = 0


@dataclass
class SimResult:
    """Hybrid arcs and per-agent metrics of one batched run."""

    controller: str
    x0: np.ndarray  # (N, 2) initial positions
    t: np.ndarray  # (T,)
    p: np.ndarray  # (T, N, 2) true positions
    m: np.ndarray  # (T, N, 2) perceived positions
    u: np.ndarray  # (T, N, k) plant inputs (the velocity for the single integrator; (v, ω) for the unicycle)
    q: np.ndarray  # (T, N) modes (1 for laws without modes)
    j: np.ndarray  # (T, N) jump counters
    target: np.ndarray | None  # (T, N, 2) perceived targets, moving-target runs only
    metrics: dict = field(default_factory=dict)  # name -> (N,) arrays
    heading: np.ndarray | None = None  # (T, N) true headings (a vehicle with one)
    heading_measured: np.ndarray | None = None  # (T, N) measured headings
    i: np.ndarray | None = None  # (T, N) active obstacles (SPEC §3.6; a law with cells)

    def metrics_frame(self) -> pd.DataFrame:
        """One row per agent: the columns of `metrics.csv`."""
        df = pd.DataFrame({"controller": self.controller, "x0": self.x0[:, 0], "y0": self.x0[:, 1]})
        for k, v in self.metrics.items():
            df[k] = v
        return df

    def save_npz(self, path) -> None:
        arrays = {k: getattr(self, k) for k in ("x0", "t", "p", "m", "u", "q", "j")}
        for k in ("target", "heading", "heading_measured"):
            if getattr(self, k) is not None:
                arrays[k] = getattr(self, k)
        np.savez_compressed(path, **arrays, termination=np.asarray(self.metrics["termination"]))


_SIM, _CAMERA = SimSettings(), CameraSettings()  # the defaults: conf/sim/default.yaml, conf/camera/default.yaml


def stall_threshold(sim: SimSettings, controller) -> float:
    """The stall speed of the outcome classes: `sim.stall_speed` when set, else `sim.stall_share` of the controller's
    speed limit (of 10, the default `u_max`, for a law without one): 0.25 at the defaults."""
    if sim.stall_speed is not None:
        return float(sim.stall_speed)
    u_max = getattr(controller, "u_max", None)
    return sim.stall_share * (10.0 if u_max is None else float(u_max))


def simulate(scene, controller, x0: np.ndarray, *, sim: SimSettings = _SIM, camera: CameraSettings = _CAMERA,
             disturbance=None, measure: Measure | None = None, target_fn: TargetFn | None = None,
             seed: int | np.random.Generator | None = None, record: bool = True, progress: bool = False,
             plant: Plant | None = None, heading0: np.ndarray | None = None) -> SimResult:
    """Simulate all agents of `x0` `(N, 2)` at once (see the module docstring) under the time model `sim` and the
    camera's timing `camera` (:class:`SimSettings`, :class:`CameraSettings`: checked where they are built, from the
    config or from Python; the defaults are the YAML's); `seed` (a number or a generator) replaces `sim.seed`.

    The first frame is always delivered (a vehicle starts with an estimate). Success: `|p - p_T| <= sim.delta`
    within the horizon without ever entering an obstacle; collision: `|p - c_i| < r_i` at any step.
    `sim.model='continuous'` integrates the hybrid arcs adaptively (`sim.method`, `rtol`, `atol`, `h_max`; `dt` is
    then the record grid only) and takes the true state only. `plant` (default: the single integrator) with
    `heading0` (the unicycle's initial headings). `camera.predict`: a lost frame's estimate is predicted with the
    held input (dead reckoning) instead of held. Outcome per agent (`metrics['outcome']`): `reached`, `collided`,
    `stalled` (mean speed below `sim.stall_speed` over the last `stall_time` seconds, away from the target;
    `stall_speed` None: `stall_share` of the controller's `u_max`, of 10 (the default `u_max`) when it has none) or
    `timed_out`.
    """
    dt, record_every, p_fail = sim.dt, sim.record_every, camera.p_fail
    every = frame_steps(dt, camera.period)
    plant = plant or SingleIntegrator()
    x0 = np.asarray(x0, dtype=float)
    if x0.ndim != 2 or x0.shape[1] != 2 or len(x0) == 0:
        raise ConfigError("init.points", f"initial conditions must be a non-empty (N, 2) array, got shape {x0.shape}")
    check_vehicle(plant, sim)
    c0 = plant.lift(x0, heading0)
    seed = sim.seed if seed is None else seed
    rng = seed if isinstance(seed, np.random.Generator) else np.random.default_rng(seed)
    stall = StallMonitor(len(x0), stall_threshold(sim, controller), sim.stall_time, dt)
    monitor = ArrivalCollision(scene, plant, len(x0), delta=sim.delta, stop_on_success=sim.stop_on_success,
                               stall=stall)
    if sim.model == "continuous":
        if (measure is not None and measure is not true_state) or target_fn is not None or p_fail > 0:
            raise ConfigError("sim.model", "continuous takes the true state only: a camera/perception-map "
                              "measurement, a moving target and camera failures (camera.p_fail = "
                              f"{p_fail}) are sampled per frame (use sim.model=sampled)")
        loop = ContinuousLoop(scene, controller, plant, disturbance)
        arc = solve_continuous(loop, loop.initial(c0, rng), dt=dt, n_steps=sim.n_steps, rng=rng, monitor=monitor,
                               frame_steps=None if loop.exact else every, record_every=record_every,
                               record=record, rtol=sim.rtol, atol=sim.atol, h_max=sim.h_max, method=sim.method)
        m = arc.c + arc.d["e"]
    else:
        try:  # V3 of SPEC §3.6 needs the frame period: checked here
            loop = SampledLoop(scene, controller, plant, disturbance, measure=measure, target_fn=target_fn,
                               p_fail=p_fail, dt=dt, every=every,
                               reckoning=DeadReckoning(camera.drift, camera.max_drift, camera.innovation)
                               if camera.predict else None)
        except ConfigError as err:
            raise explain_steering(plant, err) from None
        arc = solve_sampled(loop, loop.initial(c0, rng), dt=dt, n_steps=sim.n_steps, every=every, rng=rng,
                            monitor=monitor, record_every=record_every, record=record,
                            progress=f"simulate {controller.name}" if progress else None)
        m = arc.d["m"]
    return _result(scene, controller, plant, x0, arc, m, monitor, sim.delta, sim.stop_on_success)


def _result(scene, controller, plant, x0, arc, m, monitor: ArrivalCollision, delta, stop_on_success) -> SimResult:
    """Per-agent metrics from the solver's arc and the monitor, packed with the recorded arc."""
    term = arc.termination.copy()
    p = plant.position(arc.final.c)
    collided = term == COLLISION
    success = ~np.isnan(monitor.t_hit) & ~collided
    if not stop_on_success:
        term[success & (term == HORIZON)] = TARGET
    final_error = np.hypot(p[:, 0] - scene.p_T[0], p[:, 1] - scene.p_T[1])
    stalled = monitor.stall.stalled(p) & (term == HORIZON) & (final_error > delta)
    metrics = {
        "success": success,
        "collision": collided,
        "time_to_target": monitor.t_hit,
        "min_clearance": monitor.min_clearance(),
        "min_target_distance": np.sqrt(monitor.min_e2),
        "jumps": arc.jumps,
        "cell_jumps": arc.final.d.get("cell_jumps", np.zeros(len(x0), dtype=np.int64)),
        "mode_jumps": arc.final.d.get("mode_jumps", np.zeros(len(x0), dtype=np.int64)),
        "pushouts": arc.outside,
        "guard_frames": arc.counts.get("guard_frames", np.zeros(len(x0), dtype=np.int64)),
        "saturated_frames": arc.counts.get("saturated_frames", np.zeros(len(x0), dtype=np.int64)),
        **{k: arc.counts[k] for k in ("predicted_frames", "stopped_frames", "rejected_frames") if k in arc.counts},  # dead reckoning
        "path_length": arc.path,
        "final_error": final_error,
        "termination": np.asarray(TERMINATIONS)[term],
        "outcome": outcome(success, collided, stalled),
    }
    q = arc.d.get("q")
    heading = arc.c[..., 2] if plant.heading else None
    return SimResult(
        controller=controller.name, x0=x0, t=arc.t, p=arc.c[..., :2], m=m[..., :2], u=arc.w,
        q=(np.ones(arc.j.shape, dtype=np.int8) if q is None else q.astype(np.int8)), j=arc.j,
        target=arc.d.get("target"), metrics=metrics, heading=heading,
        heading_measured=m[..., 2] if plant.heading else None, i=arc.d.get("i"),
    )
