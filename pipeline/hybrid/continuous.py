"""The continuous-time solver: hybrid arcs of any :class:`~pipeline.hybrid.system.HybridSystem`, jumps located in time.

The flow `c_dot = F(x)` is integrated with a step size per agent (vectorised over agents: each pass advances
every live agent by its own step; `method`: `rosenbrock23`, the default, for stiff flows, or `dopri5`;
:mod:`pipeline.hybrid.steppers`). After each accepted step the events are looked for at the step's end and
located in time by bisection on the step's cubic Hermite interpolant:

- a jump where `x` enters the jump set `D` (`x+ = G(x)`; jumps take priority in `C ∩ D`, and a jump is followed
  by flow);
- entry into one of the monitor's stop sets (ends the agent's run, or only records the first entry time).

Exogenous frames (`frame_steps`: e.g. a measurement noise held per camera frame) call `system.sample` at
`t_k = k frame_steps dt`; the agents are synchronised only there, and `D` is tested first after each frame.
The recorded arc (every `record_every * dt`) and the monitor's sample grid are read off each step's
interpolant, so each agent's step grows to `h_max` where the flow allows.

A flow map with a clipped branch (`system.saturated`, e.g. a saturated velocity) has a kink: an embedded error
estimate can step over it unseen (one start in ~200 arrived 5 ms late with `h_max = 0.25`), so a step whose
ends lie on different branches is accepted only when it moves less than `sqrt(atol)` (its local error across
the kink is O(l^2 |jump of dF/dp|)).
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.hybrid.state import State
from pipeline.hybrid.steppers import dopri5_step, error_norm, hermite, jacobian, locate, rosenbrock23_step
from pipeline.hybrid.system import Arc, HybridSystem, Monitor, record_rows, row_norm

METHODS = ("rosenbrock23", "dopri5")
_INSIDE = np.arange(1, 8) / 8.0  # interior points of a step that may graze the first stop set
_J_REUSE = 3  # rosenbrock23: accepted steps a Jacobian is used for (a fresh one after a rejection, jump or frame)
_SAFETY, _GROW = 0.9, 5.0  # step-size control: safety factor, largest growth per step


class _Grid:
    """Samples of each agent's arc at the times `k * period`, read off its steps' Hermite interpolants.

    `ring` (if given) keeps a ring buffer of `ring` rows; otherwise every row (the recorded arc).
    """

    def __init__(self, period: float, arrays: dict, ring: int | None = None, on_sample=None):
        self.period, self.a, self.ring, self.on_sample = period, arrays, ring, on_sample
        n = next(iter(arrays.values())).shape[1]
        self.next_k = np.ones(n, dtype=np.int64)  # row 0 (t = 0) is written by the caller

    def fill(self, idx, t0, t1, p0, f0, p1, f1, h, extra: dict):
        """Write the rows `k` with `t0 < k * period <= t1` for agents `idx` (one step each)."""
        k_hi = np.floor(t1 / self.period + 1e-9).astype(np.int64)
        k = self.next_k[idx]
        todo = np.flatnonzero(k <= k_hi)
        while todo.size:
            kk = k[todo]
            theta = np.clip((kk * self.period - t0[todo]) / h[todo], 0.0, 1.0)
            row = kk if self.ring is None else kk % self.ring
            ag = idx[todo]
            X = hermite(p0[todo], f0[todo], p1[todo], f1[todo], h[todo], theta)
            self.a["c"][row, ag] = X
            if self.on_sample is not None:
                self.on_sample(ag, X)
            for name, val in extra.items():
                self.a[name][row, ag] = val[todo]
            k[todo] += 1
            todo = todo[k[todo] <= k_hi[todo]]
        self.next_k[idx] = k


class _Run:
    """One batched integration: per-agent solver state (step sizes, cached flow values and Jacobians)."""

    def __init__(self, system, x0, monitor, *, rtol, atol, h_max, method, record_grid, horizon):
        self.sys, self.mon = system, monitor
        # the arc length is that of the plant's position (a projection of `c`, so its rate is the projection of F)
        self.pos = system.plant.position if system.plant is not None else (lambda c: c)
        self.x = x0.replace(c=np.array(x0.c, dtype=float))
        n = len(x0)
        self.rtol, self.atol, self.h_max = rtol, atol, h_max
        self.method, self.expo = method, (0.2 if method == "dopri5" else 1.0 / 3.0)
        self.kink_len = math.sqrt(atol)
        self.term = np.asarray(monitor.start(self.x.c), dtype=np.int8).copy()
        self.active = self.term == 0
        self.t_stop = np.where(self.active, float(horizon), 0.0)
        self.first = {k: np.full(n, np.nan) for k in range(1, len(monitor.codes) + 1)}
        self.jumps = np.zeros(n, dtype=np.int64)
        self.outside = np.zeros(n, dtype=np.int64)
        self.outside_prev = np.zeros(n, dtype=bool)
        self.path = np.zeros(n)
        self.h_next = np.full(n, min(h_max, 0.01))
        self.f0 = np.zeros_like(self.x.c)
        self.f0_ok = np.zeros(n, dtype=bool)
        self.J = np.zeros((n, *self.x.c.shape[1:], *self.x.c.shape[1:]))
        self.J_age = np.full(n, _J_REUSE)
        self.stats = {"steps": 0, "rejected": 0, "kinks": 0, "evals": 0, "passes": 0,
                      "tries": np.zeros(n, dtype=np.int64)}
        self.rec_names = [k for k in system.recorded if self.x.d.get(k) is not None]
        self.grid = None
        if record_grid is not None:
            period, rows = record_grid
            arrays = {"c": np.zeros((rows, *self.x.c.shape)), "j": np.zeros((rows, n), dtype=np.int64),
                      **{k: np.zeros((rows, *self.x.d[k].shape), dtype=self.x.d[k].dtype) for k in self.rec_names}}
            self.grid = _Grid(period, arrays, on_sample=lambda ag, X: monitor.observe(ag, X, ends=False))
            arrays["c"][0], arrays["j"][0] = self.x.c, self.jumps
            for k in self.rec_names:
                arrays[k][0] = self.x.d[k]
        sg = monitor.sample_grid()
        self.sample_grid = None if sg is None else _Grid(sg[0], {"c": sg[1]}, ring=len(sg[1]))
        if sg is not None:
            sg[1][0] = self.x.c[:, : sg[1].shape[2]]

    # the flow of agents `sel` with their discrete state fixed --------------------------------------
    def flow_fn(self, xs: State):
        return lambda P: self.sys.flow_map(xs.replace(c=P))

    def jump_now(self, idx: np.ndarray) -> None:
        """Jumps at an instant for agents `idx` whose state lies in D (at most one each)."""
        if idx.size == 0:
            return
        xs = self.x.take(idx)
        jmp = self.sys.jump_set(xs)
        if jmp.any():
            j = idx[jmp]
            self.x.put(j, self.sys.jump_map(xs).take(np.flatnonzero(jmp)))
            self.jumps[j] += 1
            self.f0_ok[j] = False
            self.J_age[j] = _J_REUSE

    def step(self, sel: np.ndarray, t: np.ndarray, T1: float):
        """Try one step for agents `sel` at times `t` (clipped to the window end `T1`); returns the accepted
        rows and what the event search needs."""
        xs = self.x.take(sel)
        flow = self.flow_fn(xs)
        stale = ~self.f0_ok[sel]
        if stale.any():
            s_idx = sel[stale]
            self.f0[s_idx] = self.sys.flow_map(self.x.take(s_idx))
            self.f0_ok[s_idx] = True
            self.stats["evals"] += s_idx.size
        P, F0 = xs.c, self.f0[sel]
        room = T1 - t
        h_prop = self.h_next[sel]
        clipped = h_prop >= room
        H = np.where(clipped, room, h_prop)
        if self.method == "dopri5":
            P1, F1, err_vec, ne = dopri5_step(flow, P, F0, H)
        else:
            stale_j = np.flatnonzero(self.J_age[sel] >= _J_REUSE)
            if stale_j.size:
                g = sel[stale_j]
                sub = self.flow_fn(xs.take(stale_j))
                self.J[g] = jacobian(sub, P[stale_j], F0[stale_j])
                self.J_age[g] = 0
                self.stats["evals"] += P.shape[1] * stale_j.size
            P1, F1, err_vec, ne = rosenbrock23_step(flow, P, F0, H, self.J[sel])
        err = error_norm(err_vec, P, P1, self.rtol, self.atol)
        self.stats["evals"] += ne * sel.size
        self.stats["passes"] += 1
        self.stats["tries"][sel] += 1
        kink = self.crosses_kink(F0, F1, H)
        ok = (err <= 1.0) & ~kink
        self.stats["kinks"] += int(kink.sum())
        self.J_age[sel] = np.where(ok, self.J_age[sel] + 1, _J_REUSE)
        with np.errstate(divide="ignore"):
            fac = np.clip(_SAFETY * err**-self.expo, 0.2, _GROW)
        fac = np.where(ok, fac, np.minimum(fac, 1.0))
        fac = np.where(kink, 0.5, fac)  # halve towards the kink, then cross it in a short step
        h_new = np.minimum(H * fac, self.h_max)
        # a step clipped to the window keeps its unclipped proposal for the next window
        self.h_next[sel] = np.where(ok & clipped, np.maximum(h_new, np.minimum(h_prop, self.h_max)), h_new)
        self.stats["steps"] += int(ok.sum())
        self.stats["rejected"] += int((~ok).sum())
        a = np.flatnonzero(ok)
        return a, xs, P, F0, P1, F1, H, clipped

    def crosses_kink(self, F0, F1, H):
        s0, s1 = self.sys.saturated(F0), self.sys.saturated(F1)
        if s0 is None:
            return np.zeros(len(H), dtype=bool)
        return (s0 != s1) & (H * np.maximum(row_norm(self.pos(F0)), row_norm(self.pos(F1))) > self.kink_len)

    def events(self, ia, xa: State, Pa, Fa, P1a, F1a, Ha, t0):
        """Events inside the accepted steps: `(theta, kind, inner)`; kind 0 none, k >= 1 stop set k, -1 a jump.

        Stop sets are searched in the monitor's precedence order (a step's end inside an earlier one wins), a
        jump is taken when it comes first; `inner` holds the interior points looked at for a graze."""
        mon = self.mon
        theta = np.ones(ia.size)
        kind = np.zeros(ia.size, dtype=np.int8)
        inner = []
        for rank, code in enumerate(mon.precedence):
            cond = mon.conditions[code - 1]
            first_t = self.first[code]
            hit = cond(P1a) & (kind == 0) & (np.isnan(first_t[ia]) if rank else True)
            if hit.any():
                i = np.flatnonzero(hit)
                th = locate(cond, Pa[i], Fa[i], P1a[i], F1a[i], Ha[i])
                first_t[ia[i]] = t0[i] + th * Ha[i]
                mon.entered(code, ia[i], first_t[ia[i]])
                if mon.stops[code - 1]:
                    theta[i], kind[i] = th, code
            if rank == 0:  # the arc may pass through the first stop set between both ends of a step
                reach = mon.graze(Pa, P1a)
                if reach is not None:
                    reach &= ~hit
                if reach is not None and reach.any():
                    i = np.flatnonzero(reach)
                    first_in = np.full(i.size, np.inf)
                    for frac in _INSIDE[::-1]:
                        X = hermite(Pa[i], Fa[i], P1a[i], F1a[i], Ha[i], np.full(i.size, frac))
                        inner.append((i, frac, X))
                        first_in = np.where(cond(X), frac, first_in)
                    grazed = np.isfinite(first_in)
                    if grazed.any():  # a chord through the set's edge: an entry inside the step
                        g = i[grazed]
                        th = locate(cond, Pa[g], Fa[g], P1a[g], F1a[g], Ha[g], first_in[grazed])
                        first_t[ia[g]] = t0[g] + th * Ha[g]
                        mon.entered(code, ia[g], first_t[ia[g]])
                        theta[g], kind[g] = th, code
        x1 = xa.replace(c=P1a)
        jd = self.sys.jump_set(x1)
        outside = ~self.sys.flow_set(x1) & ~jd
        if jd.any():
            i = np.flatnonzero(jd)
            xj = xa.take(i)
            th = locate(lambda X, xj=xj: self.sys.jump_set(xj.replace(c=X)), Pa[i], Fa[i], P1a[i], F1a[i], Ha[i])
            earlier = th < theta[i]
            theta[i[earlier]], kind[i[earlier]] = th[earlier], -1
        return theta, kind, inner, outside

    def advance(self, ia, a, xa, Pa, Fa, P1a, F1a, Ha, t, clipped_a, T1):
        """Move the accepted agents to the end of their step or to its first event, and apply the events."""
        theta, kind, inner, outside = self.events(ia, xa, Pa, Fa, P1a, F1a, Ha, t[a])
        cut = kind != 0
        Pn, Fn = P1a, F1a
        if cut.any():
            i = np.flatnonzero(cut)
            Pn = P1a.copy()
            Pn[i] = hermite(Pa[i], Fa[i], P1a[i], F1a[i], Ha[i], theta[i])
        t_a0 = t[a]
        t_a1 = t_a0 + theta * Ha
        t_a1[clipped_a & ~cut] = T1  # exact window end
        if self.sample_grid is not None:
            npos = self.sample_grid.a["c"].shape[2]
            self.sample_grid.fill(ia, t_a0, t_a1, Pa[:, :npos], Fa[:, :npos], P1a[:, :npos], F1a[:, :npos], Ha, {})
        if self.grid is not None:
            extra = {k: xa.d[k] for k in self.rec_names}
            self.grid.fill(ia, t_a0, t_a1, Pa, Fa, P1a, F1a, Ha, {**extra, "j": self.jumps[ia]})
        t[a] = t_a1
        # path length: the integral of the speed (trapezoid on |F|, exact when saturated); the chord when cut
        chord = row_norm(self.pos(Pn) - self.pos(Pa))
        trap = 0.5 * Ha * (row_norm(self.pos(Fa)) + row_norm(self.pos(F1a)))
        self.path[ia] += np.where(cut, chord, np.maximum(chord, trap))
        self.x.c[ia] = Pn
        self.f0[ia] = Fn
        self.f0_ok[ia] = ~cut
        self.mon.observe(ia, Pn, ends=True)
        for i, frac, X in inner:  # interior points of the step up to its event
            keep = frac <= theta[i]
            self.mon.observe(ia[i[keep]], X[keep], ends=False)
        newly = outside & ~self.outside_prev[ia] & ~cut
        self.outside[ia[newly]] += 1
        self.outside_prev[ia] = outside & ~cut
        if cut.any():
            jc = ia[kind == -1]
            if jc.size:
                xs = self.x.take(jc)
                self.x.put(jc, self.sys.jump_map(xs))
                self.jumps[jc] += 1
                self.J_age[jc] = _J_REUSE
            stop = kind > 0
            if stop.any():
                self.term[ia[stop]] = kind[stop]
                self.active[ia[stop]] = False
                self.t_stop[ia[stop]] = t_a1[stop]
                t[a[stop]] = np.inf  # out of the window
        bad = ~np.isfinite(Pn).all(axis=1)
        if bad.any():
            self.term[ia[bad]], self.active[ia[bad]] = len(self.mon.codes) + 1, False
            self.t_stop[ia[bad]] = t_a1[bad]
            t[a[bad]] = np.inf

    def window(self, T0: float, T1: float) -> None:
        """Integrate every active agent from `T0` to `T1` (or to its stop)."""
        sel = np.flatnonzero(self.active)
        t = np.full(sel.size, T0)
        while sel.size:
            live = t < T1
            if not live.all():
                sel, t = sel[live], t[live]
                if not sel.size:
                    break
            a, xs, P, F0, P1, F1, H, clipped = self.step(sel, t, T1)
            if not a.size:
                continue
            # `t` is indexed like `sel`: `advance` moves the accepted entries `a`
            self.advance(sel[a], a, xs.take(a), P[a], F0[a], P1[a], F1[a], H[a], t, clipped[a], T1)


def solve_continuous(system: HybridSystem, x0: State, *, dt: float, n_steps: int, rng: np.random.Generator,
                     monitor: Monitor | None = None, frame_steps: int | None = None, record_every: int = 10,
                     record: bool = True, rtol: float = 1e-6, atol: float = 1e-4, h_max: float = 0.25,
                     method: str = "rosenbrock23") -> Arc:
    """Hybrid arcs of `system` from `x0` over `n_steps * dt` seconds (see the module docstring).

    `dt` is the record grid's unit only; `frame_steps` (None: no frames) the steps of `dt` between two calls of
    `system.sample`. Jumps are applied at `t = 0` where `x0 ∈ D`. Returns an :class:`Arc` recorded every
    `record_every * dt` (only the final state without `record`); a stopped agent stays where it stopped.
    """
    if method not in METHODS:
        raise ValueError(f"method must be one of {METHODS}, got {method!r}")
    monitor = monitor or Monitor()
    horizon = n_steps * dt
    period = record_every * dt
    rows = record_rows(n_steps, record_every, record)
    run = _Run(system, x0, monitor, rtol=rtol, atol=atol, h_max=h_max, method=method,
               record_grid=(period, rows) if record else None, horizon=horizon)
    run.jump_now(np.flatnonzero(run.active))
    if run.grid is not None:
        run.grid.a["j"][0] = run.jumps
        for k in run.rec_names:
            run.grid.a[k][0] = run.x.d[k]
    sync = frame_steps or n_steps
    for w in range(-(-n_steps // sync)):
        s0, s1 = w * sync, min((w + 1) * sync, n_steps)
        if frame_steps and w > 0:  # a new frame: sample, test D first
            run.x = system.sample(run.x, s0 // frame_steps, rng, run.active)
            run.f0_ok[:] = False
            run.J_age[:] = _J_REUSE
            run.jump_now(np.flatnonzero(run.active))
        run.window(s0 * dt, s1 * dt)
        if not run.active.any():
            break
    t_end = float(run.t_stop.max()) if len(x0) else 0.0
    t_rec, c_rec, d_rec, j_rec, moving = _recorded_arc(run, period, t_end, record)
    w_rec = None
    if system.plant is not None and system.plant.inputs:
        T, n = c_rec.shape[:2]
        flat = State(c_rec.reshape(T * n, -1), **{k: v.reshape(T * n, *v.shape[2:]) for k, v in d_rec.items()})
        w_in = system.input(_complete(flat, run.x, T))
        if w_in is not None:
            w_rec = np.asarray(w_in, dtype=float).reshape(T, n, -1)
            w_rec[~moving] = 0.0
    monitor.finish(t_end)
    return Arc(t=t_rec, c=c_rec, d=d_rec, w=w_rec, j=j_rec.astype(np.int32), final=run.x, termination=run.term,
               jumps=run.jumps, outside=run.outside, path=run.path, t_end=t_end, stats=run.stats)


def _complete(flat: State, final: State, T: int) -> State:
    """The recorded states with the arrays a system reads but did not record (tiled from the final state)."""
    missing = {k: np.tile(v, (T,) + (1,) * (v.ndim - 1)) for k, v in final.d.items()
               if v is not None and k not in flat.d}
    return flat.replace(**missing) if missing else flat


def _recorded_arc(run: _Run, period: float, t_end: float, record: bool):
    """Grid rows up to `t_end`, then the final state at `t_end`; a stopped agent stays where it stopped."""
    x, n = run.x, len(run.x)
    names = run.rec_names
    if record:
        g = run.grid
        k_end = int(np.floor(t_end / period + 1e-9))
        rows = {key: v[: k_end + 1] for key, v in g.a.items()}
        stopped = np.arange(k_end + 1)[:, None] >= g.next_k[None, :]
        finals = {"c": x.c, "j": run.jumps, **{k: x.d[k] for k in names}}
        for key, v in finals.items():
            mask = stopped.reshape(stopped.shape + (1,) * (rows[key].ndim - 2))
            rows[key] = np.where(mask, v, rows[key])
        t_rec = np.arange(k_end + 1) * period
        moving = np.arange(k_end + 1)[:, None] * period < run.t_stop[None, :] - 1e-9
        if abs(t_rec[-1] - t_end) > 1e-9:
            t_rec = np.append(t_rec, t_end)
            for key, v in finals.items():
                rows[key] = np.concatenate([rows[key], v[None]])
            moving = np.concatenate([moving, np.zeros((1, n), dtype=bool)])
    else:
        t_rec = np.array([t_end])
        rows = {"c": x.c[None], "j": run.jumps[None], **{k: x.d[k][None] for k in names}}
        moving = np.zeros((1, n), dtype=bool)
    return t_rec, rows["c"], {k: rows[k] for k in names}, rows["j"], moving
