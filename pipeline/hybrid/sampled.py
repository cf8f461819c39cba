"""The sampled-data solver: a frame every `every` steps of `dt`, the plant input held in between (ZOH).

At each frame `k` the solver (1) lets the system sample (`x = sample(x, k)`, from the second frame on: a
measurement is taken), (2) jumps where `x ∈ D` (at most one jump per frame; jumps have priority), (3) counts
the states left outside `C ∪ D` (where the flow map is only a fallback, SPEC §3.3), (4) holds the input
`w = input(x)`. Between frames the plant integrates the held input exactly (`plant.step`), one step of `dt`
at a time, and the monitor checks its stop sets after every step. Nothing here names a controller or a plant.

The arc length is that of the plant's position: `dt * plant.speed(w)` per step under a held input; for a plant
without input (`plant.inputs == 0`: its `step` integrates its free flow, e.g. a bouncing ball) the chord of each
exact step, and a stopped agent is no longer stepped.
"""

from __future__ import annotations

import numpy as np

from pipeline.hybrid.state import State
from pipeline.hybrid.system import Arc, HybridSystem, Monitor, record_rows, row_norm


class _Recorder:
    """The arc every `record_every` steps: `t`, the flowing state, the held input, the system's recorded arrays
    and the jump counts."""

    def __init__(self, system: HybridSystem, x: State, w: np.ndarray, rows: int):
        n = len(x)
        self.names = [k for k in system.recorded if x.d.get(k) is not None]
        self.t = np.zeros(rows)
        self.c = np.zeros((rows, *x.c.shape))
        self.w = np.zeros((rows, *w.shape))
        self.d = {k: np.zeros((rows, *x.d[k].shape), dtype=x.d[k].dtype) for k in self.names}
        self.j = np.zeros((rows, n), dtype=np.int32)
        self.k = 0

    def store(self, t: float, x: State, w: np.ndarray, jumps: np.ndarray) -> None:
        k = self.k
        self.t[k], self.c[k], self.w[k], self.j[k] = t, x.c, w, jumps
        for name in self.names:
            self.d[name][k] = x.d[name]
        self.k += 1

    def arrays(self):
        k = self.k
        return self.t[:k], self.c[:k], {n: v[:k] for n, v in self.d.items()}, self.w[:k], self.j[:k]


def frame_update(system: HybridSystem, x: State, frame: int, rng, active: np.ndarray):
    """One frame: sample, jump where `x ∈ D` (priority), count `x ∉ C ∪ D`, hold the input. Returns
    `(x, w, jumped, outside, counts)` (`counts`: the system's per-frame indicators); every agent is evaluated (the held input of a stopped agent is zeroed)."""
    if frame > 0:
        x = system.sample(x, frame, rng, active)
    jumped = system.jump_set(x)
    if jumped.any():
        x = x.where(jumped, system.jump_map(x))
    outside = ~system.flow_set(x)
    w_in = system.input(x)
    w = np.zeros((len(x), 0)) if w_in is None else np.array(w_in, dtype=float)
    if not active.all():
        w[~active] = 0.0
    return x, w, jumped, outside, system.frame_counts(x, w)


class FrameRun:
    """A batch of sampled closed loops advanced one camera frame per call: the one frame engine.

    :meth:`advance` is the frame of the module docstring (sample, jump, count, hold, then `every` steps of `dt`
    under the held input with the monitor after each step). The simulator (:func:`solve_sampled`), the
    Gymnasium environments (an agent's action as the held input) and the bracket's falsifier (an error signal
    as the measurement, exact segment checks as the monitor) all step through it. Per agent it keeps the
    termination code (`term`: 0 running or the horizon, the monitor's stop sets, then `len(monitor.codes) + 1`
    a non-finite state), `active`, the jumps, the frames outside `C ∪ D`, the system's per-frame counts and the
    arc length. An agent that enters a stop set ends its run at that step (its code and time are the step's);
    its held input is zeroed from the next frame on, as a sampled controller can only act at a frame.

    `frame`: the index of the first frame (frame 0 takes no measurement: `x0` carries it; a loop resumed at a
    later frame samples at once). `active`: the agents still running (default: those the monitor's `start`
    does not stop).
    """

    def __init__(self, system: HybridSystem, x0: State, *, dt: float, every: int, rng: np.random.Generator,
                 monitor: Monitor | None = None, frame: int = 0, active: np.ndarray | None = None):
        self.system, self.dt, self.every, self.rng = system, float(dt), int(every), rng
        self.monitor = monitor or Monitor()
        plant = system.plant
        n = len(x0)
        self.x = x0.replace(c=np.array(x0.c, dtype=float))
        self.non_finite = len(self.monitor.codes) + 1
        self.term = np.asarray(self.monitor.start(self.x.c), dtype=np.int8).copy()
        self.active = self.term == 0 if active is None else np.array(active, dtype=bool)
        self.jumps = np.zeros(n, dtype=np.int64)
        self.outside = np.zeros(n, dtype=np.int64)
        self.counts: dict[str, np.ndarray] = {}
        self.path = np.zeros(n)
        self.w = np.zeros((n, plant.inputs))
        self.free = plant.inputs == 0  # no held input: the plant flows freely between frames
        self.frame, self.steps, self.t = int(frame), 0, 0.0

    def advance(self, steps: int | None = None, on_step=None) -> np.ndarray:
        """One frame: `steps` steps of `dt` (default `every`; fewer for the horizon's last, partial frame), or
        fewer when every agent has stopped. `on_step(step, t, x)` after each step (e.g. a recorder). Returns the
        codes of the agents whose run ended in this frame `(N,)` int8 (0 elsewhere)."""
        plant, dt, active = self.system.plant, self.dt, self.active
        x, self.w, jumped, out, frame_counts = frame_update(self.system, self.x, self.frame, self.rng, active)
        self.jumps += jumped
        self.outside += out
        for name, hit in frame_counts.items():
            self.counts[name] = self.counts.get(name, 0) + (hit & active)
        speed_dt = None if self.free else dt * plant.speed(self.w)  # the input is held until the next frame
        ended = np.zeros(len(x), dtype=np.int8)
        for j in range(self.every if steps is None else steps):
            if self.free:
                c1 = plant.step(x.c, self.w, dt)
                if not active.all():
                    c1[~active] = x.c[~active]  # a stopped agent stays where it stopped
                self.path += row_norm(plant.position(c1) - plant.position(x.c))
                x.c = c1
            else:
                x.c = plant.step(x.c, self.w, dt)
                self.path += speed_dt
            step = self.steps
            self.steps, self.t = step + 1, (step + 1) * dt
            stop = self.monitor.step(step, self.t, x.c, active)
            if stop.any():
                ended[stop > 0] = stop[stop > 0]
                active &= stop == 0
            if j == self.every - 1 and not np.isfinite(x.c.sum()):
                bad = active & ~np.isfinite(x.c).all(axis=1)
                ended[bad] = self.non_finite
                active &= ~bad
            if on_step is not None:
                on_step(step, self.t, x)
            if not active.any():
                break
        self.x, self.frame = x, self.frame + 1
        self.term[ended > 0] = ended[ended > 0]
        return ended


def solve_sampled(system: HybridSystem, x0: State, *, dt: float, n_steps: int, every: int,
                  rng: np.random.Generator, monitor: Monitor | None = None, record_every: int = 10,
                  record: bool = True, progress: str | None = None) -> Arc:
    """Integrate `n_steps` steps of `dt` with a frame every `every` steps (see the module docstring), frame by
    frame through :class:`FrameRun`.

    `x0` is the state at `t = 0` (its first frame already taken, e.g. by `system.initial`). The run of an agent
    ends when the monitor says it entered a stop set, when its state is not finite (checked at frame ends), or
    at the horizon; a stopped agent stays where it stopped.
    """
    run = FrameRun(system, x0, dt=dt, every=every, rng=rng, monitor=monitor)
    rec = _Recorder(system, run.x, run.w, record_rows(n_steps, record_every, record))
    if record:
        rec.store(0.0, run.x, run.w, run.jumps)

    def store(step, t, x):
        if (step + 1) % record_every == 0:
            rec.store(t, x, run.w, run.jumps)

    bar = None
    if progress:
        from tqdm import tqdm  # progress bars only when asked for

        bar = tqdm(total=n_steps, desc=progress, unit="step", leave=False)
    while run.steps < n_steps:
        before = run.steps
        run.advance(min(every, n_steps - run.steps), store if record else None)
        if bar is not None:
            bar.update(run.steps - before)
        if not run.active.any():
            break
    if bar is not None:
        bar.close()
    x, t = run.x, run.t
    if not record or (rec.k < len(rec.t) and rec.t[rec.k - 1] != t):
        rec.store(t, x, run.w, run.jumps)  # the final state (the only one recorded without recording)
    ts, cs, ds, ws, js = rec.arrays()
    return Arc(t=ts, c=cs, d=ds, w=None if run.free else ws, j=js, final=x, termination=run.term, jumps=run.jumps,
               outside=run.outside, path=run.path, t_end=t,
               counts={k: np.asarray(v, dtype=np.int64) for k, v in run.counts.items()})
