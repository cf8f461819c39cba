"""Continuous-time hybrid arcs (`sim.model: continuous`): the paper's closed loop (Eqs. (gradient_flows1)-(jump_set1)).

The flow `p_dot = F(p + e, q)` is integrated by a batched Dormand–Prince 5(4) scheme with a step size per
agent (vectorised over agents: each pass advances every live agent by its own step). After each accepted
step the events are looked for at the step's end and located in time by bisection on the step's cubic
Hermite interpolant (the same accuracy as the step's error control):

- a jump where `(p + e, q)` enters the jump set `D` (the controller's `jump_set`, `q+ = jump_map(q)`);
  in `C ∩ D` jumps take priority (SPEC §3.3), and a jump is followed by flow;
- arrival `|p - p_T| <= delta` and collision `|p - p_0| < r`, which end the agent's run.

Disturbances: `e` is the measurement-noise process of the sampled model, drawn at the camera frames
`t_k = k camera_period` from the true state at `t_k` (gaussian: one draw per frame; alternating: the sign
of frame `k`; adversarial: `-eps sign(b(p(t_k))) e_b`) and held on `[t_k, t_{k+1})`, while the controller
is evaluated continuously on `p(t) + e_k`; at a frame the new `(p + e, q)` is tested against `D` first.
Without a disturbance no frame matters. Cameras, perception maps and camera failures are sampled-only.

Events are located on the step's cubic Hermite interpolant (its error is far below the step's own at
the default tolerances). Agents are synchronised only at the camera frames, and only when a disturbance is present; the recorded
arc (every `record_every * dt`) and the stall monitor's samples are read off each step's Hermite
interpolant, so each agent's step grows to `h_max` where the flow allows.

Methods: `rosenbrock23` (default), Shampine & Reichelt's L-stable modified Rosenbrock 2(3) (MATLAB's
`ode23s`), because the barrier makes the flow stiff where a vehicle slides along a wedge's face (normal
eigenvalue ~ -10^3 /s at u_max = 10); `dopri5`, Dormand–Prince 5(4), explicit, whose steps along a face
are bounded by stability (~2 ms), kept for comparison.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.control.controllers import Controller
from pipeline.control.scene import Scene
from pipeline.sim.disturbances import Disturbance, NoDisturbance
from pipeline.sim.metrics import StallMonitor

# Dormand–Prince 5(4) (the tableau of MATLAB's ode45 / scipy's RK45); the 7th stage is FSAL.
_C = np.array([0.0, 1 / 5, 3 / 10, 4 / 5, 8 / 9, 1.0, 1.0])
_A = [
    [],
    [1 / 5],
    [3 / 40, 9 / 40],
    [44 / 45, -56 / 15, 32 / 9],
    [19372 / 6561, -25360 / 2187, 64448 / 6561, -212 / 729],
    [9017 / 3168, -355 / 33, 46732 / 5247, 49 / 176, -5103 / 18656],
    [35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84],
]
_B5 = np.array([35 / 384, 0.0, 500 / 1113, 125 / 192, -2187 / 6784, 11 / 84, 0.0])
_B4 = np.array([5179 / 57600, 0.0, 7571 / 16695, 393 / 640, -92097 / 339200, 187 / 2100, 1 / 40])
_E = _B5 - _B4
_ROS_D, _ROS_E32 = 1.0 / (2.0 + math.sqrt(2.0)), 6.0 + math.sqrt(2.0)
METHODS = ("rosenbrock23", "dopri5")
_INSIDE = np.arange(1, 8) / 8.0  # interior points of a step near the obstacle, for the clearance
_J_REUSE = 3  # rosenbrock23: accepted steps a Jacobian is used for
_SAFETY, _GROW = 0.9, 5.0  # step-size control: safety factor, largest growth per step
_BISECT = 22  # halvings of a step when locating an event: 2.4e-7 of the step
_SAT_TOL = 1e-9  # relative: a flow value at u_max (1 - _SAT_TOL) or above is saturated


def _sq(X, c):
    """Squared distances of the rows of `X` `(k, 2)` to the point `c`."""
    dx, dy = X[:, 0] - c[0], X[:, 1] - c[1]
    return dx * dx + dy * dy


def _hermite(p0, f0, p1, f1, h, theta):
    """Cubic Hermite interpolant of a step at fractions `theta` `(k,)`."""
    t2, t3 = theta * theta, theta * theta * theta
    h00, h10, h01, h11 = 2 * t3 - 3 * t2 + 1, t3 - 2 * t2 + theta, -2 * t3 + 3 * t2, t3 - t2
    return (h00[:, None] * p0 + (h10 * h)[:, None] * f0 + h01[:, None] * p1 + (h11 * h)[:, None] * f1)


def _locate(cond, p0, f0, p1, f1, h, hi=None):
    """First fraction `theta` in (0, hi] where `cond` holds (false at 0, true at `hi`, default 1), by bisection.

    Returns `theta_hi` (cond true there) so that the event state satisfies the event's condition.
    """
    lo = np.zeros(len(h))
    hi = np.ones(len(h)) if hi is None else np.array(hi, dtype=float)
    for _ in range(_BISECT):
        mid = 0.5 * (lo + hi)
        c = cond(_hermite(p0, f0, p1, f1, h, mid))
        hi = np.where(c, mid, hi)
        lo = np.where(c, lo, mid)
    return hi


class _Grid:
    """Samples of each agent's arc at the times `k * period`, read off its steps' Hermite interpolants.

    `rows` (if given) keeps every row (the recorded arc); otherwise a ring buffer of `ring` rows.
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
            X = _hermite(p0[todo], f0[todo], p1[todo], f1[todo], h[todo], theta)
            self.a["p"][row, ag] = X
            if self.on_sample is not None:
                self.on_sample(ag, X)
            for name, val in extra.items():
                self.a[name][row, ag] = val[todo]
            k[todo] += 1
            todo = todo[k[todo] <= k_hi[todo]]
        self.next_k[idx] = k


def simulate_continuous(
    scene: Scene,
    controller: Controller,
    x0: np.ndarray,
    *,
    dt: float,
    horizon: float,
    delta: float,
    every: int,
    disturbance: Disturbance,
    rng: np.random.Generator,
    record_every: int,
    record: bool,
    stop_on_success: bool,
    stall: StallMonitor,
    rtol: float = 1e-6,
    atol: float = 1e-4,
    h_max: float = 0.25,
    method: str = "rosenbrock23",
):
    """Integrate the hybrid closed loop; returns the pieces `simulate` packs into a `SimResult`.

    `every`: steps of `dt` per camera frame. Returns `(rec, state)`: `rec` with the recorded arrays
    `t, p, m, u, q, j` and `state` with the per-agent final state and metrics.
    """
    n = len(x0)
    n_steps = int(round(horizon / dt))
    r, p0, pT = scene.obstacle_radius, scene.p_0, scene.p_T
    r2, delta2 = r * r, delta * delta
    disturbed = type(disturbance) is not NoDisturbance
    hybrid = bool(controller.hybrid)
    sync = every if disturbed else n_steps  # windows (in steps of dt): the camera frames, if they matter

    p = np.array(x0, dtype=float)
    e = disturbance(p, 0, rng, scene) if disturbed else np.zeros_like(p)
    controller.reset(p + e)
    q = (controller.q.copy() if hybrid else np.ones(n, dtype=np.int8)).astype(np.int8)
    jumps = np.zeros(n, dtype=np.int64)
    pushouts = np.zeros(n, dtype=np.int64)

    def flow(P, Q, E):
        return controller.flow_map(P + E, Q)

    def flow_pushed(P, Q, E):
        return controller.flow_map(P + E, Q, with_pushout=True)

    def err_norm(err_vec, P, P1):
        z = err_vec / (atol + rtol * np.maximum(np.abs(P), np.abs(P1)))
        return np.sqrt(0.5 * (z[:, 0] * z[:, 0] + z[:, 1] * z[:, 1]))

    def dopri5(P, F0, Q, E, H, idx):
        K = [F0]
        for i in range(1, 6):
            K.append(flow(P + H[:, None] * sum(a * K[j] for j, a in enumerate(_A[i]) if a != 0.0), Q, E))
        P1 = P + H[:, None] * sum(a * K[j] for j, a in enumerate(_A[6]) if a != 0.0)  # 5th order (row 7 = B5)
        F1, pushed = flow_pushed(P1, Q, E)
        K.append(F1)
        err_vec = H[:, None] * sum(c * K[j] for j, c in enumerate(_E) if c != 0.0)
        return P1, F1, pushed, err_norm(err_vec, P, P1), 6

    def rosenbrock23(P, F0, Q, E, H, idx):
        # J = dF/dp by forward differences (2 flow evaluations); W = I - h d J solved in closed form (2x2)
        # J is reused for up to _J_REUSE accepted steps (the formula is a W-method: second order for any J;
        # a fresh J after a rejection, a jump or a new frame keeps it close where the flow is stiff)
        stale = np.flatnonzero(J_age[idx] >= _J_REUSE)
        if stale.size:
            g = idx[stale]
            Ps, Fs = P[stale], F0[stale]
            eps = 1e-7 * np.maximum(1.0, np.abs(Ps))
            for c in range(2):
                Pc = Ps.copy()
                Pc[:, c] += eps[:, c]
                J_all[g, :, c] = (flow(Pc, Q[stale], E[stale]) - Fs) / eps[:, c : c + 1]
            J_age[g] = 0
            stats["evals"] += 2 * stale.size
        J = J_all[idx]
        hd = H * _ROS_D
        w00, w01 = 1.0 - hd * J[:, 0, 0], -hd * J[:, 0, 1]
        w10, w11 = -hd * J[:, 1, 0], 1.0 - hd * J[:, 1, 1]
        det = w00 * w11 - w01 * w10

        def solve(b):
            return np.stack([(w11 * b[:, 0] - w01 * b[:, 1]) / det, (w00 * b[:, 1] - w10 * b[:, 0]) / det], axis=1)

        k1 = solve(F0)
        F1m = flow(P + 0.5 * H[:, None] * k1, Q, E)
        k2 = solve(F1m - k1) + k1
        P1 = P + H[:, None] * k2
        F2, pushed = flow_pushed(P1, Q, E)
        k3 = solve(F2 - _ROS_E32 * (k2 - F1m) - 2.0 * (k1 - F0))
        err_vec = (H / 6.0)[:, None] * (k1 - 2.0 * k2 + k3)
        return P1, F2, pushed, err_norm(err_vec, P, P1), 2

    stepper, expo = (dopri5, 0.2) if method == "dopri5" else (rosenbrock23, 1.0 / 3.0)

    # The saturation `sat_{u_max}` makes the flow map's derivative jump where |k grad V| = u_max. An embedded
    # error estimate samples the flow at three or seven points of a step and can miss such a kink entirely
    # (the samples happen to fit a smooth curve: one start in ~200 arrived 5 ms late with h_max = 0.25). A step
    # whose ends lie on different sides of the saturation is therefore accepted only when it moves less than
    # sqrt(atol): the local error of a step of length l across a kink is O(l^2 |jump of dF/dp|).
    u_max = getattr(controller, "u_max", None)
    sat_level = None if u_max is None or not np.isfinite(u_max) else float(u_max) * (1.0 - _SAT_TOL)
    kink_len = math.sqrt(atol)

    def crosses_kink(F0, F1, H):
        if sat_level is None:
            return np.zeros(len(H), dtype=bool)
        s0 = (F0 * F0).sum(axis=1) >= sat_level * sat_level
        s1 = (F1 * F1).sum(axis=1) >= sat_level * sat_level
        return (s0 != s1) & (H * np.maximum(np.hypot(*F0.T), np.hypot(*F1.T)) > kink_len)

    active = np.ones(n, dtype=bool)
    term = np.zeros(n, dtype=np.int8)  # HORIZON
    t_hit = np.full(n, np.nan)
    t_stop = np.full(n, float(n_steps * dt))
    d2 = ((p - p0) ** 2).sum(axis=1)
    min_d2 = d2.copy()
    min_e2 = ((p - pT) ** 2).sum(axis=1)
    collided = d2 < r2
    term[collided] = 2  # COLLISION
    active &= ~collided
    t_stop[collided] = 0.0
    path = np.zeros(n)
    h_next = np.full(n, min(h_max, 0.01))
    f0 = np.zeros_like(p)
    f0_ok = np.zeros(n, dtype=bool)
    J_all = np.zeros((n, 2, 2))  # rosenbrock23: dF/dp per agent, and its age in accepted steps
    J_age = np.full(n, _J_REUSE)
    pushed_prev = np.zeros(n, dtype=bool)
    stats = {"steps": 0, "rejected": 0, "kinks": 0, "evals": 0, "passes": 0, "tries": np.zeros(n, dtype=np.int64)}

    period = record_every * dt
    n_rec = n_steps // record_every + 1 if record else 1
    rec = {"p": np.zeros((n_rec, n, 2)), "e": np.zeros((n_rec, n, 2)),
           "q": np.ones((n_rec, n), dtype=np.int8), "j": np.zeros((n_rec, n), dtype=np.int64)}
    def seen(ag, X):  # every point of the arc we look at counts for the minimum clearance
        min_d2[ag] = np.minimum(min_d2[ag], _sq(X, p0))

    grid = _Grid(period, rec, on_sample=seen) if record else None
    for key, v in (("p", p), ("e", e), ("q", q), ("j", jumps)):
        rec[key][0] = v
    stall_buf = {"p": stall.buf}
    stall_grid = _Grid(stall.period, stall_buf, ring=stall.size)
    stall.buf[0] = p

    def jump_now(idx):
        """Jumps at an instant for agents `idx` whose `(p + e, q)` lies in D (at most one each)."""
        if not hybrid or idx.size == 0:
            return
        jmp = idx[controller.jump_set(p[idx] + e[idx], q[idx])]
        if jmp.size:
            q[jmp] = controller.jump_map(q[jmp])
            jumps[jmp] += 1
            f0_ok[jmp] = False
            J_age[jmp] = _J_REUSE

    jump_now(np.flatnonzero(active))
    if record:
        rec["q"][0], rec["j"][0] = q, jumps

    n_win = -(-n_steps // sync)
    for w in range(n_win):
        s0, s1 = w * sync, min((w + 1) * sync, n_steps)
        T0, T1 = s0 * dt, s1 * dt
        if disturbed and w > 0:  # a new camera frame: new e, test D first
            e = disturbance(p, s0 // every, rng, scene)
            f0_ok[:] = False
            J_age[:] = _J_REUSE
            jump_now(np.flatnonzero(active))
        sel = np.flatnonzero(active)
        t = np.full(sel.size, T0)
        while sel.size:
            live = t < T1
            if not live.all():
                sel, t = sel[live], t[live]
                if not sel.size:
                    break
            P, Q, E = p[sel], q[sel], e[sel]
            stale = ~f0_ok[sel]
            if stale.any():
                s_idx = sel[stale]
                f0[s_idx] = flow(p[s_idx], q[s_idx], e[s_idx])
                f0_ok[s_idx] = True
                stats["evals"] += s_idx.size
            F0 = f0[sel]
            room = T1 - t
            h_prop = h_next[sel]
            clipped = h_prop >= room
            H = np.where(clipped, room, h_prop)
            P1, F1, pushed, err, ne = stepper(P, F0, Q, E, H, sel)
            stats["evals"] += ne * sel.size
            stats["passes"] += 1
            stats["tries"][sel] += 1
            kink = crosses_kink(F0, F1, H)
            ok = (err <= 1.0) & ~kink
            stats["kinks"] += int(kink.sum())
            J_age[sel] = np.where(ok, J_age[sel] + 1, _J_REUSE)
            with np.errstate(divide="ignore"):
                fac = np.clip(_SAFETY * err**-expo, 0.2, _GROW)
            fac = np.where(ok, fac, np.minimum(fac, 1.0))
            fac = np.where(kink, 0.5, fac)  # halve towards the kink, then cross it in a short step
            h_new = np.minimum(H * fac, h_max)
            # a step clipped to the window keeps its unclipped proposal for the next window
            h_next[sel] = np.where(ok & clipped, np.maximum(h_new, np.minimum(h_prop, h_max)), h_new)
            stats["steps"] += int(ok.sum())
            stats["rejected"] += int((~ok).sum())
            if not ok.any():
                continue
            a = np.flatnonzero(ok)
            ia = sel[a]
            Pa, Fa, P1a, F1a, Ha, Qa, Ea = P[a], F0[a], P1[a], F1[a], H[a], Q[a], E[a]
            # events at the step's end, located in time: collision, arrival, jump (the earliest wins)
            theta = np.ones(a.size)
            kind = np.zeros(a.size, dtype=np.int8)  # 0 none, 1 collision, 2 arrival, 3 jump
            hit_c = _sq(P1a, p0) < r2
            if hit_c.any():
                i = np.flatnonzero(hit_c)
                theta[i], kind[i] = _locate(lambda X: _sq(X, p0) < r2, Pa[i], Fa[i], P1a[i], F1a[i], Ha[i]), 1
            # the arc may pass closer than both ends: look inside steps that come near the obstacle
            d_ends = np.sqrt(np.minimum(_sq(Pa, p0), _sq(P1a, p0))) - r
            reach = (d_ends < np.hypot(*(P1a - Pa).T) + 1e-9) & ~hit_c
            inner = []
            if reach.any():
                i = np.flatnonzero(reach)
                first_in = np.full(i.size, np.inf)
                for frac in _INSIDE[::-1]:
                    X = _hermite(Pa[i], Fa[i], P1a[i], F1a[i], Ha[i], np.full(i.size, frac))
                    d2x = _sq(X, p0)
                    inner.append((i, frac, d2x))
                    first_in = np.where(d2x < r2, frac, first_in)
                grazed = np.isfinite(first_in)
                if grazed.any():  # a chord through the disc's edge: a collision inside the step
                    g = i[grazed]
                    th = _locate(lambda X: _sq(X, p0) < r2, Pa[g], Fa[g], P1a[g], F1a[g], Ha[g], first_in[grazed])
                    theta[g], kind[g] = th, 1
            hit_t = (_sq(P1a, pT) <= delta2) & (kind == 0) & np.isnan(t_hit[ia])
            if hit_t.any():
                i = np.flatnonzero(hit_t)
                th = _locate(lambda X: _sq(X, pT) <= delta2, Pa[i], Fa[i], P1a[i], F1a[i], Ha[i])
                t_hit[ia[i]] = t[a[i]] + th * Ha[i]
                if stop_on_success:
                    theta[i], kind[i] = th, 2
            if hybrid:
                jd = controller.jump_set(P1a + Ea, Qa)
                if jd.any():
                    i = np.flatnonzero(jd)
                    Ej, Qj = Ea[i], Qa[i]
                    th = _locate(lambda X, Ej=Ej, Qj=Qj: controller.jump_set(X + Ej, Qj),
                                 Pa[i], Fa[i], P1a[i], F1a[i], Ha[i])
                    earlier = th < theta[i]
                    theta[i[earlier]], kind[i[earlier]] = th[earlier], 3
            cut = kind > 0
            Pn, Fn = P1a, F1a
            if cut.any():
                i = np.flatnonzero(cut)
                Pn = P1a.copy()
                Pn[i] = _hermite(Pa[i], Fa[i], P1a[i], F1a[i], Ha[i], theta[i])
            t_a0 = t[a]
            t_a1 = t_a0 + theta * Ha
            t_a1[clipped[a] & ~cut] = T1  # exact window end
            # samples of the arc inside the step (before its event, if any)
            stall_grid.fill(ia, t_a0, t_a1, Pa, Fa, P1a, F1a, Ha, {})
            if grid is not None:
                grid.fill(ia, t_a0, t_a1, Pa, Fa, P1a, F1a, Ha, {"e": Ea, "q": Qa, "j": jumps[ia]})
            t[a] = t_a1
            # path length: the integral of the speed (trapezoid on |F|, exact at u_max); the chord for a cut step
            chord = np.hypot(*(Pn - Pa).T)
            trap = 0.5 * Ha * (np.hypot(*Fa.T) + np.hypot(*F1a.T))
            path[ia] += np.where(cut, chord, np.maximum(chord, trap))
            p[ia] = Pn
            f0[ia] = Fn
            f0_ok[ia] = ~cut
            min_d2[ia] = np.minimum(min_d2[ia], _sq(Pn, p0))
            for i, frac, d2x in inner:  # interior points of the step up to its event
                keep = frac <= theta[i]
                min_d2[ia[i[keep]]] = np.minimum(min_d2[ia[i[keep]]], d2x[keep])
            min_e2[ia] = np.minimum(min_e2[ia], _sq(Pn, pT))
            newly = pushed[a] & ~pushed_prev[ia] & ~cut
            pushouts[ia[newly]] += 1
            pushed_prev[ia] = pushed[a] & ~cut
            if cut.any():
                jc = ia[kind == 3]
                if jc.size:
                    q[jc] = controller.jump_map(q[jc])
                    jumps[jc] += 1
                    J_age[jc] = _J_REUSE
                stop = (kind == 1) | (kind == 2)
                if stop.any():
                    term[ia[kind == 1]] = 2
                    collided[ia[kind == 1]] = True
                    term[ia[kind == 2]] = 1
                    active[ia[stop]] = False
                    t_stop[ia[stop]] = t_a1[stop]
                    t[a[stop]] = np.inf  # out of the window
            bad = ~np.isfinite(Pn).all(axis=1)
            if bad.any():
                term[ia[bad]], active[ia[bad]] = 3, False
                t_stop[ia[bad]] = t_a1[bad]
                t[a[bad]] = np.inf
        if not active.any():
            break
    t_end = float(t_stop.max()) if n else 0.0
    stall.count = int(np.floor(t_end / stall.period + 1e-9)) + 1
    # the recorded arc: grid rows up to t_end, then the final state at t_end; stopped agents stay put
    if record:
        k_end = int(np.floor(t_end / period + 1e-9))
        rows = {key: v[: k_end + 1] for key, v in rec.items()}
        stopped = np.arange(k_end + 1)[:, None] >= grid.next_k[None, :]
        rows["p"] = np.where(stopped[..., None], p, rows["p"])
        rows["e"] = np.where(stopped[..., None], e, rows["e"])
        rows["q"] = np.where(stopped, q, rows["q"])
        rows["j"] = np.where(stopped, jumps, rows["j"])
        t_rec = np.arange(k_end + 1) * period
        moving = np.arange(k_end + 1)[:, None] * period < t_stop[None, :] - 1e-9
        if abs(t_rec[-1] - t_end) > 1e-9:
            t_rec = np.append(t_rec, t_end)
            for key, v in (("p", p), ("e", e), ("q", q), ("j", jumps)):
                rows[key] = np.concatenate([rows[key], v[None]])
            moving = np.concatenate([moving, np.zeros((1, n), dtype=bool)])
    else:
        t_rec = np.array([t_end])
        rows = {"p": p[None], "e": e[None], "q": q[None], "j": jumps[None]}
        moving = np.zeros((1, n), dtype=bool)
    # m and u along the recorded arc: the same flow map, zero velocity once an agent stopped
    T = len(t_rec)
    m_rec = rows["p"] + rows["e"]
    u_rec = controller.flow_map(m_rec.reshape(-1, 2), rows["q"].reshape(-1)).reshape(T, n, 2)
    u_rec[~moving] = 0.0
    controller.q, controller.jumps, controller.pushouts = q.copy(), jumps.copy(), pushouts.copy()
    state = {"p": p, "term": term, "t_hit": t_hit, "collided": collided, "min_d2": min_d2, "min_e2": min_e2,
             "path": path, "jumps": jumps, "pushouts": pushouts, "t_end": t_end, "stats": stats}
    return {"t": t_rec, "p": rows["p"], "m": m_rec, "u": u_rec, "q": rows["q"].astype(np.int8),
            "j": rows["j"].astype(np.int32)}, state
