"""The paper's hybrid controller (Eqs. (gradient_flows1)-(jump_set1); SPEC §3.3), with the locally active obstacle
of SPEC §3.6 for several obstacles: logic state `(i, q)` (`i` the active obstacle, `q` its mode).

For the active obstacle `i` with covering `O_1, O_2` and potentials `V^q = V_i^q` (SPEC §3.2), at the perceived
position `m`:

- flow set `C`: `V^q(m) <= χ V^{3-q}(m)` and `dist_i(m) <= min_j dist_j(m) + h` (Eq. (flowset1); §3.6);
- flow map `F`: `u = sat(-k ∇V^q(m))` (Eq. (gradient_flows1)), `i_dot = q_dot = 0`;
- jump set `D`: a cell jump where `dist_i(m) >= min_j dist_j(m) + h`, else a mode jump where
  `V^q(m) >= (χ - λ) V^{3-q}(m)` (Eq. (jump_set1));
- jump map `G`: cell jump `i+ = argmin_j dist_j(m)`, `q+ = argmin_q V_{i+}^q(m)` (ties: `q = 1` below the line
  `b = 0`); mode jump `q+ = 3 - q` (`p+ = p`).

with `dist_j(m) = |m - c_j| - R_j` (SPEC §3.6) and the cell hysteresis `h`. With one obstacle the cell logic never
fires and this is §3.3 step for step. Sampled-data rules (SPEC §3.3): `V^q = ∞` (m outside `O_q`) jumps if
`m ∈ O_{3-q}`; `V^q = 0` (the target) never jumps; outside `C ∪ D` (inside the diamond, through perception
error only) the flow map pushes out of `W_q` along its outward normal at `push_speed`.
"""

from __future__ import annotations

import copy
import math
from typing import Annotated, Literal

import numpy as np

from pipeline.control.covering import SQRT1_2
from pipeline.control.feedback import Feedback
from pipeline.control.potentials import both_potentials_frame, fused_potentials, potential
from pipeline.control.scene import Scene
from pipeline.control.validity import cell_distance, check_field
from pipeline.errors import ConfigError
from pipeline.schema import NonNegative, OpenShare, Positive, Range, checked


class Evaluation:
    """What the four maps read at `m`, for each agent's obstacle `i` (after a cell jump where one is due).

    `a, b`: frame coordinates; `ua, ub`: the attraction `-k ∇φ` in the frame (the whole flow far from both
    wedges); `cell`: rows in the cell-jump part of `D`; `idx`: rows near the wedge of their mode (or due a cell
    jump), with `V1, V2, ga1, gb1, ga2, gb2` for them only. Far from `W_q` (`d_q >= reach^2`)
    `V^q = |p - p_T|^2 <= V^{3-q}`: no mode jump, no barrier.
    """

    __slots__ = ("i", "i_from", "q", "a", "b", "ua", "ub", "cell", "idx", "V1", "V2", "ga1", "gb1", "ga2", "gb2",
                 "c", "ea", "eb")

    def due(self, xd: dict) -> np.ndarray:
        """The rows of `xd` in the cell-jump part of `D` (after the cell jump, none: `i` is then the nearest)."""
        return self.cell & (xd["i"] == self.i_from)


def _along_face(va, vb, na, nb, limit):
    """The component of `v = (va, vb)` normal to the unit `n = (na, nb)` (along the face), scaled down to norm
    `<= limit`; and `v · n`."""
    vn = va * na + vb * nb
    ta, tb = va - vn * na, vb - vn * nb
    scale = np.minimum(1.0, limit / np.maximum(np.hypot(ta, tb), 1e-300))
    return ta * scale, tb * scale, vn


def tangent_saturate(ua: np.ndarray, ub: np.ndarray, ba: np.ndarray, bb: np.ndarray, u_max: float):
    """`v = (ua, ub)` brought to norm `<= u_max` keeping its component along the barrier's face first: with `n` the
    barrier term's direction `(ba, bb)` (the wedge's outward normal; rows where it is zero are left to the radial
    rule), `v = v_t + v_n n` becomes `u_t = v_t min(1, u_max / |v_t|)`, `u_n = sign(v_n) sqrt(u_max^2 - |u_t|^2)`.

    Still a descent direction of `V_q` (`u · v = |u_t||v_t| + |u_n||v_n| > 0` for `v != 0`) at full speed, but a
    vehicle whose perceived position enters and leaves the barrier's layer on alternate frames (the benchmark's
    noise) keeps sliding along the face at the attraction's tangential speed instead of the radial rule's, which
    shrinks the tangent by the barrier's size on every frame inside the layer (docs/dense.md)."""
    nb = np.hypot(ba, bb)
    rows = (nb > 0) & (np.hypot(ua, ub) > u_max) & np.isfinite(ua) & np.isfinite(ub)
    if not rows.any():
        return ua, ub
    ua, ub = ua.copy(), ub.copy()
    na, nbb = ba[rows] / nb[rows], bb[rows] / nb[rows]
    ta, tb, vn = _along_face(ua[rows], ub[rows], na, nbb, u_max)
    un = np.sign(vn) * np.sqrt(np.maximum(0.0, u_max * u_max - (ta * ta + tb * tb)))
    ua[rows], ub[rows] = ta + un * na, tb + un * nbb
    return ua, ub


def _with_tangent(pa, pb, ua, ub, push: float, u_max: float):
    """The push-out `p` (`|p| = push`, along the wedge's outward normal) plus the attraction's `(ua, ub)` component
    along the face, limited so that the sum stays within `u_max` (`tangent` saturation's push-out)."""
    ta, tb, _ = _along_face(ua, ub, pa / push, pb / push, math.sqrt(max(0.0, u_max * u_max - push * push)))
    return pa + ta, pb + tb


@checked("controller")
class HybridController(Feedback):
    """The hybrid controller of the paper (SPEC §3.3) over the locally active obstacle (SPEC §3.6).

    `chi > 1`, `lam in (0, chi - 1)`: the hysteresis; `cell_hysteresis` (`h > 0`): the cells' hysteresis;
    `noise_tolerance` (`θ >= 0`, null: off): the side hysteresis of docs/dense.md, sized by the perception error the
    loop must tolerate: a mode jump (the ratio rule or `m ∈ W_q`) only where the perceived position lies past the
    line `b = 0` by at least `θ` on the side the new mode passes (`q = 1 -> 2` needs `b(m) >= θ`); elsewhere in
    `W_q` the push-out rule applies. `saturation`: how `-k ∇V_q` is brought to `u_max` where a barrier acts
    (`radial`: scaled down as a whole, the paper's; `tangent`: :func:`tangent_saturate`, docs/dense.md);
    `push_tangent` (with `tangent`): a push-out also keeps the attraction's component along the face, within
    `u_max` (:func:`_with_tangent`).
    """

    name = "hybrid"
    hybrid = True
    logic = ("i", "q")

    def __init__(self, scene: Scene, k: Positive = 1.0, chi: Annotated[float, Range(gt=1)] = 1.1, lam: Positive = 0.09,
                 u_max: Positive | None = 10.0, push_speed: Positive | None = None, cell_hysteresis: Positive = 1.0,
                 guard: bool = True, guard_gamma: OpenShare = 0.5, noise_tolerance: NonNegative | None = None,
                 saturation: Literal["radial", "tangent"] = "radial", push_tangent: bool = False):
        super().__init__(scene, k=k, u_max=u_max, push_speed=push_speed)
        if not lam < chi - 1:
            raise ConfigError("controller.lam", f"must be in (0, chi - 1) = (0, {chi - 1:.6g}), got {lam!r}")
        self.chi, self.lam, self.h = float(chi), float(lam), float(cell_hysteresis)
        self.guard, self.gamma = bool(guard), float(guard_gamma)
        self.theta = None if noise_tolerance is None else float(noise_tolerance)
        if push_tangent and saturation != "tangent":
            raise ConfigError("controller.push_tangent", f"applies only with controller.saturation=tangent, got "
                                                         f"saturation={saturation!r}")
        self.saturation, self.push_tangent = saturation, bool(push_tangent)
        self.M = scene.n_obstacles
        if self.M > 1:  # SPEC §3.6's validity: V1 (every target rule), V2 (the cells), the discs in the arena
            arr = scene.arrays
            check_field(arr["center"], arr["radius"], scene.p_T, apex=arr["c"], reach=arr["reach"], h=self.h,
                        arena=scene.bounds)
        self._arr = scene.arrays
        b = scene.barrier
        self._barrier = {"kind": b.kind, "rho": float(b.rho), "gain": float(b.gain),
                         "phi_weight": 0.5 if b.kind == "authors_code" else 1.0}

    def with_hysteresis(self, chi, lam) -> HybridController:
        """This controller with the hysteresis `(chi, lam)` (the margin sweeps' variants: derived from the built
        object, not rebuilt from config); the rules of `__init__` hold. Arrays `(N,)`: a hysteresis per agent of a
        batch of `N` (several cells of a margin map in one run, each agent decided as its own cell's variant
        decides); such a variant is evaluated on its whole batch only (the sampled loop's frames, :meth:`_hysteresis`)."""
        c, v = np.asarray(chi, float), np.asarray(lam, float)
        if not (c > 1).all():
            raise ConfigError("controller.chi", f"must be > 1, got {chi!r}")
        if not ((0 < v) & (v < c - 1)).all():
            raise ConfigError("controller.lam", f"must be in (0, chi - 1) = (0, {np.min(c) - 1:.6g}), got {lam!r}")
        variant = copy.copy(self)
        variant.chi, variant.lam = (float(c), float(v)) if c.ndim == v.ndim == 0 else np.broadcast_arrays(c, v)
        return variant

    def _hysteresis(self, ev: Evaluation, n: int):
        """`(chi, lam)` at the evaluated rows `ev.idx` of a batch of `n`: the scalars, or a per-agent variant's."""
        if np.ndim(self.chi) == 0:
            return self.chi, self.lam
        if len(self.chi) != n:
            raise ValueError(f"a hysteresis per agent of {len(self.chi)} agents evaluated on {n} points: such a "
                             "variant runs on its whole batch (the sampled loop)")
        return self.chi[ev.idx], self.lam[ev.idx]

    # ---- the cells (SPEC §3.6) --------------------------------------------------------------------------
    def cell_distance(self, m: np.ndarray) -> np.ndarray:
        """`dist_j(m) = |m - c_j| - R_j` `(N, M)` (:func:`pipeline.control.validity.cell_distance`)."""
        return cell_distance(m, self._arr["center"], self._arr["R"])

    def initial_state(self, m0: np.ndarray, target=None) -> dict[str, np.ndarray]:
        """`i0 = argmin_j dist_j(m0)`, `q0` the mode with the smaller `V_{i0}^q(m0)` (ties: `q = 1` below `b = 0`)."""
        m0 = np.asarray(m0, dtype=float)
        i = np.zeros(len(m0), dtype=np.int64) if self.M == 1 else self.cell_distance(m0).argmin(axis=1)
        q = np.ones(len(m0), dtype=np.int8)
        for j in np.unique(i):
            rows = np.flatnonzero(i == j)
            cov = self.scene.covering(int(j))
            tgt = target if target is None or np.ndim(target) == 1 else np.asarray(target, float)[rows]
            V1, V2 = (potential(cov, mode, m0[rows], tgt) for mode in (1, 2))
            _, b = cov.to_frame(m0[rows])
            q[rows] = np.where(V1 < V2, 1, np.where(V2 < V1, 2, np.where(b < 0, 1, 2)))
        return {"i": i, "q": q}

    # ---- the fused evaluation ----------------------------------------------------------------------------
    def evaluate(self, m: np.ndarray, xd: dict, target=None) -> Evaluation:
        m = np.asarray(m, dtype=float)
        q, i = xd["q"], xd["i"]
        arr, ev = self._arr, Evaluation()
        if self.M > 1:
            dist = self.cell_distance(m)
            best = dist.argmin(axis=1)
            rows = np.arange(len(m))
            ev.cell = dist[rows, i] >= dist[rows, best] + self.h
            i = np.where(ev.cell, best, i)
        else:
            ev.cell = np.zeros(len(m), dtype=bool)
        ev.i_from, ev.i, ev.q = xd["i"], i, q
        p0, ea, eb = arr["center"][i], arr["e_a"][i], arr["e_b"][i]
        rx, ry = m[:, 0] - p0[:, 0], m[:, 1] - p0[:, 1]
        a = rx * ea[:, 0] + ry * ea[:, 1]
        b = rx * eb[:, 0] + ry * eb[:, 1]
        if target is None:
            at, bt = arr["target_a"][i], arr["target_b"][i]
        elif self.M == 1:
            at, bt = self.scene.covering(0).to_frame(np.broadcast_to(np.asarray(target, dtype=float), m.shape))
        else:
            d = np.broadcast_to(np.asarray(target, dtype=float), m.shape) - p0
            at, bt = np.einsum("ij,ij->i", d, ea), np.einsum("ij,ij->i", d, eb)
        w = self._barrier["phi_weight"]
        ev.a, ev.b, ev.c, ev.ea, ev.eb = a, b, arr["c"][i], ea, eb
        ev.ua = (-2.0 * w * self.k) * (a - at)
        ev.ub = (-2.0 * w * self.k) * (b - bt)
        # only agents near (or inside) the wedge W_q of their mode can jump modes or feel a barrier: with
        # d_q >= reach^2, V_q = |p - p_T|^2 <= V_{3-q}; the test below is a superset of {d_q < reach^2}
        reach = arr["reach"][i]
        sigma_b = np.where(q == 1, b, -b)
        ev.idx = idx = np.flatnonzero((ev.c - np.abs(a) + sigma_b > -math.sqrt(2.0) * reach) | ev.cell)
        if idx.size:
            with np.errstate(invalid="ignore", divide="ignore"):
                if self.M == 1:  # the single covering's own path (its target frame from the target itself)
                    tgt = target if target is None or np.ndim(target) == 1 else np.asarray(target, float)[idx]
                    pots = both_potentials_frame(self.scene.covering(0), a[idx], b[idx], tgt)
                else:
                    pots = fused_potentials(a[idx], b[idx], at[idx], bt[idx], ev.c[idx], arr["ell"][i][idx],
                                            reach[idx], **self._barrier)
            ev.V1, ev.V2, ev.ga1, ev.gb1, ev.ga2, ev.gb2 = pots
        return ev

    def check_loop(self, period: float | None) -> None:
        """V3 of SPEC §3.6 for a sampled loop with frames every `period`: the cells' gap outlasts a frame."""
        if self.M > 1 and period is not None and self.u_max is not None:
            arr = self.scene.arrays
            check_field(arr["center"], arr["radius"], self.scene.p_T, apex=arr["c"], reach=arr["reach"], h=self.h,
                        u_max=self.u_max, T_s=period)

    def covers(self, ev: Evaluation, xd_from: dict, xd: dict) -> bool:
        """Whether `ev` (made at `xd_from`) serves `xd`: same active obstacles, changed modes only where both
        modes were evaluated."""
        if not np.array_equal(ev.i, xd["i"]):
            return False
        changed = np.flatnonzero(xd["q"] != xd_from["q"])
        return changed.size == 0 or bool(np.isin(changed, ev.idx).all())

    def _ev(self, m, xd, target, ev) -> Evaluation:
        return self.evaluate(m, xd, target) if ev is None else ev

    def _modes(self, ev: Evaluation, q: np.ndarray):
        is1 = q[ev.idx] == 1
        return is1, np.where(is1, ev.V1, ev.V2), np.where(is1, ev.V2, ev.V1)

    # ---- the paper's hybrid data ------------------------------------------------------------------------
    def jump_set(self, m, xd, target=None, ev=None) -> np.ndarray:
        """Eq. (jump_set1), and the cell jump of SPEC §3.6; `V_q = inf` jumps only if `m ∈ O_{3-q}`, `V_q = 0`
        never."""
        ev = self._ev(m, xd, target, ev)
        jump = ev.due(xd)
        if ev.idx.size:
            _, Vq, Vo = self._modes(ev, xd["q"])
            chi, lam = self._hysteresis(ev, len(jump))
            with np.errstate(invalid="ignore"):
                mode = (Vq > 0) & np.isfinite(Vo) & (Vq >= (chi - lam) * Vo)
            if self.theta is not None:
                mode &= self._past_line(ev, xd["q"])
            jump[ev.idx] |= mode
        return jump

    def jump_map(self, m, xd, target=None, ev=None) -> dict[str, np.ndarray]:
        """The paper's jump map `q+ = 3 - q` (`p+ = p`); a cell jump takes `i+` and the mode with the smaller
        potential there (SPEC §3.6)."""
        ev = self._ev(m, xd, target, ev)
        q = (3 - np.asarray(xd["q"])).astype(np.int8)
        due = ev.due(xd)
        if due.any():
            rows = np.flatnonzero(due)
            pos = np.searchsorted(ev.idx, rows)  # cell rows are in idx
            V1, V2, b = ev.V1[pos], ev.V2[pos], ev.b[rows]
            q[rows] = np.where(V1 < V2, 1, np.where(V2 < V1, 2, np.where(b < 0, 1, 2)))
        return {"i": ev.i.copy(), "q": q}

    def flow_set(self, m, xd, target=None, ev=None) -> np.ndarray:
        """Eq. (flowset1) `V_q(m) <= χ V_{3-q}(m)` (`V_q` finite), and `m` within the cell of `i`."""
        ev = self._ev(m, xd, target, ev)
        inside = ~ev.due(xd)
        if ev.idx.size:
            _, Vq, Vo = self._modes(ev, xd["q"])
            chi, _ = self._hysteresis(ev, len(inside))
            with np.errstate(invalid="ignore"):
                flow = np.isfinite(Vq) & (Vq <= chi * Vo)
            if self.theta is not None:
                flow |= ~self._past_line(ev, xd["q"])
            inside[ev.idx] &= flow
        return inside

    def _past_line(self, ev: Evaluation, q: np.ndarray) -> np.ndarray:
        """For the rows `ev.idx`: the perceived position lies past `b = 0` by at least `θ` on the side of the other
        mode (`b >= θ` in mode 1, `b <= -θ` in mode 2): where the side hysteresis lets a mode jump happen."""
        b = ev.b[ev.idx]
        return np.where(q[ev.idx] == 1, b, -b) >= self.theta

    def flow_map(self, m, xd, target=None, ev=None) -> np.ndarray:
        """Eq. (gradient_flows1) `u = -k ∇V_q(m)` saturated at `u_max`; where `m ∉ O_q` (perception error
        only) SPEC §3.3's rule: leave `W_q` along the outward normal of its nearest face at `push_speed`."""
        ev = self._ev(m, xd, target, ev)
        q = np.asarray(xd["q"], dtype=np.int8)
        ua, ub = ev.ua.copy(), ev.ub.copy()
        if ev.idx.size:
            idx = ev.idx
            is1, Vq, _ = self._modes(ev, q)
            with np.errstate(invalid="ignore"):
                va = -self.k * np.where(is1, ev.ga1, ev.ga2)
                vb = -self.k * np.where(is1, ev.gb1, ev.gb2)
            bad = ~(np.isfinite(Vq) & np.isfinite(va) & np.isfinite(vb))
            if bad.any():  # m inside W_q (hence in the diamond): the outward normal of its nearest face
                a, b, c = ev.a[idx[bad]], ev.b[idx[bad]], ev.c[idx[bad]]
                sigma = np.where(q[idx[bad]] == 1, 1.0, -1.0)
                bp = c + sigma * b
                nearest_u = (bp + a) <= (bp - a)  # u <= v: cross the u = 0 face
                va[bad] = np.where(nearest_u, -SQRT1_2, SQRT1_2) * self.push_speed
                vb[bad] = -sigma * SQRT1_2 * self.push_speed
                if self.push_tangent and self.u_max is not None:
                    va[bad], vb[bad] = _with_tangent(va[bad], vb[bad], ev.ua[idx[bad]], ev.ub[idx[bad]],
                                                     self.push_speed, self.u_max)
            if self.saturation == "tangent" and self.u_max is not None:  # the barrier's part: none in push-outs
                va, vb = tangent_saturate(va, vb, np.where(bad, 0.0, va - ev.ua[idx]),
                                          np.where(bad, 0.0, vb - ev.ub[idx]), self.u_max)
            ua[idx] = va
            ub[idx] = vb
        if self.u_max is not None:
            norm = np.hypot(ua, ub)
            scale = np.minimum(1.0, self.u_max / np.maximum(norm, 1e-300))
            ua, ub = ua * scale, ub * scale
        return np.stack([ua * ev.ea[:, 0] + ub * ev.eb[:, 0], ua * ev.ea[:, 1] + ub * ev.eb[:, 1]], axis=1)

    # ---- the sampled-data guard (SPEC §3.3) ----------------------------------------------------------------
    def hold(self, u: np.ndarray, m, xd, ev: Evaluation, period: float) -> tuple[np.ndarray, np.ndarray]:
        """The velocity a sampled loop holds for `period` seconds, and the rows where the guard acted.

        With the guard (`guard: true`): `u <- u + max(0, -(1 - γ) s / T_s - n·u) n`, `s = dist(m, W_q)` the
        distance to the active mode's wedge and `n` its unit outward normal, so that `s(m + t u) >= γ s(m)` for
        `t in [0, T_s]` (s is convex along a segment): a held segment never enters the wedge. It never increases
        `|u|`, acts only within `u_max T_s / (1 - γ)` of the wedge and vanishes as `T_s -> 0`.
        """
        active = np.zeros(len(u), dtype=bool)
        if not self.guard:
            return u, active
        sigma = np.where(xd["q"] == 1, 1.0, -1.0)
        bp = ev.c + sigma * ev.b
        mu = np.minimum((bp + ev.a) * SQRT1_2, 0.0)
        mv = np.minimum((bp - ev.a) * SQRT1_2, 0.0)
        s = np.sqrt(mu * mu + mv * mv)
        near = s > 0
        if self.u_max is not None:
            near &= s < self.u_max * period / (1.0 - self.gamma)
        rows = np.flatnonzero(near)
        if rows.size == 0:
            return u, active
        na = (mu[rows] - mv[rows]) * SQRT1_2 / s[rows]  # ∇s in the frame: the outward normal of W_q
        nb = sigma[rows] * (mu[rows] + mv[rows]) * SQRT1_2 / s[rows]
        ea, eb = ev.ea[rows], ev.eb[rows]
        n = na[:, None] * ea + nb[:, None] * eb
        beta = np.maximum(0.0, -(1.0 - self.gamma) * s[rows] / period - np.einsum("ij,ij->i", n, u[rows]))
        u = u.copy()
        u[rows] += beta[:, None] * n
        active[rows] = beta > 0
        return u, active
