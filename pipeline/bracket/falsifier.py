"""The falsifier of SPEC §5.5: the upper end `ε_hi` of the bracket, per controller and start.

For a start `p0` and a bound `ε`, a search over error signals `|e(t)| <= ε` for one that makes the sampled loop
fail (:mod:`pipeline.bracket.loop`: collision, leaving the camera's view, stall, timeout):

- ``fixed``: §3.5's direction `e = -ε sign(b(p)) e_b` (Proposition 1's adversary);
- ``mode_aware``: every frame, among `ε` times `n_dirs` directions (and 0), the error whose frame decision jumps
  the mode (it sees `q`), else puts the perceived point in the active wedge (a push-out), else makes the least
  progress towards the target;
- ``receding``: a receding-horizon search: per run `n_candidates` error sequences over `lookahead` frames (each
  fixed direction held, the two adversaries above, random directions per frame), all simulated at once; the
  worst (a failure, else the farthest from the target, the closest to the obstacle) is played for `commit` frames,
  and the search repeats from there. Each candidate is scored after `tail` more frames of the fixed adversary
  (a rollout of the base policy), so that the search keeps what the fixed adversary achieves and improves on it;
- ``trap``: aimed at the back vertex of the obstacle (the end of the set `K` behind it, where the abstraction's
  last non-transient component sits): every frame the error whose run ends nearest the vertex (pushed out by
  `trap_offset`), one frame ahead among `ε` times `n_dirs` directions (and 0) while the run is farther than
  `trap_reach`, two frames ahead within it (the first among `trap_dirs` directions at 1, 0.7 and 0.4 of `ε`, the
  second among `n_dirs` at `ε`). At the vertex it finds the chattering orbit the other three miss: the perceived
  point crosses the axis every two frames, each crossing a jump, each mode sliding the run back along its face
  (docs/bracket.md, "The falsifier aimed at the vertex").

The bound may also depend on the position (:class:`MapBound`: a certified error map's `ε̄` at the true position of
each frame; :func:`attack` with it): every adversary then chooses with the bound where the run is, and the error it
plays is clipped to that bound, so a counterexample's signal lies within the map's certificate frame by frame.

`ε_hi` is the smallest `ε` found failing by bisection on `[0, eps_max]` (`inf`: no failure up to `eps_max`).
Failing is monotone in `ε` for the true worst case (a signal within `ε` is within every larger bound), so every
`ε >= ε_hi` fails too; the search is a heuristic, so `ε_hi` is an upper bound of the robustness margin. Each
failure comes with its trajectory (a counterexample).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.bracket.loop import COLLIDED, LEFT, REACHED, RUNNING, FrameLoop
from pipeline.sim.disturbances import frame_b

ADVERSARIES = ("fixed", "mode_aware", "receding", "trap")
TRAP_RADII = (1.0, 0.7, 0.4)  # the trap search's first-frame candidates: these fractions of ε


def directions(n: int) -> np.ndarray:
    """`n` unit vectors evenly spaced from angle 0 `(n, 2)`."""
    ang = 2.0 * np.pi * np.arange(n) / n
    return np.stack([np.cos(ang), np.sin(ang)], axis=1)


def fixed_error(loop: FrameLoop, st: dict, eps: np.ndarray) -> np.ndarray:
    """§3.5's adversary: `-ε sign(b(p)) e_b` (ties `b = 0`: `-ε e_b`, as :class:`pipeline.sim.Adversarial`), in the
    frame of the obstacle whose centre is nearest (several obstacles, as the simulator's disturbances)."""
    b, e_b = frame_b(st["p"], loop.scene)
    sign = np.where(b >= 0, 1.0, -1.0)
    return -(eps * sign)[:, None] * e_b


def mode_aware_error(loop: FrameLoop, st: dict, eps: np.ndarray, dirs: np.ndarray,
                     base: np.ndarray | None = None) -> np.ndarray:
    """The mode-aware adversary (module docstring): all `(run, candidate)` pairs evaluated in one batch. The
    candidates perceive `base + ε d` (`base` `(N, 2)`, default the true positions; the camera falsifier passes
    the map's clean estimates); the chosen offset from `base` is returned."""
    n, k = len(st["p"]), len(dirs) + 1
    cand = np.concatenate([np.zeros((1, 2)), dirs], axis=0)  # (k, 2), 0 first
    E = (eps[:, None, None] * cand[None]).reshape(-1, 2)
    P = np.repeat(st["p"], k, axis=0)
    xd = {name: np.repeat(a, k) for name, a in st["xd"].items()}
    m = (P if base is None else np.repeat(np.asarray(base, float), k, axis=0)) + E
    xd1, jumped, u = loop.decision(m, xd)
    ev = loop.controller.evaluate(m, xd1)
    pushed = ~loop.controller.flow_set(m, xd1, ev=ev) & ~loop.controller.jump_set(m, xd1, ev=ev)
    pT = loop.scene.p_T
    before = np.hypot(*(P - pT).T)
    after = np.hypot(*(P + loop.period * u - pT).T)
    scale = loop.period * max(getattr(loop.controller, "u_max", None) or 10.0, 1e-9)
    score = 4.0 * jumped + 2.0 * pushed + np.clip((after - before) / scale, -1.0, 1.0)
    best = score.reshape(n, k).argmax(axis=1)
    return E.reshape(n, k, 2)[np.arange(n), best]


@dataclass
class Search:
    """Settings of the receding-horizon search and of the mode-aware adversary."""

    n_dirs: int = 16
    lookahead: int = 8
    commit: int = 8
    tail: int = 40
    n_random: int = 4
    seed: int = 0
    trap_dirs: int = 64
    trap_reach: float = 3.0
    trap_offset: float = 0.2


def _badness(loop: FrameLoop, st: dict) -> np.ndarray:
    """How close a rollout came to failing: a failure first, then distance to the target minus clearance."""
    out = st["outcome"]
    fail = (out == COLLIDED) | (out == LEFT)
    dist = np.hypot(*(st["p"] - loop.scene.p_T).T)
    score = dist - 0.5 * np.minimum(st["clearance"], 5.0)
    score = np.where(out == REACHED, -1e6, score)
    return np.where(fail, 1e6, score)


class MapBound:
    """A bound that depends on the true position: a certified error map's `ε̄` there (`table.at`, the smallest bound
    of the cells holding the point) times `scale`, and 0 where the map is certified nowhere: a counterexample is then
    within the map's certificate where it has one and exact elsewhere."""

    def __init__(self, table, scale: float = 1.0):
        self.table, self.scale = table, float(scale)

    def __call__(self, p: np.ndarray) -> np.ndarray:
        v = self.table.at(p)
        return self.scale * np.where(np.isfinite(v), v, 0.0)


def _now(eps, p: np.ndarray) -> np.ndarray:
    """The bounds of the runs at their positions `p`: a :class:`MapBound` evaluated there, an array `(N,)` as it is."""
    return eps(p) if callable(eps) else eps


def _rows(eps, rows):
    """The bounds of the runs `rows`: a :class:`MapBound` as it is (it depends on the position only)."""
    return eps if callable(eps) else eps[rows]


def clip_to(e: np.ndarray, eps: np.ndarray) -> np.ndarray:
    """The errors `e` `(N, 2)` scaled down where longer than `eps` `(N,)`."""
    n = np.hypot(*np.asarray(e, float).T)
    with np.errstate(invalid="ignore", divide="ignore"):
        s = np.where(n > eps, eps / n, 1.0)
    return e * s[:, None]


def run_adversary(loop: FrameLoop, p0: np.ndarray, eps, kind: str, search: Search, record: bool = True) -> dict:
    """Runs from `p0` `(N, 2)` under adversary `kind` with bounds `eps` (`(N,)`, or a :class:`MapBound` of the
    position); the final batch (and with `record` the positions per frame `path` `(F + 1, N, 2)` and the errors
    played `errors` `(F, N, 2)`: frame `k` perceives `path[k] + errors[k]`)."""
    dirs = directions(search.n_dirs)
    rng = np.random.default_rng(search.seed)
    eps = eps if callable(eps) else np.asarray(eps, float)
    play = (lambda e, b: clip_to(e, b)) if callable(eps) else (lambda e, b: e)  # arrays: every candidate within ε
    p0 = np.asarray(p0, float)
    probe = {"p": p0, "xd": loop.controller.initial_state(p0)}
    policy = _policy(loop, kind, dirs, search)
    now = _now(eps, p0)
    if kind in ("receding", "trap"):  # the frame-0 error sets the initial mode: §3.5's
        e0 = play(fixed_error(loop, probe, now), now)
    else:
        e0 = play(policy(probe, now), now)
    st = loop.start(p0, e0)
    path = [st["p"].copy()] if record else None
    played = [] if record else None
    if kind != "receding":
        first = True
        while st["frame"] < loop.n_frames and (st["outcome"] == RUNNING).any():
            now = _now(eps, st["p"])
            e = e0 if first else play(policy(st, now), now)
            first = False
            st = loop.step(st, e)
            if record:
                path.append(st["p"].copy())
                played.append(np.array(e, float))
    else:
        locked = np.zeros(len(p0), bool)  # runs the fixed adversary alone already breaks from here
        while st["frame"] < loop.n_frames and (st["outcome"] == RUNNING).any():
            free = np.flatnonzero(~locked & (st["outcome"] == RUNNING))
            locked[free] |= _base_fails(loop, FrameLoop.take(st, free), _rows(eps, free))
            free = np.flatnonzero(~locked & (st["outcome"] == RUNNING))
            plan = np.zeros((len(p0), search.lookahead, 2))
            if free.size:
                plan[free] = _plan(loop, FrameLoop.take(st, free), _now(_rows(eps, free), st["p"][free]), dirs,
                                   search, rng)
            for j in range(min(search.commit, loop.n_frames - st["frame"])):
                now = _now(eps, st["p"])
                e = play(plan[:, j], now)  # a map's bound: planned where the plan began, played within this one
                e[locked] = fixed_error(loop, st, now)[locked]
                st = loop.step(st, e)
                if record:
                    path.append(st["p"].copy())
                    played.append(np.array(e, float))
    if record:
        st["path"] = np.stack(path)
        st["errors"] = np.stack(played) if played else np.zeros((0, len(p0), 2))
    return st


def _base_fails(loop: FrameLoop, st: dict, eps) -> np.ndarray:
    """Runs that the fixed adversary (bounds `eps`: `(N,)` or a :class:`MapBound`), played from `st` to the horizon,
    keeps from arriving."""
    sub = FrameLoop.take(st, np.arange(len(st["p"])))
    while sub["frame"] < loop.n_frames and (sub["outcome"] == RUNNING).any():
        sub = loop.step(sub, fixed_error(loop, sub, _now(eps, sub["p"])))
    return (sub["outcome"] != REACHED) & (st["outcome"] == RUNNING)


def _policy(loop, kind, dirs, search: Search):
    if kind == "fixed":
        return lambda st, eps: fixed_error(loop, st, eps)
    if kind in ("mode_aware", "receding"):
        return lambda st, eps: mode_aware_error(loop, st, eps, dirs)
    if kind == "trap":
        return trap_policy(loop, dirs, search)
    raise ValueError(f"unknown adversary {kind!r}: one of {ADVERSARIES}")


def vertex_aims(scene, offset: float) -> np.ndarray:
    """The back vertex of each obstacle's covering (`a = -c`, `b = 0` in its frame: the end of `K`), `offset` farther
    from the obstacle along its axis `(M, 2)`."""
    return np.concatenate([cov.from_frame(np.array([-cov.c - offset]), np.array([0.0])) for cov in scene.coverings])


def _ring(dirs: np.ndarray, radii) -> np.ndarray:
    """0 and `dirs` scaled by each of `radii` `(1 + len(radii) len(dirs), 2)`."""
    return np.concatenate([np.zeros((1, 2))] + [r * dirs for r in radii])


def _near_aim(st: dict, aim: np.ndarray) -> np.ndarray:
    """Closeness of each run to its aim (higher: closer); a failure first, an arrival last."""
    out = st["outcome"]
    score = -np.hypot(*(st["p"] - aim).T)
    score = np.where(out == REACHED, -1e6, score)
    return np.where((out == COLLIDED) | (out == LEFT), 1e6, score)


def _toward(loop: FrameLoop, st: dict, eps: np.ndarray, aim: np.ndarray, first: np.ndarray,
            second: np.ndarray | None) -> np.ndarray:
    """Per run the error among `eps` times the offsets `first` whose run ends nearest `aim` after this frame or,
    with `second`, after the next one too (its error among `eps` times `second`; the better of the two frames)."""
    n, k1 = len(st["p"]), len(first)
    s1 = loop.step(FrameLoop.take(st, np.repeat(np.arange(n), k1)), (eps[:, None, None] * first[None]).reshape(-1, 2))
    aim1 = np.repeat(aim, k1, axis=0)
    score = _near_aim(s1, aim1)
    if second is not None:
        k2 = len(second)
        s2 = loop.step(FrameLoop.take(s1, np.repeat(np.arange(n * k1), k2)),
                       (np.repeat(eps, k1)[:, None, None] * second[None]).reshape(-1, 2))
        later = _near_aim(s2, np.repeat(aim1, k2, axis=0)).reshape(n * k1, k2).max(axis=1)
        score = np.maximum(score, np.where(s1["outcome"] == RUNNING, later, score))
    return eps[:, None] * first[score.reshape(n, k1).argmax(axis=1)]


def trap_policy(loop: FrameLoop, dirs: np.ndarray, search: Search):
    """The ``trap`` adversary (module docstring) as a policy `(st, eps) -> e`."""
    aims = vertex_aims(loop.scene, search.trap_offset)
    far_set = second = _ring(dirs, (1.0,))
    near_set = _ring(directions(search.trap_dirs), TRAP_RADII)

    def policy(st: dict, eps: np.ndarray) -> np.ndarray:
        d = np.hypot(*(st["p"][:, None, :] - aims[None]).transpose(2, 0, 1))
        aim = aims[d.argmin(axis=1)]
        run = st["outcome"] == RUNNING
        near = d.min(axis=1) <= search.trap_reach
        e = np.zeros_like(st["p"])
        for rows, first, nxt in ((np.flatnonzero(run & ~near), far_set, None),
                                 (np.flatnonzero(run & near), near_set, second)):
            if rows.size:
                e[rows] = _toward(loop, FrameLoop.take(st, rows), eps[rows], aim[rows], first, nxt)
        return e
    return policy


def _plan(loop: FrameLoop, st: dict, eps: np.ndarray, dirs: np.ndarray, search: Search, rng) -> np.ndarray:
    """The worst of the candidate error sequences over `lookahead` frames per run `(N, lookahead, 2)`."""
    n, nd, H = len(st["p"]), len(dirs), search.lookahead
    c = nd + 2 + search.n_random  # held directions, fixed, mode-aware, random
    idx = np.repeat(np.arange(n), c)
    sub = FrameLoop.take(st, idx)
    E_eps = eps[idx]
    kind = np.tile(np.arange(c), n)
    plan = np.zeros((n * c, H, 2))
    for j in range(H):
        e = np.zeros((n * c, 2))
        held = kind < nd
        e[held] = E_eps[held, None] * dirs[kind[held]]
        fx = kind == nd
        e[fx] = fixed_error(loop, FrameLoop.take(sub, fx), E_eps[fx])
        ma = kind == nd + 1
        e[ma] = mode_aware_error(loop, FrameLoop.take(sub, ma), E_eps[ma], dirs)
        rnd = kind > nd + 1
        e[rnd] = E_eps[rnd, None] * dirs[rng.integers(0, nd, int(rnd.sum()))]
        plan[:, j] = e
        sub = loop.step(sub, e)
    for _ in range(min(search.tail, loop.n_frames - sub["frame"])):
        sub = loop.step(sub, fixed_error(loop, sub, E_eps))
    best = _badness(loop, sub).reshape(n, c).argmax(axis=1)
    return plan.reshape(n, c, H, 2)[np.arange(n), best]


@dataclass
class Bracket:
    """Per start: `eps_hi` (inf: none found up to `eps_max`), the adversary and outcome of the counterexample at
    `eps_hi`, its path `(F + 1, N, 2)` (NaN rows for starts without one)."""

    eps_hi: np.ndarray
    adversary: np.ndarray
    outcome: np.ndarray
    path: np.ndarray | None = None
    tried: list = field(default_factory=list)


def attack(loop: FrameLoop, p0: np.ndarray, eps, search: Search,
           adversaries=ADVERSARIES, run=run_adversary) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Every adversary in turn on the runs not yet failed: `(failed, adversary index, outcome, path)`; `eps` the
    bounds `(N,)` or a :class:`MapBound`; `run` plays one adversary (`run(loop, p0, bounds, kind, search)` -> the
    final batch with its `path`; the camera falsifier passes its own)."""
    n = len(p0)
    failed = np.zeros(n, bool)
    which = np.full(n, -1)
    outcome = np.zeros(n, np.int8)
    path = np.full((loop.n_frames + 1, n, 2), np.nan)
    for a, kind in enumerate(adversaries):
        rows = np.flatnonzero(~failed)
        if rows.size == 0:
            break
        st = run(loop, p0[rows], _rows(eps, rows), kind, search)
        bad = st["outcome"] != REACHED
        r = rows[bad]
        failed[r], which[r], outcome[r] = True, a, st["outcome"][bad]
        pth = st["path"]
        if len(pth) < loop.n_frames + 1:  # runs that all ended early: hold the last position
            pth = np.concatenate([pth, np.repeat(pth[-1:], loop.n_frames + 1 - len(pth), axis=0)])
        path[:, r] = pth[:, bad]
    return failed, which, outcome, path


def falsify(loop: FrameLoop, p0: np.ndarray, eps_max: float, n_bisect: int, search: Search,
            adversaries=ADVERSARIES) -> Bracket:
    """`ε_hi` per start by bisection on `[0, eps_max]` (module docstring), with the counterexamples."""
    p0 = np.asarray(p0, float)
    n = len(p0)
    eps_hi = np.full(n, np.inf)
    adv = np.full(n, -1)
    outc = np.zeros(n, np.int8)
    path = np.full((loop.n_frames + 1, n, 2), np.nan)
    tried = []

    def keep(eps, failed, which, outcome, pth):
        better = failed & (eps < eps_hi)
        eps_hi[better], adv[better], outc[better] = eps[better], which[better], outcome[better]
        path[:, better] = pth[:, better]

    zero = np.zeros(n)
    f0 = attack(loop, p0, zero, search, adversaries=("fixed",))  # ε = 0: every adversary is the nominal run
    keep(zero, *f0)
    tried.append((0.0, int(f0[0].sum())))
    lo, hi = np.zeros(n), np.full(n, float(eps_max))
    rows = np.flatnonzero(~f0[0])
    if rows.size:
        res = attack(loop, p0[rows], hi[rows], search, adversaries)
        full = scatter(n, rows, res, loop)
        keep(np.where(np.isin(np.arange(n), rows), hi, np.inf), *full)
        tried.append((float(eps_max), int(res[0].sum())))
    live = np.isfinite(eps_hi) & (eps_hi > 0)
    for _ in range(n_bisect):
        rows = np.flatnonzero(live)
        if rows.size == 0:
            break
        mid = 0.5 * (lo[rows] + np.minimum(hi[rows], eps_hi[rows]))
        res = attack(loop, p0[rows], mid, search, adversaries)
        eps_full = np.full(n, np.inf)
        eps_full[rows] = mid
        keep(eps_full, *scatter(n, rows, res, loop))
        lo[rows] = np.where(res[0], lo[rows], mid)
    return Bracket(eps_hi=eps_hi, adversary=np.array([adversaries[a] if a >= 0 else ("fixed" if np.isfinite(e) else "")
                                                     for a, e in zip(adv, eps_hi)]),
                   outcome=outc, path=path, tried=tried)


def scatter(n, rows, res, loop):
    """The result of :func:`attack` on the runs `rows`, as arrays over all `n` runs (the others: not failed)."""
    failed, which, outcome, pth = res
    fail_all, which_all = np.zeros(n, bool), np.full(n, -1)
    out_all, path_all = np.zeros(n, np.int8), np.full((loop.n_frames + 1, n, 2), np.nan)
    fail_all[rows], which_all[rows], out_all[rows], path_all[:, rows] = failed, which, outcome, pth
    return fail_all, which_all, out_all, path_all
