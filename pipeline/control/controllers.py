"""Batched feedback laws: the hybrid controller (SPEC §3.3) and the smooth/CBF baselines (SPEC §3.4).

Every controller maps perceived positions `m` `(N, 2)` to velocities `u` `(N, 2)`; per-agent state (the mode
`q` and event counters) lives in the object and is (re)initialised by `reset`. No NaN or infinite velocity
is ever returned.
"""

from __future__ import annotations

import math

import numpy as np

from pipeline.control.covering import wedge_axes, wedge_coords
from pipeline.control.potentials import (
    both_potentials_frame,
    potential,
    potential_and_grad,
    smooth_potential_grad,
)
from pipeline.control.scene import Scene
from pipeline.errors import ConfigError

_SQRT1_2 = math.sqrt(0.5)


def _positive(value, field: str, allow_none: bool = False) -> float | None:
    if value is None and allow_none:
        return None
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ConfigError(field, f"must be a number, got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ConfigError(field, f"must be > 0{' (or null for no limit)' if allow_none else ''}, got {value!r}")
    return v


def saturate(u: np.ndarray, u_max: float | None) -> np.ndarray:
    """Scale rows of `u` down to norm `u_max` (the vehicle's speed limit); `None` = no limit."""
    if u_max is None:
        return u
    norm = np.hypot(u[:, 0], u[:, 1])
    scale = np.minimum(1.0, u_max / np.maximum(norm, 1e-300))
    return u * scale[:, None]


class Controller:
    """Common interface of the feedback laws, as a hybrid system's data (the Hybrid Equations Toolbox's names).

    `flow_map(m, q)` (the velocity), `jump_map(q)`, `flow_set(m, q)` and `jump_set(m, q)` are pure functions of
    the perceived position `m` `(N, 2)` and the mode `q` `(N,)`; both simulators (`sim.model: sampled` and
    `continuous`) read the hybrid rules through them. `__call__(m, target)` is the sampled-data step: one jump
    where `(m, q)` is in the jump set (jumps take priority), then the flow map of the new mode; it updates the
    per-agent state `q` and the event counters, (re)initialised by `reset`. The smooth/CBF baselines have a
    flow map only (empty jump set).
    """

    name = "controller"
    hybrid = False

    def __init__(self, scene: Scene, k: float = 1.0, u_max: float | None = 10.0, push_speed: float | None = None):
        if not isinstance(scene, Scene):
            raise TypeError("scene must be a pipeline.control.Scene")
        self.scene = scene
        self.k = _positive(k, "controller.k")
        self.u_max = _positive(u_max, "controller.u_max", allow_none=True)
        # speed used to leave a set the controller cannot be in (u_max, or 10 units/s without a limit)
        self.push_speed = self.u_max if push_speed is None and self.u_max is not None else (push_speed or 10.0)
        self.jumps = np.zeros(0, dtype=np.int64)
        self.pushouts = np.zeros(0, dtype=np.int64)
        self.q = np.ones(0, dtype=np.int8)

    def reset(self, m0: np.ndarray, target=None) -> None:
        n = len(m0)
        self.jumps = np.zeros(n, dtype=np.int64)
        self.pushouts = np.zeros(n, dtype=np.int64)
        self.q = np.ones(n, dtype=np.int8)

    # ---- hybrid data (pure) -----------------------------------------------------------------------------
    def flow_map(self, m: np.ndarray, q: np.ndarray | None = None, target=None, with_pushout: bool = False):
        """Velocity `u = F(m, q)` `(N, 2)`, saturated at `u_max`, never NaN.

        `with_pushout=True` also returns the rows where `F` is the push-out fallback (boolean `(N,)`).
        """
        u, pushed = self._flow(np.asarray(m, dtype=float), target)
        return (u, pushed) if with_pushout else u

    def jump_map(self, q: np.ndarray) -> np.ndarray:
        """`q+ = G(q)`: the identity for a controller without modes."""
        return np.asarray(q).copy()

    def flow_set(self, m: np.ndarray, q: np.ndarray | None = None, target=None) -> np.ndarray:
        """Membership of `(m, q)` in the flow set `C` (boolean `(N,)`): everywhere for a smooth law."""
        return np.ones(len(m), dtype=bool)

    def jump_set(self, m: np.ndarray, q: np.ndarray | None = None, target=None) -> np.ndarray:
        """Membership of `(m, q)` in the jump set `D` (boolean `(N,)`): empty for a smooth law."""
        return np.zeros(len(m), dtype=bool)

    def _flow(self, m: np.ndarray, target) -> tuple[np.ndarray, np.ndarray]:  # pragma: no cover - interface
        """`(u, pushed)`: the flow map and the rows where it is the push-out fallback."""
        raise NotImplementedError

    # ---- sampled-data step --------------------------------------------------------------------------------
    def __call__(self, m: np.ndarray, target=None) -> np.ndarray:
        m = np.asarray(m, dtype=float)
        if len(self.jumps) != len(m):
            self.reset(m, target)
        u, pushed = self._flow(m, target)
        self.pushouts += pushed
        return u

    def _finalise(self, u: np.ndarray, bad: np.ndarray, fallback: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Replace rows that cannot be evaluated by `fallback * push_speed`, saturate; `(u, replaced rows)`."""
        bad = bad | ~np.isfinite(u).all(axis=1)
        if bad.any():
            u[bad] = fallback[bad] * self.push_speed
        return saturate(u, self.u_max), bad


class _HybridData:
    """`V_1, V_2` and their gradients at `m`, evaluated only where a barrier can act (the hot path).

    `a, b`: obstacle-frame coordinates; `ua, ub`: the attraction `-k ∇(-φ)` in the frame (the whole flow
    far from both wedges); `idx`: the agents near the wedge `W_q` of their mode `q`, with `V1, V2, ga1, ...`
    for them only. Far from `W_q` (`d_q >= reach^2`) `V_q = |p - p_T|^2 <= V_{3-q}`: no jump, no barrier.
    """

    __slots__ = ("a", "b", "ua", "ub", "idx", "V1", "V2", "ga1", "gb1", "ga2", "gb2")


class HybridController(Controller):
    """The perception-based hybrid controller of the paper (Eqs. (gradient_flows1)-(jump_set1); SPEC §3.3).

    Flow while `V_q(m) <= chi V_{3-q}(m)` with `u = -k ∇V_q(m)`; jump `q -> 3 - q` when
    `V_q(m) >= (chi - lam) V_{3-q}(m)` (jumps take priority in the overlap; at most one jump per sample).
    Sampled-data rules: `m ∉ O_q, m ∈ O_{3-q}` jumps (V_q = inf); `m` in neither set (inside the diamond)
    does not jump and pushes out of `W_q` along its outward normal at `push_speed`, counted in
    `pushouts`. At `V_q(m) = 0` (the target itself) there is no jump, which rules out Zeno at `p_T`.
    """

    name = "hybrid"
    hybrid = True

    def __init__(self, scene: Scene, k: float = 1.0, chi: float = 1.1, lam: float = 0.09,
                 u_max: float | None = 10.0, push_speed: float | None = None):
        super().__init__(scene, k=k, u_max=u_max, push_speed=push_speed)
        try:
            chi, lam = float(chi), float(lam)
        except (TypeError, ValueError):
            raise ConfigError("controller.chi", f"chi and lam must be numbers, got {chi!r}, {lam!r}") from None
        if not (math.isfinite(chi) and chi > 1):
            raise ConfigError("controller.chi", f"must be > 1 (hysteresis), got {chi!r}")
        if not (0 < lam < chi - 1):
            raise ConfigError("controller.lam", f"must be in (0, chi - 1) = (0, {chi - 1:.6g}), got {lam!r}")
        self.chi, self.lam = chi, lam
        self._axes = {q: wedge_axes(scene, q) for q in (1, 2)}

    def reset(self, m0: np.ndarray, target=None) -> None:
        """Initial mode: the one with the smaller `V_q` at the first measurement (ties: the side of `b`)."""
        super().reset(m0, target)
        self.q = self.initial_mode(m0, target)

    def initial_mode(self, m0: np.ndarray, target=None) -> np.ndarray:
        """The mode with the smaller `V_q(m0)` (ties: `q = 1` below the line `b = 0`), int8 `(N,)`."""
        m0 = np.asarray(m0, dtype=float)
        V1, _ = potential_and_grad(self.scene, 1, m0, target)
        V2, _ = potential_and_grad(self.scene, 2, m0, target)
        _, b = self.scene.to_frame(m0)
        return np.where(V1 < V2, 1, np.where(V2 < V1, 2, np.where(b < 0, 1, 2))).astype(np.int8)

    # ---- the paper's hybrid data ------------------------------------------------------------------------
    def flow_map(self, m: np.ndarray, q: np.ndarray, target=None, with_pushout: bool = False):
        """Eq. (gradient_flows1): `p_dot = -k ∇V_q(m)`, `q_dot = 0`, saturated at `u_max`.

        Where `m ∉ O_q` (possible through perception error only), SPEC §3.3's rule: leave `W_q` along the
        outward normal of its nearest face at `push_speed`; `with_pushout=True` also returns those rows.
        """
        q = np.asarray(q, dtype=np.int8)
        u, pushed = self._flow_data(self._data(np.asarray(m, dtype=float), q, target), q)
        return (u, pushed) if with_pushout else u

    def jump_map(self, q: np.ndarray) -> np.ndarray:
        """The paper's jump map: `p+ = p`, `q+ = 3 - q`."""
        return (3 - np.asarray(q)).astype(np.int8)

    def flow_set(self, m: np.ndarray, q: np.ndarray, target=None) -> np.ndarray:
        """Eq. (flowset1): `C = {(m, q): V_q(m) <= chi V_{3-q}(m)}` (boolean `(N,)`)."""
        m = np.asarray(m, dtype=float)
        q = np.asarray(q, dtype=np.int8)
        V = {j: potential(self.scene, j, m, target) for j in (1, 2)}
        Vq, Vo = np.where(q == 1, V[1], V[2]), np.where(q == 1, V[2], V[1])
        with np.errstate(invalid="ignore"):
            return np.isfinite(Vq) & (Vq <= self.chi * Vo)

    def jump_set(self, m: np.ndarray, q: np.ndarray, target=None) -> np.ndarray:
        """Eq. (jump_set1): `D = {(m, q): V_q(m) >= (chi - lam) V_{3-q}(m)}` (boolean `(N,)`).

        With SPEC §3.3's rules: `V_q = inf` (m outside `O_q`) jumps only if `m ∈ O_{3-q}`, and `V_q = 0`
        (the target) never jumps.
        """
        q = np.asarray(q, dtype=np.int8)
        return self._jump_data(self._data(np.asarray(m, dtype=float), q, target), q)

    # ---- batched evaluation -----------------------------------------------------------------------------
    def _data(self, m: np.ndarray, q: np.ndarray, target) -> _HybridData:
        sc = self.scene
        d = _HybridData()
        rx, ry = m[:, 0] - sc.p_0[0], m[:, 1] - sc.p_0[1]
        a = rx * sc.e_a[0] + ry * sc.e_a[1]
        b = rx * sc.e_b[0] + ry * sc.e_b[1]
        if target is None:
            at, bt = sc._target_frame
        else:
            at, bt = sc.to_frame(np.broadcast_to(np.asarray(target, dtype=float), m.shape))
        # Far from both wedges the barriers vanish, V_1 = V_2 = |p - p_T|^2: no jump, pure attraction.
        d.a, d.b = a, b
        d.ua = (-2.0 * sc.phi_weight * self.k) * (a - at)
        d.ub = (-2.0 * sc.phi_weight * self.k) * (b - bt)
        # Only agents near (or inside) the wedge W_q of their own mode can jump or feel a barrier: with
        # d_q >= reach^2, V_q = |p - p_T|^2 <= V_{3-q}. The test below is a superset of {d_q < reach^2}.
        lim = -math.sqrt(2.0) * sc.barrier_reach
        sigma_b = np.where(q == 1, b, -b)
        d.idx = idx = np.flatnonzero(sc.c - np.abs(a) + sigma_b > lim)
        if idx.size:
            tgt = target if target is None or np.ndim(target) == 1 else np.asarray(target, dtype=float)[idx]
            with np.errstate(invalid="ignore", divide="ignore"):
                d.V1, d.V2, d.ga1, d.gb1, d.ga2, d.gb2 = both_potentials_frame(sc, a[idx], b[idx], tgt)
        return d

    def _jump_data(self, d: _HybridData, q: np.ndarray) -> np.ndarray:
        jump = np.zeros(len(q), dtype=bool)
        if d.idx.size:
            is1 = q[d.idx] == 1
            Vq = np.where(is1, d.V1, d.V2)
            Vo = np.where(is1, d.V2, d.V1)
            with np.errstate(invalid="ignore"):
                jump[d.idx] = (Vq > 0) & np.isfinite(Vo) & (Vq >= (self.chi - self.lam) * Vo)
        return jump

    def _flow_data(self, d: _HybridData, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        sc = self.scene
        ua, ub = d.ua.copy(), d.ub.copy()
        pushed = np.zeros(len(q), dtype=bool)
        if d.idx.size:
            idx = d.idx
            is1 = q[idx] == 1
            with np.errstate(invalid="ignore"):
                Vq = np.where(is1, d.V1, d.V2)
                va = -self.k * np.where(is1, d.ga1, d.ga2)
                vb = -self.k * np.where(is1, d.gb1, d.gb2)
            bad = ~(np.isfinite(Vq) & np.isfinite(va) & np.isfinite(vb))
            if bad.any():
                # m inside W_q (hence in the diamond): leave W_q along the outward normal of its nearest face
                a, b = d.a[idx[bad]], d.b[idx[bad]]
                sigma = np.where(q[idx[bad]] == 1, 1.0, -1.0)
                bp = sc.c + sigma * b
                nearest_u = (bp + a) <= (bp - a)  # u <= v: cross the u = 0 face
                va[bad] = np.where(nearest_u, -_SQRT1_2, _SQRT1_2) * self.push_speed
                vb[bad] = -sigma * _SQRT1_2 * self.push_speed
                pushed[idx[bad]] = True
            ua[idx] = va
            ub[idx] = vb
        if self.u_max is not None:
            norm = np.hypot(ua, ub)
            scale = np.minimum(1.0, self.u_max / np.maximum(norm, 1e-300))
            ua, ub = ua * scale, ub * scale
        u = np.stack([ua * sc.e_a[0] + ub * sc.e_b[0], ua * sc.e_a[1] + ub * sc.e_b[1]], axis=1)
        return u, pushed

    def __call__(self, m: np.ndarray, target=None) -> np.ndarray:
        """Sampled-data step: jump where `(m, q) ∈ D` (priority), then flow with the new mode."""
        m = np.asarray(m, dtype=float)
        if len(self.q) != len(m):
            self.reset(m, target)
        d = self._data(m, self.q, target)
        jump = self._jump_data(d, self.q)
        if jump.any():
            self.q = np.where(jump, self.jump_map(self.q), self.q).astype(np.int8)
            self.jumps += jump
        u, pushed = self._flow_data(d, self.q)
        self.pushouts += pushed
        return u

    def _exit_direction(self, m: np.ndarray, q: np.ndarray) -> np.ndarray:
        """Unit outward normal of `W_q` at the nearest face, for points inside `W_q` (world frame)."""
        out = np.empty_like(m)
        for mode in (1, 2):
            sel = q == mode
            if not sel.any():
                continue
            u, v = wedge_coords(self.scene, mode, m[sel])
            du, dv = self._axes[mode]
            out[sel] = np.where((u <= v)[:, None], -du, -dv)
        return out

    @property
    def modes(self) -> np.ndarray:
        return self.q


class SmoothController(Controller):
    """Gradient flow of `V_s = |p - p_T|^2 + B(dist(p, D_2r)^2 / l_B^2)` (SPEC §3.4): the smooth baseline.

    Proposition 1: the ray behind the obstacle holds a saddle (the set K), so arbitrarily small errors stall it.
    Flow map only (Eq. (smoothfeedback)); inside the margin disc, a radial push-out at `push_speed`.
    """

    name = "smooth"

    def _flow(self, m, target):
        u = -self.k * smooth_potential_grad(self.scene, m, target)
        inside = ~np.isfinite(u).all(axis=1)
        return self._finalise(u, inside, _radial(self.scene, m))


class CBFController(Controller):
    """CBF safety filter (SPEC §3.4): `u = argmin |u - u_nom|^2 s.t. ∇h·u >= -alpha h` in closed form.

    `u_nom = -k (p - p_T)`, `h(p) = |p - p_0|^2 - (2r)^2`. Continuous, hence also subject to Proposition 1.
    """

    name = "cbf"

    def __init__(self, scene: Scene, k: float = 1.0, alpha: float = 1.0, u_max: float | None = 10.0,
                 push_speed: float | None = None):
        super().__init__(scene, k=k, u_max=u_max, push_speed=push_speed)
        self.alpha = _positive(alpha, "controller.alpha")

    def _flow(self, m, target):
        tgt = self.scene.p_T if target is None else np.asarray(target, dtype=float)
        u_nom = -self.k * (m - tgt)
        rel = m - self.scene.p_0
        h = np.einsum("ij,ij->i", rel, rel) - (2.0 * self.scene.obstacle_radius) ** 2
        gh = 2.0 * rel
        gg = np.einsum("ij,ij->i", gh, gh)
        slack = np.einsum("ij,ij->i", gh, u_nom) + self.alpha * h
        active = slack < 0
        with np.errstate(divide="ignore", invalid="ignore"):
            corr = np.where(active, -slack / gg, 0.0)
            u = u_nom + corr[:, None] * gh
        return self._finalise(u, gg <= 0, _radial(self.scene, m))


def _radial(scene: Scene, m: np.ndarray) -> np.ndarray:
    """Unit vectors from the obstacle centre (e_b at the centre itself)."""
    rel = m - scene.p_0
    norm = np.hypot(rel[:, 0], rel[:, 1])
    out = np.tile(scene.e_b, (len(m), 1))
    ok = norm > 0
    out[ok] = rel[ok] / norm[ok, None]
    return out


CONTROLLERS = {"hybrid": HybridController, "smooth": SmoothController, "cbf": CBFController}
