"""The sampled closed loop of SPEC §3.3 frame by frame, with the error signal chosen per frame (the falsifier's plant).

Single integrator, one obstacle or several (SPEC §3.6). The loop is the simulator's own
(:class:`pipeline.sim.SampledLoop` stepped by the one frame engine :class:`pipeline.hybrid.sampled.FrameRun`), with
the falsifier's error signal as its disturbance (:class:`pipeline.sim.disturbances.Played`: `m_k = p_k + e_k`) and
one step of `dt = T_s` per frame, which is exact for the held velocity: the vehicle moves along the straight segment
`p_k -> p_k + T_s u_k`. The monitor (:class:`Segments`) checks that segment exactly (the obstacle discs, the success
disc, the arena)
instead of on a grid of `dt`. `start` takes the first frame (`m_0 = p_0 + e_0`: the law's initial state); every
`step` then samples a frame with its own error (the falsifier may choose frame 0's input error apart from the
initial state's, a stronger adversary than one measurement, covered by the certificate all the same).

A batch is a dict of arrays: `p` `(N, 2)`, `m` the last measurement, `xd` the law's logic state, `t`, `outcome`
(an :class:`pipeline.sim.metrics.Outcome`), `clearance` (the smallest distance to the obstacle so far) and
`anchor`, the stall test's reference: the position `stall_time` before the horizon (the start until then). Only the
horizon's frame reads it, so a batch carries one position per run, not a history (branching a batch of candidates,
as the falsifier does every frame, copies `(N, 2)`, not `stall_time / T_s` frames of it).
"""

from __future__ import annotations

import numpy as np

from pipeline.hybrid import Monitor, State
from pipeline.hybrid.sampled import FrameRun, frame_update
from pipeline.plants import SingleIntegrator
from pipeline.sim.closed_loop import SampledLoop
from pipeline.sim.disturbances import Played
from pipeline.sim.metrics import NAMES as OUTCOMES
from pipeline.sim.metrics import Outcome

RUNNING, REACHED, COLLIDED, LEFT, STALLED, TIMED_OUT = (Outcome.RUNNING, Outcome.REACHED, Outcome.COLLIDED,
                                                      Outcome.LEFT_VIEW, Outcome.STALLED, Outcome.TIMED_OUT)
__all__ = ["COLLIDED", "LEFT", "OUTCOMES", "REACHED", "RUNNING", "STALLED", "TIMED_OUT", "FrameLoop", "Segments"]


def segment_distance(p0: np.ndarray, p1: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest distances from the points `c` (`(K, 2)`; one point `(2,)`: `(N,)`) to the segments `p0 -> p1`
    (rows): `(N, K)`, every point in one pass."""
    c = np.asarray(c, float)
    one = c.ndim == 1
    c = c.reshape(-1, 2)
    dx, dy = p1[:, 0] - p0[:, 0], p1[:, 1] - p0[:, 1]
    dd = (dx * dx + dy * dy)[:, None]
    ox, oy = c[None, :, 0] - p0[:, 0, None], c[None, :, 1] - p0[:, 1, None]  # (N, K)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(dd > 0, (ox * dx[:, None] + oy * dy[:, None]) / dd, 0.0)
    t = np.clip(t, 0.0, 1.0)
    out = np.hypot(p0[:, 0, None] + t * dx[:, None] - c[None, :, 0], p0[:, 1, None] + t * dy[:, None] - c[None, :, 1])
    return out[:, 0] if one else out


def clearance(p: np.ndarray, scene) -> np.ndarray:
    """Distances of the points `p` `(N, 2)` to the nearest obstacle's edge (negative inside a disc)."""
    arr = scene.arrays
    return np.min([np.hypot(*(p - c).T) - r for c, r in zip(arr["center"], arr["radius"])], axis=0)


class Segments(Monitor):
    """The falsifier's exact checks on each step's straight segment: a collision where it meets an open obstacle
    disc (whatever else), an arrival where it meets the success disc, leaving the view where it ends outside the
    arena. `clear`: the last segments' distances to the nearest obstacle's edge."""

    codes = ("target", "collision", "left_view")
    stops = (True, True, True)

    def __init__(self, scene, delta: float):
        self.centres, self.radii = scene.arrays["center"], scene.arrays["radius"]
        self.pT, self.delta = scene.p_T, float(delta)
        (self.x0, self.x1), (self.y0, self.y1) = scene.bounds
        self.prev = self.clear = None

    def start(self, c):
        self.prev = np.array(c, dtype=float)
        return np.zeros(len(c), dtype=np.int8)

    def step(self, k, t, c, active):
        p, p1 = self.prev, c
        dist = segment_distance(p, p1, np.vstack([self.centres, self.pT]))  # the obstacles' centres, then the goal
        self.clear = np.min(dist[:, :-1] - self.radii, axis=1)
        arrived = dist[:, -1] <= self.delta
        left = (p1[:, 0] < self.x0) | (p1[:, 0] > self.x1) | (p1[:, 1] < self.y0) | (p1[:, 1] > self.y1)
        codes = np.zeros(len(c), dtype=np.int8)
        codes[active & left] = LEFT
        codes[active & arrived] = REACHED
        codes[active & (self.clear < 0)] = COLLIDED  # a segment through the obstacle is a collision, whatever else
        self.prev = np.array(c, dtype=float)
        return codes


class FrameLoop:
    """The sampled loop of a feedback law on one scene, one frame per call (see the module docstring).

    `period` the camera's frame period `T_s`, `horizon` seconds, `delta` the success radius; a run that has not
    arrived by the horizon is `stalled` when it moved less than `stall_speed * stall_time` over the last
    `stall_time` seconds (SPEC §4's outcome classes), else `timed_out`.
    """

    def __init__(self, scene, controller, *, period: float = 0.05, horizon: float = 30.0, delta: float = 1.0,
                 stall_speed: float = 0.25, stall_time: float = 5.0):
        self.scene, self.controller = scene, controller
        self.period, self.horizon, self.delta = float(period), float(horizon), float(delta)
        self.n_frames = int(round(horizon / period))
        self.stall_frames = max(1, int(round(stall_time / period)))
        self.stall_dist = stall_speed * stall_time
        self.error = Played()
        self.system = SampledLoop(scene, controller, SingleIntegrator(), self.error, dt=self.period, every=1)
        self.monitor = Segments(scene, delta)
        self._rng = np.random.default_rng(0)  # unused: no lost frames, the error is played

    # ---- the law at a perceived position: the engine's frame decision ----------------------------------------
    def decision(self, m: np.ndarray, xd: dict) -> tuple[dict, np.ndarray, np.ndarray]:
        """The frame's decision at the perceived points `m`: the logic state after the jump, the rows that jumped
        and the velocity held for the frame (the flow map through the sampled-data guard)."""
        x = State(np.asarray(m, float), m=np.asarray(m, float), **xd)
        x, w, jumped, *_ = frame_update(self.system, x, 0, self._rng, np.ones(len(m), dtype=bool))
        return {k: x.d[k] for k in xd}, jumped, w

    def held(self, m: np.ndarray, xd: dict) -> np.ndarray:
        """The velocity held for a frame in the logic state `xd` (no jump decided): the loop's input at `m`."""
        return self.system.input(State(np.asarray(m, float), m=np.asarray(m, float), **xd))

    def decided(self, m: np.ndarray, xd: dict) -> tuple[dict, np.ndarray]:
        """A frame perceiving `m` in the logic state `xd` (the one frame engine's step, :func:`frame_update`): its jump
        decision, then the velocity held (the logic state after the decision, which the abstraction's nodes carry,
        and the input)."""
        m = np.asarray(m, float)
        x, w, *_ = frame_update(self.system, State(m, m=m, **xd), 0, None, np.ones(len(m), bool))
        return {k: x.d[k] for k in xd}, w

    # ---- a batch of runs ------------------------------------------------------------------------------------
    def start(self, p0: np.ndarray, e0: np.ndarray) -> dict:
        """Runs from `p0` `(N, 2)` whose first frame perceives `p0 + e0` (the law's initial state there)."""
        p0 = np.array(p0, dtype=float)
        self.error.e = np.broadcast_to(np.asarray(e0, float), p0.shape)
        x = self.system.initial(p0, self._rng)
        n = len(p0)
        st = {"p": p0, "m": x.m, "xd": {k: x.d[k] for k in self.controller.logic}, "frame": 0,
              "outcome": np.zeros(n, np.int8), "t_end": np.full(n, np.nan),
              "clearance": clearance(p0, self.scene), "anchor": p0, "jumps": np.zeros(n, np.int64)}
        st["outcome"][st["clearance"] < 0] = COLLIDED
        return st

    def step(self, st: dict, e: np.ndarray) -> dict:
        """One frame with errors `e` `(N, 2)` (rows already ended stay where they ended)."""
        run = st["outcome"] == RUNNING
        self.error.e = np.asarray(e, float)
        x = State(st["p"], m=st["m"], **st["xd"])
        engine = FrameRun(self.system, x, dt=self.period, every=1, rng=self._rng, monitor=self.monitor,
                          frame=st["frame"] + 1, active=run)
        ended = engine.advance()
        p1, clear = engine.x.c, self.monitor.clear
        out = np.where(ended > 0, ended, st["outcome"]).astype(np.int8)
        t = (st["frame"] + 1) * self.period
        t_end = np.where(run & (out != RUNNING), t, st["t_end"])
        frame = st["frame"] + 1
        anchor = np.array(p1, float) if frame == self.n_frames - self.stall_frames else st["anchor"]
        if frame >= self.n_frames:
            still = out == RUNNING
            moved = np.hypot(*(p1 - anchor).T)  # over the last stall_frames frames (from the start if fewer)
            out[still] = np.where(moved[still] < self.stall_dist, STALLED, TIMED_OUT)
            t_end = np.where(still, t, t_end)
        xd = {k: np.where(run, engine.x.d[k], st["xd"][k]).astype(st["xd"][k].dtype) for k in st["xd"]}
        return {"p": np.where(run[:, None], p1, st["p"]), "m": engine.x.m, "xd": xd, "frame": frame, "outcome": out,
                "t_end": t_end, "clearance": np.minimum(st["clearance"], np.where(run, clear, np.inf)), "anchor": anchor,
                "jumps": st["jumps"] + (engine.jumps.astype(bool) & run)}

    @staticmethod
    def take(st: dict, idx) -> dict:
        """The runs `idx` of a batch (copies), e.g. to branch candidates."""
        out = {}
        for k, v in st.items():
            if k == "xd":
                out[k] = {n: a[idx] for n, a in v.items()}
            elif k == "frame":
                out[k] = v
            else:
                out[k] = v[idx]
        return out
