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


def solve_sampled(system: HybridSystem, x0: State, *, dt: float, n_steps: int, every: int,
                  rng: np.random.Generator, monitor: Monitor | None = None, record_every: int = 10,
                  record: bool = True, progress: str | None = None) -> Arc:
    """Integrate `n_steps` steps of `dt` with a frame every `every` steps (see the module docstring).

    `x0` is the state at `t = 0` (its first frame already taken, e.g. by `system.initial`). The run of an agent
    ends when the monitor says it entered a stop set, when its state is not finite (checked at frame ends), or
    at the horizon; a stopped agent stays where it stopped.
    """
    monitor = monitor or Monitor()
    plant = system.plant
    n = len(x0)
    x = x0.replace(c=np.array(x0.c, dtype=float))
    non_finite = len(monitor.codes) + 1
    term = np.asarray(monitor.start(x.c), dtype=np.int8).copy()
    active = term == 0
    jumps = np.zeros(n, dtype=np.int64)
    outside = np.zeros(n, dtype=np.int64)
    counts: dict[str, np.ndarray] = {}
    path = np.zeros(n)
    w = np.zeros((n, plant.inputs))
    free = plant.inputs == 0  # no held input: the plant flows freely between frames
    speed_dt = np.zeros(n)
    rec = _Recorder(system, x, w, record_rows(n_steps, record_every, record))
    if record:
        rec.store(0.0, x, w, jumps)
    t = 0.0
    steps = range(n_steps)
    if progress:
        from tqdm import tqdm

        steps = tqdm(steps, desc=progress, unit="step", leave=False)
    for step in steps:
        if step % every == 0:
            x, w, jumped, out, frame_counts = frame_update(system, x, step // every, rng, active)
            jumps += jumped
            outside += out
            for name, hit in frame_counts.items():
                counts[name] = counts.get(name, 0) + (hit & active)
            if not free:
                speed_dt = dt * plant.speed(w)  # the input is held until the next frame
        if free:
            c1 = plant.step(x.c, w, dt)
            if not active.all():
                c1[~active] = x.c[~active]  # a stopped agent stays where it stopped
            path += row_norm(plant.position(c1) - plant.position(x.c))
            x.c = c1
        else:
            x.c = plant.step(x.c, w, dt)
            path += speed_dt
        t = (step + 1) * dt
        stop = monitor.step(step, t, x.c, active)
        if stop.any():
            term[stop > 0] = stop[stop > 0]
            active &= stop == 0
        if step % every == every - 1 and not np.isfinite(x.c.sum()):
            bad = active & ~np.isfinite(x.c).all(axis=1)
            term[bad] = non_finite
            active &= ~bad
        if record and (step + 1) % record_every == 0:
            rec.store(t, x, w, jumps)
        if not active.any():
            break
    if not record or (rec.k < len(rec.t) and rec.t[rec.k - 1] != t):
        rec.store(t, x, w, jumps)  # the final state (the only one recorded without recording)
    ts, cs, ds, ws, js = rec.arrays()
    return Arc(t=ts, c=cs, d=ds, w=None if free else ws, j=js, final=x, termination=term, jumps=jumps,
               outside=outside, path=path, t_end=t, counts={k: np.asarray(v, dtype=np.int64) for k, v in counts.items()})
