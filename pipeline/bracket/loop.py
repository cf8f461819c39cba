"""The sampled closed loop of SPEC §3.3 frame by frame, with the error signal chosen per frame (the falsifier's plant).

Single integrator, one obstacle: between two camera frames the held velocity `u_k` moves the vehicle along the
straight segment `p_k -> p_k + T_s u_k`, so this steps one frame at a time and checks the segment exactly (the
obstacle disc, the success disc, the arena) instead of on a grid of `dt`. At frame `k`: `m_k = p_k + e_k`, jump
where the law's jump set holds (at frame 0 after `initial_state`), `u_k = hold(flow_map(m_k))` (the guard). The
same sequence as :func:`pipeline.hybrid.sampled.frame_update` (tested: the fixed adversary's frames agree with
:func:`pipeline.sim.simulate`).

A batch is a dict of arrays: `p` `(N, 2)`, `xd` the law's logic state, `t`, `outcome` (0 running, then the codes
of :data:`OUTCOMES`), `clearance` (the smallest distance to the obstacle so far) and a short position history for
the stall test.
"""

from __future__ import annotations

import numpy as np

OUTCOMES = ("running", "reached", "collided", "left_view", "stalled", "timed_out")
RUNNING, REACHED, COLLIDED, LEFT, STALLED, TIMED_OUT = range(6)


def segment_distance(p0: np.ndarray, p1: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Smallest distance from the point `c` to the segments `p0 -> p1` (rows)."""
    d = p1 - p0
    dd = np.einsum("ij,ij->i", d, d)
    with np.errstate(invalid="ignore", divide="ignore"):
        t = np.where(dd > 0, np.einsum("ij,ij->i", c - p0, d) / dd, 0.0)
    t = np.clip(t, 0.0, 1.0)
    x = p0 + t[:, None] * d
    return np.hypot(x[:, 0] - c[0], x[:, 1] - c[1])


class FrameLoop:
    """The sampled loop of a feedback law on one scene, one frame per call (see the module docstring).

    `period` the camera's frame period `T_s`, `horizon` seconds, `delta` the success radius; a run that has not
    arrived by the horizon is `stalled` when it moved less than `stall_speed * stall_time` over the last
    `stall_time` seconds (SPEC §4's outcome classes), else `timed_out`.
    """

    def __init__(self, scene, controller, *, period: float = 0.05, horizon: float = 30.0, delta: float = 1.0,
                 stall_speed: float = 0.25, stall_time: float = 5.0):
        if scene.n_obstacles != 1:
            raise ValueError("the bracket covers one obstacle (SPEC §5.5's scope)")
        self.scene, self.controller = scene, controller
        self.period, self.horizon, self.delta = float(period), float(horizon), float(delta)
        self.n_frames = int(round(horizon / period))
        self.stall_frames = max(1, int(round(stall_time / period)))
        self.stall_dist = stall_speed * stall_time
        self.p0, self.r = np.asarray(scene.p_0, float), float(scene.obstacle_radius)
        (self.x0, self.x1), (self.y0, self.y1) = scene.bounds

    # ---- the law at a perceived position ---------------------------------------------------------------------
    def decide(self, m: np.ndarray, xd: dict) -> tuple[dict, np.ndarray]:
        """The frame's jump decision at `m`: the logic state after it and the rows that jumped."""
        c = self.controller
        ev = c.evaluate(m, xd)
        jump = c.jump_set(m, xd, ev=ev)
        if not jump.any():
            return xd, jump
        new = c.jump_map(m, xd, ev=ev)
        return {k: np.where(jump, new[k], xd[k]).astype(xd[k].dtype) for k in xd}, jump

    def held(self, m: np.ndarray, xd: dict) -> np.ndarray:
        """The velocity held for one frame: the flow map at `m` through the sampled-data guard."""
        c = self.controller
        ev = c.evaluate(m, xd)
        u = c.flow_map(m, xd, ev=ev)
        return c.hold(u, m, xd, ev, self.period)[0]

    # ---- a batch of runs ------------------------------------------------------------------------------------
    def start(self, p0: np.ndarray, e0: np.ndarray) -> dict:
        """Runs from `p0` `(N, 2)` whose first frame perceives `p0 + e0` (the law's initial state there)."""
        p0 = np.array(p0, dtype=float)
        xd = self.controller.initial_state(p0 + e0)
        n = len(p0)
        hist = np.repeat(p0[None], self.stall_frames + 1, axis=0)
        st = {"p": p0, "xd": xd, "frame": 0, "outcome": np.zeros(n, np.int8), "t_end": np.full(n, np.nan),
              "clearance": np.hypot(*(p0 - self.p0).T) - self.r, "hist": hist, "jumps": np.zeros(n, np.int64)}
        st["outcome"][st["clearance"] < 0] = COLLIDED
        return st

    def step(self, st: dict, e: np.ndarray, first: bool = False) -> dict:
        """One frame with errors `e` `(N, 2)` (rows already ended stay where they ended)."""
        run = st["outcome"] == RUNNING
        m = st["p"] + e
        xd, jumped = self.decide(m, st["xd"])
        u = self.held(m, xd)
        u[~run] = 0.0
        p1 = st["p"] + self.period * u
        clear = segment_distance(st["p"], p1, self.p0) - self.r
        arrived = segment_distance(st["p"], p1, self.scene.p_T) <= self.delta
        out = st["outcome"].copy()
        t = (st["frame"] + 1) * self.period
        left = (p1[:, 0] < self.x0) | (p1[:, 0] > self.x1) | (p1[:, 1] < self.y0) | (p1[:, 1] > self.y1)
        out[run & left] = LEFT
        out[run & arrived] = REACHED
        out[run & (clear < 0)] = COLLIDED  # a segment through the obstacle is a collision, whatever else
        t_end = np.where(run & (out != RUNNING), t, st["t_end"])
        hist = np.concatenate([st["hist"][1:], p1[None]], axis=0)
        frame = st["frame"] + 1
        if frame >= self.n_frames:
            still = out == RUNNING
            moved = np.hypot(*(hist[-1] - hist[0]).T)
            out[still] = np.where(moved[still] < self.stall_dist, STALLED, TIMED_OUT)
            t_end = np.where(still, t, t_end)
        xd = {k: np.where(run, xd[k], st["xd"][k]).astype(xd[k].dtype) for k in xd}
        return {"p": np.where(run[:, None], p1, st["p"]), "xd": xd, "frame": frame, "outcome": out, "t_end": t_end,
                "clearance": np.minimum(st["clearance"], np.where(run, clear, np.inf)), "hist": hist,
                "jumps": st["jumps"] + (jumped & run)}

    @staticmethod
    def take(st: dict, idx) -> dict:
        """The runs `idx` of a batch (copies), e.g. to branch candidates."""
        out = {}
        for k, v in st.items():
            if k == "xd":
                out[k] = {n: a[idx] for n, a in v.items()}
            elif k == "hist":
                out[k] = v[:, idx]
            elif k == "frame":
                out[k] = v
            else:
                out[k] = v[idx]
        return out
