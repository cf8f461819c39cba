"""The winning set of the abstraction (SPEC §5.4) and its arrival-time bound (SPEC §5.6, the horizon).

`win(abs, period, p_T)`: strongly connected components of the safe non-goal nodes by Tarjan's algorithm
(iterative; it emits components sinks first), each decided once in that order: in `Win` when every successor
outside it is in `Win` and it is a single node without a self-loop or transient (:func:`rates`).

With it, per node of `Win`, `frames`: an upper bound on the camera frames from the node (a frame instant) until the
position is in a goal cell at a frame instant, for every run the abstraction allows. A goal node: 0. A component,
in the same sinks-first order, per node `n` of it: `inner(n) + max over the component's exit edges (v -> s) of
(f(v) + frames(s))`, `f(v)` the frames of `v`'s edges (1, or `Abstraction.frames` on edges over several frames) and
`inner(n)` the frames a run from `n` can spend inside it: 0 for a single node without a self-loop; for a transient
one, its ranking function's largest value on `n`'s cell less its smallest on the cells of the component's nodes with
an exit edge (a run leaves from one of them), over the least decrease per frame (`w·p` decreasing by `c T_s` per frame, `c` the smallest `-w·u`
over the component's inputs; or `|p - p_T|²` by its least certified decrease), rounded down, the smallest over the
directions and the distance.
"""

from __future__ import annotations

import numpy as np

from pipeline.bracket.abstraction import Abstraction
from pipeline.bracket.enclosures import DIRS, dist_range, support_at

J = len(DIRS)


RATE_DIRS = 24 * J  # candidate directions of the transience rule (the support directions among them)


RATE_W = np.stack([np.cos(2 * np.pi * np.arange(RATE_DIRS) / RATE_DIRS),
                   np.sin(2 * np.pi * np.arange(RATE_DIRS) / RATE_DIRS)], axis=1)
RATE_C = support_at(np.eye(J)[:, None, :], RATE_W)  # (J, RATE_DIRS): w_k's bound a h_j + b h_{j+1}, linear in h


def direction_bounds(U: np.ndarray) -> np.ndarray:
    """`(nodes, RATE_DIRS)`: an upper bound of `w_k·u` over each polytope `U` `(nodes, J)` (:func:`support_at`
    between two support directions; exactly the support on the support directions). A node without inputs (-inf):
    -1 in every direction (it decreases everything; it has no successors either)."""
    with np.errstate(invalid="ignore"):  # (a +inf support times a zero coefficient: nan, not decreasing)
        out = np.where(np.isneginf(U), -1.0, U) @ RATE_C
    out[:, :: RATE_DIRS // J] = np.where(np.isneginf(U), -1.0, U)
    return np.where(np.isnan(out), np.inf, out)


def rates(ab: Abstraction, period: float, p_T: np.ndarray,
          active: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Per node: `dir_ok` `(nodes, RATE_DIRS)` (`w_k·u < 0` for every input, `w_k` at `k · 360°/RATE_DIRS`: `w_k·p`
    decreases every frame; between two support directions bounded by :func:`support_at`, so a direction a
    polytope's support function does not itself list counts only where that upper bound is negative) and
    `lyap_dec` `(nodes,)`, the least decrease of `|p - p_T|²` over a frame from any point of the cell
    (`-T_s (2 (p - p_T)·u + T_s |u|²)`; positive where it decreases, the distance rule). `active`: the nodes a
    component can hold (others get `dir_ok` False: never read)."""
    U = ab.U.reshape(-1, J)
    rows = np.arange(len(U)) if active is None else np.flatnonzero(active)
    dir_ok = np.zeros((len(U), RATE_DIRS), bool)
    dir_ok[rows] = direction_bounds(U[rows]) < 0
    boxes = np.repeat(ab.grid.boxes(), ab.modes, axis=0)
    r = np.maximum(U, 0).max(axis=1) / np.cos(np.pi / J)  # |u| <= r
    worst = np.full(len(U), -np.inf)
    for cx, cy in ((0, 2), (1, 2), (1, 3), (0, 3)):  # h_U convex: the largest (p - p_T)·u at a corner
        x = np.stack([boxes[:, cx], boxes[:, cy]], axis=1) - p_T
        worst = np.maximum(worst, support_at(U, x))
    lyap_dec = -period * (2 * worst + period * r * r)
    if ab.multi is not None:
        lyap_dec = np.where(ab.multi, -np.inf, lyap_dec)  # an edge over several frames leaves P: the bound is on P only
    return dir_ok, lyap_dec


def tarjan(n: int, indptr: np.ndarray, succ: np.ndarray, active: np.ndarray) -> list[np.ndarray]:
    """Strongly connected components of the subgraph on `active` nodes, sinks first (iterative Tarjan)."""
    index = np.full(n, -1, np.int64)
    low = np.zeros(n, np.int64)
    on = np.zeros(n, bool)
    stack, comps, counter = [], [], 0
    ptr, succ_l = indptr.tolist(), succ.tolist()
    act = active.tolist()
    for root in np.flatnonzero(active).tolist():
        if index[root] >= 0:
            continue
        work = [(root, ptr[root])]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on[root] = True
        while work:
            v, i = work[-1]
            end = ptr[v + 1]
            while i < end and not act[succ_l[i]]:
                i += 1
            if i < end:
                w = succ_l[i]
                work[-1] = (v, i + 1)
                if index[w] < 0:
                    index[w] = low[w] = counter
                    counter += 1
                    stack.append(w)
                    on[w] = True
                    work.append((w, ptr[w]))
                elif on[w]:
                    low[v] = min(low[v], index[w])
                continue
            work.pop()
            if work:
                u = work[-1][0]
                low[u] = min(low[u], low[v])
            if low[v] == index[v]:
                comp = []
                while True:
                    w = stack.pop()
                    on[w] = False
                    comp.append(w)
                    if w == v:
                        break
                comps.append(np.array(comp, np.int64))
    return comps


def _inner_frames(ab: Abstraction, comp: np.ndarray, leaves: np.ndarray, period: float, p_T: np.ndarray,
                  dir_ok: np.ndarray, lyap_dec: np.ndarray) -> tuple[np.ndarray, str | None]:
    """Per node of the transient component `comp`, the frames a run from it can spend in the component before the
    frame instant at which it takes an exit edge from one of the nodes `leaves` (a mask of `comp`): its ranking
    function's largest value on the node's cell less its smallest on the leaving nodes' cells, over the least
    decrease per frame, rounded down; the smaller of every direction's and the distance's. And the rule that shows
    the component transient (`direction` first, else `distance`; None: not transient, inf)."""
    cells = comp // ab.modes
    boxes = ab.grid.boxes()[cells]
    best, rule = np.full(len(comp), np.inf), None
    ok = np.flatnonzero(dir_ok[comp].all(axis=0))
    if len(ok):
        rate = -direction_bounds(ab.U.reshape(-1, J)[comp])[:, ok].max(axis=0)  # (ok,) > 0
        corners = np.stack([boxes[:, [0, 2]], boxes[:, [1, 2]], boxes[:, [1, 3]], boxes[:, [0, 3]]], 1)
        wp = corners @ RATE_W[ok].T  # (nodes, 4, ok)
        span = wp.max(axis=1) - wp[leaves].min(axis=(0, 1))
        best, rule = np.floor(np.maximum(span, 0.0) / (rate * period)).min(axis=1), "direction"
    dec = lyap_dec[comp].min()
    if dec > 0:
        lo, hi = dist_range(boxes, p_T)
        best, rule = np.minimum(best, np.floor(np.maximum(hi**2 - lo[leaves].min() ** 2, 0.0) / dec)), rule or "distance"
    return best, rule


def _single(v: int, ptr: list, succ: list, f: list, W: np.ndarray, frames: np.ndarray) -> bool | None:
    """:func:`win`'s step for a single node `v` without a self-loop, in plain Python (most components are one node;
    numpy's per-call cost was most of `win`): in `Win` (True) when every successor is, with `f(v)` plus their largest
    bound (the same float operations), else False. None where it has a self-loop (decided by the general step)."""
    outs = succ[ptr[v]:ptr[v + 1]]
    if v in outs:
        return None
    if not all(W[s] for s in outs):
        return False
    W[v] = True
    frames[v] = max(f[v] + frames[s] for s in outs) if outs else 0.0
    return True


def win(ab: Abstraction, period: float, p_T: np.ndarray,
        seeds: np.ndarray | None = None) -> tuple[np.ndarray, dict, np.ndarray]:
    """`Win` `(nodes,)`, counts (components, transient ones and by which rule) and the arrival bound `frames`
    `(nodes,)` (inf outside `Win`; module docstring). `seeds` `(nodes,)`: nodes shown winning by another argument
    with their arrival bound (finite; the funnels of :mod:`pipeline.bracket.funnel`): in `Win` like goal nodes, with
    that bound, their own edges not followed."""
    n = len(ab.safe)
    goal = np.repeat(ab.goal, ab.modes)
    W = goal.copy()
    frames = np.where(goal, 0.0, np.inf)
    if seeds is not None:
        seeded = ~goal & np.isfinite(seeds)
        W |= seeded
        frames = np.where(seeded, seeds, frames)
    f = np.where(ab.multi, ab.frames, 1) if ab.multi is not None else np.ones(n, np.int64)
    active = ab.safe & ~W
    dir_ok, lyap_dec = rates(ab, period, p_T, active)
    comps = tarjan(n, ab.indptr, ab.succ, active)
    stats = {"components": len(comps), "transient_direction": 0, "transient_distance": 0, "won_components": 0}
    member = np.full(n, -1, np.int64)
    ptr, succ_l, f_l = ab.indptr.tolist(), ab.succ.tolist(), f.tolist()
    for ci, comp in enumerate(comps):
        member[comp] = ci
        if len(comp) == 1 and (won := _single(int(comp[0]), ptr, succ_l, f_l, W, frames)) is not None:
            stats["won_components"] += won
            continue
        deg = ab.indptr[comp + 1] - ab.indptr[comp]
        outs = np.concatenate([ab.succ[ab.indptr[v]:ab.indptr[v + 1]] for v in comp])
        internal = member[outs] == ci
        if internal.all() and internal.any() or not W[outs[~internal]].all():
            continue  # (a component without an exit edge is never left: not in `Win`)
        src = np.repeat(comp, deg)[~internal]
        inner = 0.0
        if internal.any():
            inner, rule = _inner_frames(ab, comp, np.isin(comp, src), period, p_T, dir_ok, lyap_dec)
            if rule is None:
                continue
            stats[f"transient_{rule}"] += 1
        W[comp] = True
        exit_frames = (f[src] + frames[outs[~internal]]).max() if (~internal).any() else 0.0
        frames[comp] = inner + exit_frames
        stats["won_components"] += 1
    return W, stats, frames


def relax_frames(ab: Abstraction, W: np.ndarray, frames: np.ndarray, max_rounds: int = 100_000) -> np.ndarray:
    """Arrival bounds no larger than `frames` (:func:`win`'s, or after the funnels and the window), each still an upper
    bound: from a node of `Win` whose successors are all in `Win`, every run is in one of them after `f(v)` frames, so
    `f(v) + max_s frames(s)` bounds it too, and the smaller of two bounds is one. Iterated to the fixed point (each
    round from sound bounds gives sound bounds). It matters where a node's bound came from another argument: a
    funnel's seed is taken as it is in :func:`win` (its node's own edges not followed), and may be longer than the
    path through the node's edges once the window has won its successors."""
    n = len(W)
    f = np.where(ab.multi, ab.frames, 1).astype(float) if ab.multi is not None else np.ones(n)
    deg = np.diff(ab.indptr)
    has = np.flatnonzero(deg > 0)
    pick = np.flatnonzero(W[has] & (frames[has] > 0))  # positions in `has` of the nodes to tighten
    rows = has[pick]
    out = frames.astype(float).copy()
    for _ in range(max_rounds):
        cand = f[rows] + np.maximum.reduceat(out[ab.succ], ab.indptr[has])[pick]
        lower = cand < out[rows]
        if not lower.any():
            break
        out[rows[lower]] = cand[lower]
    return out


def arrival_frames(ab: Abstraction, frames: np.ndarray) -> np.ndarray:
    """Per start cell, the largest arrival bound over the initial nodes it can have `(cells,)` (inf: one of them
    is not in `Win`; a cell without initial nodes: inf)."""
    F = np.where(ab.initial, frames.reshape(-1, ab.modes), -np.inf).max(axis=1)
    return np.where(ab.initial.any(axis=1), F, np.inf)


def certified_cells(ab: Abstraction, W: np.ndarray, frames: np.ndarray | None = None,
                    horizon: float = np.inf) -> np.ndarray:
    """Start cells whose every possible initial node is in `Win` `(cells,)`, and with `frames` (:func:`win`) whose
    arrival bound fits `horizon` frames."""
    Wc = W.reshape(-1, ab.modes)
    ok = (~ab.initial | Wc).all(axis=1) & ab.initial.any(axis=1)
    return ok if frames is None else ok & (arrival_frames(ab, frames) <= horizon)


def directional_frames(ab: Abstraction, W: np.ndarray, frames: np.ndarray, period: float, members: np.ndarray,
                       shares=(0.5, 0.4, 0.3, 0.22), max_rounds: int = 1000) -> np.ndarray:
    """Tighter arrival bounds from a direction's decrease over a set of nodes rather than edge by edge (docs/bracket.md
    "Arrival bounds through a set"): the longest path charges every edge its frames, and where cells are not much
    larger than a frame's travel an abstract path may advance by much less per frame than any run does.

    For a support direction `d_j` and a rate `c > 0`, `S` is the set of `members` (nodes of `Win` with a finite
    bound and the abstraction's own edges and inputs: not goal nodes, nor the window's exits) whose every input (`Abstraction.U`: over all its edge's frames) has
    `d_j·u <= -c`: while a run stays in `S`, `d_j·p` falls by at least `c T_s` a frame. A run from `n ∈ S`
    (`d_j·p <= hi_n`, the largest on its cell) that is still in `S` at a frame instant in node `v` (reached from `n`
    along edges inside `S`) has spent at most `(hi_n - lo_v) / (c T_s)` frames (`lo_v` the smallest of `d_j·p` on
    `v`'s cell), and leaves `S` along an edge of `v` to a node `s` outside `S`, in `Win` since `v` is: it arrives within
    `max over such v of (hi_n - lo_v) / (c T_s) + f(v) + max over v's successors s ∉ S of frames(s)`. That maximum is
    taken over the nodes reachable inside `S` by relaxation (`R(n) = max(own, max over successors in S of R)`, to its
    fixed point). Each bound is sound given sound `frames` of the successors, so the smaller is kept, over the 32
    support directions and the rates `c` at the `shares` of the largest rate among the members."""
    frames = frames.copy()
    U = ab.U.reshape(-1, J)
    n = len(U)
    members = members & W & np.isfinite(frames)
    if not members.any():
        return frames
    f = np.where(ab.multi, ab.frames, 1) if ab.multi is not None else np.ones(n, np.int64)
    hb = _extent(ab)
    src = np.repeat(np.arange(n), np.diff(ab.indptr))
    rows = np.flatnonzero(np.diff(ab.indptr) > 0)
    starts = ab.indptr[rows]
    for j in range(J):
        rate = np.where(members, -U[:, j], -np.inf)  # the least decrease of d_j·p per unit time (inf: no input)
        finite = rate[np.isfinite(rate)]
        top = finite.max() if finite.size else 0.0
        if not top > 0:
            continue
        hi, lo = hb[:, j], -hb[:, (j + J // 2) % J]
        for c in top * np.asarray(shares):
            S = rate >= c
            step = c * period
            out = S[src] & ~S[ab.succ]
            E = np.full(n, -np.inf)  # f(v) + the largest bound of a successor outside S
            np.maximum.at(E, src[out], f[src[out]] + frames[ab.succ[out]])
            R = np.where(S, E - lo / step, -np.inf)
            inside = S[src] & S[ab.succ]
            for _ in range(max_rounds):
                nxt = R.copy()
                vals = np.where(inside, R[ab.succ], -np.inf)
                nxt[rows] = np.maximum(nxt[rows], np.maximum.reduceat(vals, starts))
                if np.array_equal(nxt, R):
                    break
                R = nxt
            else:
                continue  # not converged: no bound from this set
            bound = np.where(S & np.isfinite(R), hi / step + R, np.inf)
            frames = np.minimum(frames, np.floor(bound + 1e-9))  # a count of frames: a whole number below the bound
    return frames


def _extent(ab: Abstraction) -> np.ndarray:
    """`(nodes, J)`: the largest `d_j·p` over each node's cell (its support on the support directions)."""
    boxes = np.repeat(ab.grid.boxes(), ab.modes, axis=0)
    return (np.maximum(boxes[:, 0:1] * DIRS[:, 0], boxes[:, 1:2] * DIRS[:, 0])
            + np.maximum(boxes[:, 2:3] * DIRS[:, 1], boxes[:, 3:4] * DIRS[:, 1]))
