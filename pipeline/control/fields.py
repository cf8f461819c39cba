"""Several-obstacle fields (SPEC §3.6): seeded random valid fields drawn by rejection against V1–V3, the named
fields (the authors' 12-disc field, two discs in a row), and the analysis of which apex / barrier settings make
a field valid."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from pipeline.control.scene import Arena, Barrier, Obstacle, Scene
from pipeline.control.validity import (
    ARENA_FIELD,
    DEFAULT_APEX_FACTOR,
    DEFAULT_ARENA,
    DEFAULT_BARRIER_RHO,
    OBSTACLES_FIELD,
    RANDOM_FIELD,
    SQRT2,
    STARTS_FIELD,
    TARGET_FIELD,
    arena_box,
    as_points,
    barrier_reach,
    diamond_signed_distance,
    field_geometry,
    field_violations,
    fmt,
    loop_params,
    positive,
    to_frames,
)
from pipeline.errors import ConfigError
from pipeline.schema import NonNegative


def random_field(
    n_obstacles: int,
    *,
    seed: int,
    arena=DEFAULT_ARENA,
    radius_range: tuple[float, float] = (2.0, 4.0),
    target=(40.0, 0.0),
    starts=None,
    start_clearance: float | None = None,
    h: float = 1.0,
    u_max: float | None = 10.0,
    T_s: float | None = 0.05,
    apex_factor: float = DEFAULT_APEX_FACTOR,
    barrier_rho: float = DEFAULT_BARRIER_RHO,
    barrier_scale_factor: float = 1.0,
    inflation: float = 0.0,
    margin: float = 0.0,
    batch: int = 256,
    batches_per_obstacle: int = 8,
    max_restarts: int = 25,
) -> tuple[np.ndarray, np.ndarray]:
    """A seeded random field valid under SPEC §3.6: `(centers (M, 2), radii (M,))`.

    Radii are uniform in `radius_range`; apex `c^a_i = apex_factor (r_i + inflation)`, barrier scale
    `l_i = barrier_scale_factor (r_i + inflation)`, reach `sqrt(barrier_rho) l_i`. Each obstacle in turn is the
    first of a batch of `batch` candidates (centres uniform over the arena shrunk by `r + margin`) that passes
    V1, the start condition and V2/V3 against the obstacles already placed; after `batches_per_obstacle` empty
    batches the field is redrawn from scratch, at most `max_restarts` times, then ConfigError. Deterministic
    in `seed`; the result is checked with `field_violations` (same `margin`)."""
    M = int(n_obstacles)
    if M < 1 or M != n_obstacles:
        raise ConfigError(f"{RANDOM_FIELD}.n_obstacles", f"must be an integer >= 1, got {n_obstacles!r}")
    box = arena_box(arena)
    if box is None:
        raise ConfigError(ARENA_FIELD, "random_field needs an arena")
    r_lo, r_hi = (float(x) for x in radius_range)
    if not (0 < r_lo <= r_hi and math.isfinite(r_hi)):
        raise ConfigError(f"{RANDOM_FIELD}.radius_range", f"must be 0 < r_min <= r_max, got {radius_range!r}")
    if not apex_factor > SQRT2:
        raise ConfigError(f"{RANDOM_FIELD}.apex_factor", f"must exceed sqrt(2) (the diamond must contain the disc), got {apex_factor!r}")
    rho_b = positive(barrier_rho, f"{RANDOM_FIELD}.barrier.rho")
    scale_f = positive(barrier_scale_factor, f"{RANDOM_FIELD}.barrier_scale_factor")
    h, step = loop_params(h, u_max, T_s)
    margin = float(margin)
    d = float(inflation)
    p_T = as_points(target, TARGET_FIELD)[0]
    P = np.zeros((0, 2)) if starts is None else as_points(starts, STARTS_FIELD)
    clear = d if start_clearance is None else float(start_clearance)
    k_R = apex_factor + SQRT2 * math.sqrt(rho_b) * scale_f  # R_i = k_R (r_i + d)
    half = (box[:, 1] - box[:, 0]) / 2.0
    if r_lo + margin >= half.min():
        raise ConfigError(f"{RANDOM_FIELD}.radius_range", f"a disc of radius {r_lo} (margin {margin}) does not fit the arena {arena!r}")
    named = [(TARGET_FIELD, p_T)] + [(f"{STARTS_FIELD}[{k}]", P[k]) for k in range(len(P))]
    for name, pt in named:
        if np.any(pt < box[:, 0]) or np.any(pt > box[:, 1]):
            raise ConfigError(name, f"({fmt(pt[0])}, {fmt(pt[1])}) lies outside the arena {box.tolist()}")
    gap_need = max(2.0 * step, 0.0) + 2.0 * margin  # V2 (gap > 0) and V3 (gap / 2 > u_max T_s), with the margin
    plan = _FieldDraw(M, box, half, r_lo, r_hi, apex_factor, rho_b, scale_f, k_R, h, margin, d, p_T, P, clear, gap_need)
    rng = np.random.default_rng(seed)
    for _ in range(max_restarts):
        placed = _place_obstacles(plan, rng, batch, batches_per_obstacle)
        if placed is not None:
            return _checked_field(plan, *placed, u_max=u_max, T_s=T_s)
    raise ConfigError(
        f"{RANDOM_FIELD}.n_obstacles",
        f"no valid field of {M} obstacles found in {max_restarts} tries (influence radius R = {fmt(k_R)} (r + d), "
        f"radii {r_lo}..{r_hi}, arena {box.tolist()}): use fewer or smaller discs, a larger arena, or a smaller "
        f"apex factor or barrier",
    )


@dataclass(frozen=True, eq=False)
class _FieldDraw:
    """What `random_field` draws from (its checked arguments): the arena `box` (2, 2) and its `half` sides, the
    radii, the covering factors (`R_i = k_R (r_i + d)`), the margin, the starts `P` (K, 2) and the V2/V3 gap."""

    M: int
    box: np.ndarray
    half: np.ndarray
    r_lo: float
    r_hi: float
    apex_factor: float
    rho_b: float
    scale_f: float
    k_R: float
    h: float
    margin: float
    d: float
    p_T: np.ndarray
    P: np.ndarray
    clear: float
    gap_need: float


def _place_obstacles(plan: _FieldDraw, rng: np.random.Generator, batch: int, batches_per_obstacle: int):
    """One attempt: each obstacle in turn is the first candidate of a batch that passes V1, the start condition
    and V2/V3 against those already placed. `(centers, radii)`, or None after `batches_per_obstacle` empty
    batches for one obstacle."""
    cs, rs, Rs = np.zeros((0, 2)), np.zeros(0), np.zeros(0)
    for _m in range(plan.M):
        for _b in range(batches_per_obstacle):
            c, r, R, ok = _candidates(plan, rng, batch, cs, Rs)
            if ok.any():
                break
        else:
            return None
        k = np.flatnonzero(ok)[0]
        cs, rs, Rs = np.vstack([cs, c[k]]), np.append(rs, r[k]), np.append(Rs, R[k])
    return cs, rs


def _candidates(plan: _FieldDraw, rng: np.random.Generator, batch: int, cs: np.ndarray, Rs: np.ndarray):
    """A batch of candidate discs (centres uniform over the arena shrunk by `r + margin`): `(c, r, R, ok)` with
    `ok` where V1, the start condition and V2/V3 against the placed discs `cs` (influence radii `Rs`) hold."""
    box, margin, d = plan.box, plan.margin, plan.d
    r = rng.uniform(plan.r_lo, min(plan.r_hi, plan.half.min() - margin - 1e-9), batch)
    u = rng.uniform(0.0, 1.0, (batch, 2))
    lo = box[:, 0] + (r + margin)[:, None]
    span = np.maximum((box[:, 1] - box[:, 0]) - 2.0 * (r + margin)[:, None], 0.0)
    c = lo + u * span
    R = plan.k_R * (r + d)
    ok = np.hypot(*(plan.p_T - c).T) > R + margin  # V1
    if len(plan.P):
        a_ = plan.apex_factor * (r + d)
        ok &= np.all(diamond_signed_distance(plan.P, c, a_, plan.p_T) > plan.clear + margin, axis=0)
    if len(Rs):
        dij = np.hypot(*np.moveaxis(c[:, None, :] - cs[None, :, :], -1, 0))
        ok &= np.all(dij - R[:, None] - Rs[None, :] - plan.h > plan.gap_need, axis=1)
    return c, r, R, ok


def _checked_field(plan: _FieldDraw, cs: np.ndarray, rs: np.ndarray, *, u_max, T_s) -> tuple[np.ndarray, np.ndarray]:
    """The drawn field, confirmed by `field_violations` (same margin)."""
    d, P = plan.d, plan.P
    kw = dict(apex=plan.apex_factor * (rs + d), reach=barrier_reach(plan.rho_b, plan.scale_f * (rs + d)), h=plan.h,
              u_max=u_max, T_s=T_s, arena=plan.box, starts=P if len(P) else None, inflation=d,
              start_clearance=plan.clear, margin=plan.margin)
    left = field_violations(cs, rs, plan.p_T, **kw)
    if not left:
        return cs, rs
    raise AssertionError(f"random_field drew an invalid field: {left[0].line}")  # pragma: no cover


# ----------------------------------------------------------------------------- example fields
def _frozen(a) -> np.ndarray:
    a = np.array(a, dtype=float)
    a.setflags(write=False)
    return a


@dataclass(frozen=True, eq=False)
class FieldExample:
    """A named field: discs `(M, 3)` rows `[x, y, r]`, target `(2,)`, starts `(K, 2)`, arena `(2, 2)`."""

    name: str
    discs: np.ndarray
    target: np.ndarray
    starts: np.ndarray
    arena: np.ndarray
    note: str = ""

    def __post_init__(self):
        for k in ("discs", "target", "starts", "arena"):
            object.__setattr__(self, k, _frozen(getattr(self, k)))

    @property
    def centers(self) -> np.ndarray:
        return self.discs[:, :2]

    @property
    def radii(self) -> np.ndarray:
        return self.discs[:, 2]


AUTHORS_MULTI = FieldExample(
    name="authors_multi",
    discs=[[-84, 16, 8], [-64, -20, 5], [-50, 34, 9], [-36, 0, 6], [-16, -28, 6], [-4, 24, 5], [14, -6, 9],
           [36, 16, 4], [34, -36, 8], [74, 30, 7], [70, -4, 8], [70, -34, 5]],
    target=[90.0, 40.0],
    starts=[[-90.0, 0.0]],
    arena=[[-100.0, 100.0], [-50.0, 50.0]],
    note="the authors' follow-up code: 12 discs in a 200 x 100 arena centred on the origin",
)


def two_in_row() -> FieldExample:
    """Two discs of the default radius 4 in a row on the segment from the start (-40, 0) to the default target
    (40, 0), in the default arena: valid with every default (apex 2 sqrt(2) r, rho_b = 0.5, l = r, h = 1,
    u_max = 10, T_s = 0.05). Centres 34 apart (V3 needs > 2 R + h + 2 u_max T_s = 32.63)."""
    return FieldExample(
        name="two_in_row",
        discs=[[-14.0, 0.0, 4.0], [20.0, 0.0, 4.0]],
        target=[40.0, 0.0],
        starts=[[-40.0, 0.0]],
        arena=[list(DEFAULT_ARENA[0]), list(DEFAULT_ARENA[1])],
        note="two default discs in a row between the start and the target",
    )


# ----------------------------------------------------------------------------- feasibility of a given field
def _start_apex_bound(starts, centers, radii, target, clearance: float) -> np.ndarray:
    """Per start and obstacle, the supremum of apex factors `f` (apex `f r_i`) that keep the start more than
    `clearance` from the diamond, `(K, M)` (bisection on the signed distance, decreasing in the apex)."""
    P = np.asarray(starts, dtype=float).reshape(-1, 2)
    r = np.asarray(radii, dtype=float)
    a, b = to_frames(P, centers, target)
    if clearance == 0:
        return (np.abs(a) + np.abs(b)) / r
    lo = np.zeros(a.shape)
    hi = (np.abs(a) + np.abs(b)) / r
    for _ in range(60):
        mid = (lo + hi) / 2
        half = mid * r / SQRT2
        ex, ey = np.abs(a + b) / SQRT2 - half, np.abs(b - a) / SQRT2 - half
        sd = np.hypot(np.maximum(ex, 0), np.maximum(ey, 0)) + np.minimum(np.maximum(ex, ey), 0)
        ok = sd > clearance
        lo, hi = np.where(ok, mid, lo), np.where(ok, hi, mid)
    return lo


@dataclass(frozen=True, eq=False)
class FieldAnalysis:
    """Which covering settings make a field valid (SPEC §3.6), for settings uniform in the (inflated) radius:
    apex `c^a_i = f rr_i`, reach `rho_i = g rr_i` (`g = sqrt(rho_b) l_i / rr_i`, `rr_i = r_i + inflation`), so
    `R_i = kappa rr_i` with `kappa = f + sqrt(2) g`. V1–V3 depend on `kappa` only; the start condition on `f`
    only; `f > sqrt(2)` and `g > 0`, so `kappa > sqrt(2)`. Every `*_max` is a supremum (strict bound).

    The field admits some setting (uniform or not: every condition is monotone in each `R_i` and apex) iff
    `kappa_max > sqrt(2)` and `start_apex_max > sqrt(2)`.
    """

    h: float
    u_max: float | None
    T_s: float | None
    inflation: float
    pairs: np.ndarray            # (P, 2) obstacle indices i < j, sorted by pair_kappa
    pair_distance: np.ndarray    # (P,) |c_i - c_j|
    pair_kappa: np.ndarray       # (P,) sup kappa that passes V2 and V3 for this pair
    pair_binding: tuple          # (P,) 'V3' (sampled loop) or 'V2'
    target_kappa: np.ndarray     # (M,) sup kappa that passes V1: |p_T - c_i| / rr_i
    kappa_max: float             # sup uniform kappa over V1–V3
    kappa_binding: tuple         # (field, condition) of the binding constraint
    start_apex: np.ndarray       # (K, M) sup apex factor f keeping start k clear of obstacle i's diamond
    start_apex_max: float
    apex_factor_max: float       # sup f over every condition (as the reach -> 0): min(kappa_max, start_apex_max)
    reach_factor_max: float      # sup g (as f -> sqrt 2): (kappa_max - sqrt 2) / sqrt 2
    rho_b_max_at_l_r: float      # sup rho_b with l_i = rr_i, f -> sqrt 2 (g^2)
    rho_b_max_authors_apex: float  # sup rho_b with l_i = rr_i and the authors' code's apex f = 1.5
    default_apex_factor_max: float  # sup f with SPEC's barrier (rho_b = 0.5, l = rr: sqrt(2) g = 1): kappa_max - 1
    R_headroom: np.ndarray       # (M,) sup R_i with every other R_j at its least sqrt(2) rr_j (non-uniform)
    feasible: bool
    defaults_violations: list = field(default_factory=list)  # SPEC defaults: apex 2 sqrt2 rr, rho_b 0.5, l = rr
    example: dict = field(default_factory=dict)              # a valid setting and its violations (empty)

    def summary(self) -> str:
        i, j = (int(x) for x in self.pairs[0])
        s2 = SQRT2
        lines = [(f"R_i = kappa (r_i + d), kappa = f + sqrt(2) g (apex f (r_i + d), reach g (r_i + d)), "
                  f"d = {self.inflation}: V1–V3 need kappa < {self.kappa_max:.4f} (binding {self.kappa_binding[0]}, "
                  f"{self.kappa_binding[1]}); every setting has kappa > sqrt(2) = {s2:.4f}.")]
        lines.append(f"{'Feasible' if self.feasible else 'Infeasible'}: largest uniform apex factor {self.apex_factor_max:.4f} "
                     f"(reach -> 0; the start allows f < {self.start_apex_max:.4f}); largest reach factor "
                     f"{self.reach_factor_max:.4f} (f -> sqrt 2), i.e. rho_b < {self.rho_b_max_at_l_r:.4f} at l = r; "
                     f"with the authors' apex 1.5 r: rho_b < {self.rho_b_max_authors_apex:.4f} at l = r.")
        lines.append(f"SPEC defaults (kappa = {DEFAULT_APEX_FACTOR + 1:.4f}) fail: {len(self.defaults_violations)} "
                     f"violations; with SPEC's barrier (rho_b = 0.5, l = r) the apex factor must be < "
                     f"{self.default_apex_factor_max:.4f} {'<' if self.default_apex_factor_max <= s2 else '>'} sqrt(2).")
        lines.append(f"Tightest pair: ({i}, {j}), {self.pair_binding[0]}, kappa < {self.pair_kappa[0]:.4f}.")
        return "\n".join(lines)


def analyse_field(
    centers, radii, target, *, starts=None, arena=None, h: float = 1.0, u_max: float | None = 10.0,
    T_s: float | None = 0.05, inflation: float = 0.0, start_clearance: float | None = None,
    example: tuple[float, float, float] = (1.5, 0.25, 0.5),
) -> FieldAnalysis:
    """The settings under which a given field is valid (see FieldAnalysis). `example` = `(f, rho_b, l / rr)`
    is checked with `field_violations` and recorded with its violations (empty when valid)."""
    g0 = field_geometry(centers, radii, target, inflation=inflation)
    h, step = loop_params(h, u_max, T_s)
    sampled = u_max is not None and T_s is not None
    c, rr, p_T = g0.centers, g0.cover_radii, g0.target
    d = float(inflation)
    clear = d if start_clearance is None else float(start_clearance)
    ii, jj = np.triu_indices(len(rr), 1)
    dij = np.hypot(*(c[ii] - c[jj]).T)
    pair_k = (dij - h - 2.0 * step) / (rr[ii] + rr[jj])
    order = np.argsort(pair_k, kind="stable")
    target_k = np.hypot(*(p_T - c).T) / rr
    cand = [(float(target_k.min()), f"{OBSTACLES_FIELD}[{int(np.argmin(target_k))}]", "V1")]
    if len(ii):
        t = order[0]
        cand.append((float(pair_k[t]), f"{OBSTACLES_FIELD}[{ii[t]},{jj[t]}]", "V3" if sampled else "V2"))
    kappa_max, *binding = min(cand, key=lambda x: x[0])
    P = np.zeros((0, 2)) if starts is None else as_points(starts, STARTS_FIELD)
    start_apex = _start_apex_bound(P, c, rr, p_T, clear) if len(P) else np.full((0, len(rr)), np.inf)
    start_max = float(start_apex.min()) if start_apex.size else math.inf
    reach_f = (kappa_max - SQRT2) / SQRT2
    R_head = target_k * rr
    if len(ii):
        lim = dij - h - 2.0 * step
        head = np.full((len(rr), len(rr)), np.inf)
        head[ii, jj] = lim - SQRT2 * rr[jj]
        head[jj, ii] = lim - SQRT2 * rr[ii]
        R_head = np.minimum(R_head, head.min(axis=1))
    kw = dict(h=h, u_max=u_max, T_s=T_s, arena=arena, starts=P if len(P) else None, inflation=d, start_clearance=clear)
    arena_ok = not [v for v in field_violations(c, g0.radii, p_T, **kw) if v.condition == "arena"]
    f_ex, rho_ex, l_ex = example
    ex_kw = dict(apex=f_ex * rr, reach=barrier_reach(rho_ex, l_ex * rr))
    return FieldAnalysis(
        h=h, u_max=u_max, T_s=T_s, inflation=d,
        pairs=np.stack([ii[order], jj[order]], axis=1), pair_distance=dij[order], pair_kappa=pair_k[order],
        pair_binding=tuple(("V3" if sampled else "V2") for _ in order), target_kappa=target_k,
        kappa_max=kappa_max, kappa_binding=tuple(binding), start_apex=start_apex, start_apex_max=start_max,
        apex_factor_max=min(kappa_max, start_max), reach_factor_max=reach_f,
        rho_b_max_at_l_r=max(reach_f, 0.0) ** 2, rho_b_max_authors_apex=max((kappa_max - 1.5) / SQRT2, 0.0) ** 2,
        default_apex_factor_max=kappa_max - 1.0, R_headroom=R_head,
        feasible=bool(kappa_max > SQRT2 and start_max > SQRT2 and arena_ok),
        defaults_violations=field_violations(c, g0.radii, p_T, **kw),
        example=dict(apex_factor=f_ex, rho_b=rho_ex, scale_factor=l_ex,
                     violations=field_violations(c, g0.radii, p_T, **ex_kw, **kw)),
    )


def authors_multi_analysis(*, h: float = 1.0, u_max: float | None = 10.0, T_s: float | None = 0.05,
                           inflation: float = 0.0) -> FieldAnalysis:
    """`analyse_field` on AUTHORS_MULTI (its start and arena) with h = 1, u_max = 10, T_s = 0.05 by default."""
    F = AUTHORS_MULTI
    return analyse_field(F.centers, F.radii, F.target, starts=F.starts, arena=F.arena, h=h, u_max=u_max, T_s=T_s,
                         inflation=inflation)


def random_scene(n_obstacles: int = 5, seed: int = 0, radius_range: list[float] = (2.0, 3.5),
                 target: list[float] = (40.0, 0.0), keep_free: list[list[float]] | None = None,
                 arena: Arena | None = None, barrier: Barrier | None = None, apex_factor: float = DEFAULT_APEX_FACTOR,
                 barrier_scale_factor: float = 1.0, h: float = 1.0, u_max: float | None = 10.0,
                 T_s: float | None = 0.05, margin: float = 1.0, inflation: NonNegative = 0.0, name: str = "field") -> Scene:
    """A seeded random valid scene of `n_obstacles` discs (the `field` preset, conf/scene/field.yaml): drawn by
    rejection against V1–V3 of SPEC §3.6 for the cell hysteresis `h`, `u_max` and the frame period `T_s` it will
    run with, inside the arena by `margin`, every point of `keep_free` (e.g. a start) outside every diamond;
    apex `apex_factor r_i`, barrier scale `barrier_scale_factor r_i`; valid also with every disc grown by `inflation` (Scene.inflated, the unicycle's steering scene, SPEC §3.7)."""
    arena = arena if isinstance(arena, Arena) else Arena(**(arena or {}))
    barrier = barrier if isinstance(barrier, Barrier) else Barrier(**(barrier or {}))
    centers, radii = random_field(int(n_obstacles), seed=int(seed), arena=arena.bounds, radius_range=tuple(radius_range),
                                  target=tuple(target), starts=keep_free, h=h, u_max=u_max, T_s=T_s,
                                  apex_factor=apex_factor, barrier_rho=barrier.rho,
                                  barrier_scale_factor=barrier_scale_factor, margin=margin, inflation=inflation)
    obstacles = [Obstacle(center=[float(x), float(y)], radius=float(r), apex=float(apex_factor * r),
                          barrier_scale=float(barrier_scale_factor * r)) for (x, y), r in zip(centers, radii)]
    return Scene(target=list(target), obstacles=obstacles, barrier=barrier, arena=arena, name=name)


def example_scene(example: FieldExample, apex_factor: float, barrier: Barrier, barrier_scale_factor: float) -> Scene:
    """A named field as a Scene with a uniform apex and barrier-scale factor (see `analyse_field`)."""
    obstacles = [Obstacle(center=[float(x), float(y)], radius=float(r), apex=float(apex_factor * r),
                          barrier_scale=float(barrier_scale_factor * r)) for x, y, r in example.discs]
    (x0, x1), (y0, y1) = example.arena
    return Scene(target=list(example.target), obstacles=obstacles, barrier=barrier,
                 arena=Arena(x=[x0, x1], y=[y0, y1]), name=example.name)


__all__ = ["AUTHORS_MULTI", "FieldAnalysis", "FieldExample", "analyse_field", "authors_multi_analysis", "example_scene",
           "random_field", "random_scene", "two_in_row"]
