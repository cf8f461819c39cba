"""The closed loop of the paper as one hybrid system: plant, feedback law and measurement (SPEC §1, §3.3).

State `x = (c, i, q, m, target, e)`: `c` the plant's state (position, and heading for a unicycle), `(i, q)` the
feedback law's logic variables, `m` the measurement the law reads, `target` a perceived moving target (SPEC §4,
else None). The four maps are the law's, read at the steered point of the measurement:

    F(x) = plant.flow(c, plant.actuate(m, κ(point(m), i, q)))      flow while x ∈ C = C_κ(point(m), i, q)
    G(x) = (c, G_κ(point(m), i, q), m)                            jump when  x ∈ D = D_κ(point(m), i, q)

- :class:`SampledLoop` (`sim.model: sampled`): `m` is held between camera frames; at a frame (`sample`) the
  camera (or the true state) and the disturbance give a new `m`, lost with probability `p_fail` (the last
  estimate is held; a measurement hook may also return NaN rows, held alike); with dead reckoning
  (:class:`DeadReckoning`, `camera.predict`) a lost frame's estimate is predicted with the vehicle's own held
  input instead, `m <- plant.step(m, w, T_s)` (`m + T_s u` for the single integrator);
- :class:`ContinuousLoop` (`sim.model: continuous`): `m = c + e` along the flow, the disturbance `e` drawn at the
  frames from the true state and held (true state only: no camera, no failures).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from pipeline.hybrid import HybridSystem, State
from pipeline.hybrid.system import row_norm
from pipeline.sim.disturbances import NoDisturbance

# measure(c_true (n, dim), idx (n,), frame, rng) -> measured states (n, dim), before the disturbance
Measure = Callable[[np.ndarray, np.ndarray, int, np.random.Generator], np.ndarray]
# target_fn(t, frame, p_true (n, 2), idx (n,), rng) -> perceived (moving) targets (n, 2)
TargetFn = Callable[[float, int, np.ndarray, np.ndarray, np.random.Generator], np.ndarray]


def true_state(c: np.ndarray, idx: np.ndarray, frame: int, rng: np.random.Generator) -> np.ndarray:
    """Measurement without a camera: the true state (a disturbance is added on top)."""
    return c.copy()


def _hold(new: np.ndarray, last: np.ndarray) -> np.ndarray:
    """NaN rows of a measurement are failed frames (e.g. gated by the map's own predicted error): the last
    estimate is held for those agents, as for `p_fail`."""
    bad = np.isnan(new).any(axis=1)
    if bad.any():
        new = np.array(new, dtype=float)
        new[bad] = last[bad]
    return new


@dataclass(frozen=True)
class DeadReckoning:
    """A lost frame's estimate predicted with the vehicle's own input held over the frame, `m <- plant.step(m, w,
    T_s)` (`p_hat <- p_hat + T_s u`), instead of held. Its uncertainty `r` grows by `drift` per unit of distance
    predicted (the odometry's error) and is 0 after a frame is used; past `max_drift` the vehicle stops (input 0)
    until a frame is used again: it no longer knows well enough where it is to move (docs/attacks.md).

    `innovation` (world units; None: off): a delivered frame whose position is farther than `innovation + r` from
    the prediction contradicts the vehicle's own motion and is not used (a *rejected* frame, lost like a gated
    one); it is kept as a *candidate*, predicted alike, and the vehicle stops while one is pending. The next frame
    within `innovation + r` of the prediction is used (the candidate was the outlier), or, within `innovation` of
    the candidate, it is used instead (two frames agree against the prediction: the estimate was the outlier, it
    is re-localised). Two frames within `ε` of the truth never differ by more than `2 ε` (the prediction carries
    the last used frame's error), so a loop whose used frames err by at most `innovation / 2` rejects none."""

    drift: float = 0.1
    max_drift: float = 2.0
    innovation: float | None = None


def _counters(n: int) -> dict[str, np.ndarray]:
    """Jump counters by kind: logic variables that the jump map increments."""
    return {"cell_jumps": np.zeros(n, dtype=np.int64), "mode_jumps": np.zeros(n, dtype=np.int64)}


class _Loop(HybridSystem):
    """What both time models share: the four maps of the feedback law at the measured point."""

    recorded = ("m", "q", "i", "target")

    def __init__(self, scene, controller, plant, disturbance):
        self.scene, self.controller, self.plant, self.disturbance = scene, controller, plant, disturbance
        self.exact = disturbance is None or isinstance(disturbance, NoDisturbance)
        self._memo = None

    def measured(self, x: State) -> np.ndarray:  # pragma: no cover - interface
        raise NotImplementedError

    def _logic(self, x: State) -> dict:
        return {k: x.d[k] for k in self.controller.logic}

    def _disturb(self, c: np.ndarray, frame: int, rng, idx: np.ndarray | None = None) -> np.ndarray:
        """The disturbance on the position part of a measured state (SPEC §3.5); `idx`: the agents of `c` in the
        batch, where only some are measured (a per-agent disturbance reads it)."""
        args = (idx,) if idx is not None and getattr(self.disturbance, "per_agent", False) else ()
        e = self.disturbance(self.plant.position(c), frame, rng, self.scene, *args)
        if c.shape[1] == 2:
            return e
        return np.column_stack([e, np.zeros((len(c), c.shape[1] - 2))])

    def _evaluation(self, x: State):
        """The law's evaluation at `x` (memo: the last state, or a state with the same held measurement whose
        logic state the evaluation covers, e.g. the state after this frame's jump)."""
        if self._memo is not None:
            x_ref, m_ref, xd_ref, point, ev = self._memo
            if x is x_ref:
                return point, ev
            if m_ref is not None and x.d.get("m") is m_ref and self.controller.covers(ev, xd_ref, self._logic(x)):
                self._memo = (x, m_ref, self._logic(x), point, ev)
                return point, ev
        point = self.plant.point(self.measured(x))
        xd = self._logic(x)
        ev = self.controller.evaluate(point, xd, x.d.get("target"))
        self._memo = (x, x.d.get("m"), xd, point, ev)
        return point, ev

    def _law(self, x: State):
        point, ev = self._evaluation(x)
        return point, self._logic(x), x.d.get("target"), ev

    def input(self, x):
        point, xd, target, ev = self._law(x)
        return self.plant.actuate(self.measured(x), self.controller.flow_map(point, xd, target, ev=ev))

    def jump_set(self, x):
        point, xd, target, ev = self._law(x)
        return self.controller.jump_set(point, xd, target, ev=ev)

    def jump_map(self, x):
        """`G`: the law's jump; a change of the active obstacle counts as a cell jump, else as a mode jump."""
        point, xd, target, ev = self._law(x)
        new = self.controller.jump_map(point, xd, target, ev=ev)
        cell = new["i"] != xd["i"] if "i" in new else np.zeros(len(x), dtype=bool)
        counts = {k: x.d.get(k, np.zeros(len(x), dtype=np.int64)) for k in ("cell_jumps", "mode_jumps")}
        return x.replace(**new, cell_jumps=counts["cell_jumps"] + cell, mode_jumps=counts["mode_jumps"] + ~cell)

    def flow_set(self, x):
        point, xd, target, ev = self._law(x)
        return self.controller.flow_set(point, xd, target, ev=ev)

    def saturated(self, flow):
        u_max = getattr(self.controller, "u_max", None)
        if u_max is None or not np.isfinite(u_max) or self.plant.dim != 2:
            return None
        level = float(u_max) * (1.0 - 1e-9)
        return (flow * flow).sum(axis=1) >= level * level


class SampledLoop(_Loop):
    """The camera in the loop: `m` held between frames, a frame every `every` steps of `dt`; the velocity held for
    a frame is the law's through its sampled-data guard (SPEC §3.3, `controller.guard`)."""

    def __init__(self, scene, controller, plant, disturbance=None, *, measure: Measure | None = None,
                 target_fn: TargetFn | None = None, p_fail: float = 0.0, dt: float = 0.01, every: int = 1,
                 reckoning: DeadReckoning | None = None):
        super().__init__(scene, controller, plant, disturbance)
        self.measure = measure or true_state
        self.target_fn, self.p_fail, self.dt, self.every = target_fn, float(p_fail), dt, every
        self.reckoning = reckoning
        self.period = every * dt
        controller.check_loop(self.period)
        self._guarded = (None, None)
        self._held = None  # the input held over the last frame (dead reckoning predicts the estimate with it)
        self._commanded: list[np.ndarray] = []  # the last commands, newest first (`plant.smoothing`)

    def input(self, x):
        point, xd, target, ev = self._law(x)
        u = self.controller.flow_map(point, xd, target, ev=ev)
        u, guarded = self.controller.hold(u, point, xd, ev, self.period)
        self._guarded = (x, guarded)
        w = self.plant.actuate(self.measured(x), self._smoothed(u))
        if self.reckoning is not None:
            w = np.where(self._stopped(x)[:, None], 0.0, w)  # the fallback: stop
            self._held = w
        return w

    def _stopped(self, x) -> np.ndarray:
        """Dead reckoning's stop: the estimate's uncertainty past `max_drift`, or a rejected frame pending."""
        stop = x.drift > self.reckoning.max_drift
        return stop | ~np.isnan(x.candidate[:, 0]) if self.reckoning.innovation is not None else stop

    def _smoothed(self, u: np.ndarray) -> np.ndarray:
        """The mean of this frame's command and the `plant.smoothing - 1` before it (fewer at a run's start): one
        call per frame (:func:`pipeline.hybrid.sampled.frame_update`), the history reset by :meth:`initial`."""
        k = self.plant.smoothing
        if k == 1:
            return u
        self._commanded = [np.array(u, dtype=float)] + self._commanded[: k - 1]
        return sum(self._commanded) / len(self._commanded)

    def frame_counts(self, x, w) -> dict[str, np.ndarray]:
        """Per frame: the guard acted (SPEC §3.3), the vehicle's input was clipped (the unicycle's |ω|); with dead
        reckoning, the estimate was predicted, the vehicle stopped (its uncertainty past `max_drift`)."""
        guarded = self._guarded[1] if self._guarded[0] is x else np.zeros(len(x), dtype=bool)
        counts = {"guard_frames": guarded, "saturated_frames": self.plant.saturated(w)}
        if self.reckoning is not None:
            counts |= {"predicted_frames": x.predicted, "stopped_frames": self._stopped(x)}
            if self.reckoning.innovation is not None:
                counts["rejected_frames"] = x.rejected
        return counts

    def measured(self, x):
        return x.m

    def _perceive(self, c, idx, frame, rng):
        m = self.measure(c, idx, frame, rng)
        return m if self.exact else m + self._disturb(c, frame, rng, idx)

    def initial(self, c0, rng):
        """The first frame (always delivered: a vehicle starts with an estimate) and the law's initial state."""
        c0 = np.array(c0, dtype=float)
        self._commanded = []  # a new run: no commands before its first frame
        all_idx = np.arange(len(c0))
        m = self._perceive(c0, all_idx, 0, rng)
        target = None
        if self.target_fn is not None:
            target = np.asarray(self.target_fn(0.0, 0, self.plant.position(c0), all_idx, rng), dtype=float)
        xd = self.controller.initial_state(self.plant.point(m), target)
        reckon = {} if self.reckoning is None else {"drift": np.zeros(len(c0)), "predicted": np.zeros(len(c0), bool)}
        if self.reckoning is not None and self.reckoning.innovation is not None:
            reckon |= {"candidate": np.full_like(c0, np.nan), "rejected": np.zeros(len(c0), bool)}
        return State(c0, m=m, target=target, **xd, **_counters(len(c0)), **reckon)

    def sample(self, x, frame, rng, active):
        n = len(x)
        fresh = active & (rng.random(n) >= self.p_fail) if self.p_fail > 0 else active
        t = (frame * self.every) * self.dt
        target = x.d.get("target")
        prior = x.m if self.reckoning is None else self.plant.step(x.m, np.where(active[:, None], self._held, 0.0),
                                                                   self.period)
        m, used = prior, np.zeros(n, dtype=bool)
        if fresh.all():
            idx = np.arange(n)
            new = self._perceive(x.c, idx, frame, rng)
            m, used = _hold(new, prior), ~np.isnan(new).any(axis=1)
            if self.target_fn is not None:
                target = _hold(np.asarray(self.target_fn(t, frame, self.plant.position(x.c), idx, rng), float), target)
        elif fresh.any():
            idx = np.flatnonzero(fresh)
            new = self._perceive(x.c[idx], idx, frame, rng)
            m = prior.copy()
            m[idx] = _hold(new, prior[idx])
            used[idx] = ~np.isnan(new).any(axis=1)
            if self.target_fn is not None:
                target = target.copy()
                target[idx] = _hold(np.asarray(self.target_fn(t, frame, self.plant.position(x.c[idx]), idx, rng),
                                               float), target[idx])
        if self.reckoning is None:
            return x.replace(m=m, target=target)
        moved = row_norm(self.plant.position(prior) - self.plant.position(x.m))
        r = x.drift + self.reckoning.drift * moved
        checked = {}
        if self.reckoning.innovation is not None:
            m, used, checked = self._innovation(x, prior, m, used, r, active)
        return x.replace(m=m, target=target, drift=np.where(used, 0.0, r), predicted=~used & active, **checked)

    def _innovation(self, x, prior, m, used, r, active):
        """:class:`DeadReckoning`'s `innovation` check of the frames about to be used: `(m, used, state)`."""
        pos, limit = self.plant.position, self.reckoning.innovation
        candidate = self.plant.step(x.candidate, np.where(active[:, None], self._held, 0.0), self.period)
        with np.errstate(invalid="ignore"):  # NaN rows: no candidate (never within reach)
            ok = (row_norm(pos(m) - pos(prior)) <= limit + r) | (row_norm(pos(m) - pos(candidate)) <= limit)
        rejected = used & ~ok
        candidate = np.where(rejected[:, None], m, np.where((used & ok)[:, None], np.nan, candidate))
        m = np.where(rejected[:, None], prior, m)
        return m, used & ok, {"candidate": candidate, "rejected": rejected}


class ContinuousLoop(_Loop):
    """The paper's continuous-time closed loop: `m = c + e(t_k)` along the flow (true state, held disturbance)."""

    recorded = ("e", "q", "i")

    def measured(self, x):
        return x.c + x.e

    def initial(self, c0, rng):
        c0 = np.array(c0, dtype=float)
        e = np.zeros_like(c0) if self.exact else self._disturb(c0, 0, rng)
        xd = self.controller.initial_state(self.plant.point(c0 + e))
        return State(c0, e=e, **xd, **_counters(len(c0)))

    def sample(self, x, frame, rng, active):
        return x.replace(e=self._disturb(x.c, frame, rng))
