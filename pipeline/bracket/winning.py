"""The winning set of the abstraction (SPEC §5.4): the least fixed point with the transience rule.

`win(abs, period, p_T)`: strongly connected components of the safe non-goal nodes by Tarjan's algorithm
(iterative; it emits components sinks first), each decided once in that order: in `Win` when every successor
outside it is in `Win` and it is a single node without a self-loop or transient (:func:`rates`).
"""

from __future__ import annotations

import numpy as np

from pipeline.bracket.abstraction import Abstraction
from pipeline.bracket.enclosures import DIRS, support_at

J = len(DIRS)


RATE_DIRS = 24 * J  # candidate directions of the transience rule (the support directions among them)


def rates(ab: Abstraction, period: float, p_T: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per node: `dir_ok` `(nodes, RATE_DIRS)` (`w_k·u < 0` for every input, `w_k` at `k · 360°/RATE_DIRS`: `w_k·p`
    decreases every frame; between two support directions bounded by :func:`support_at`, so a direction a
    polytope's support function does not itself list counts only where that upper bound is negative) and
    `lyap_ok` `(nodes,)` (`|p - p_T|²` decreases over every frame from every point of the cell:
    `2 (p - p_T)·u + T_s |u|² < 0`)."""
    U = ab.U.reshape(-1, J)
    W = np.stack([np.cos(2 * np.pi * np.arange(RATE_DIRS) / RATE_DIRS),
                  np.sin(2 * np.pi * np.arange(RATE_DIRS) / RATE_DIRS)], axis=1)
    C = support_at(np.eye(J)[:, None, :], W)  # (J, RATE_DIRS): w_k's bound a h_j + b h_{j+1} as a linear map of h
    with np.errstate(invalid="ignore"):  # (a +inf support times a zero coefficient: nan, not decreasing)
        dir_ok = np.where(np.isneginf(U), -1.0, U) @ C < 0  # a node without inputs (-inf): every direction decreases
    dir_ok[:, :: RATE_DIRS // J] = U < 0  # the support directions themselves, exactly
    boxes = np.repeat(ab.grid.boxes(), ab.modes, axis=0)
    r = np.maximum(U, 0).max(axis=1) / np.cos(np.pi / J)  # |u| <= r
    worst = np.full(len(U), -np.inf)
    for cx, cy in ((0, 2), (1, 2), (1, 3), (0, 3)):  # h_U convex: the largest (p - p_T)·u at a corner
        x = np.stack([boxes[:, cx], boxes[:, cy]], axis=1) - p_T
        worst = np.maximum(worst, support_at(U, x))
    lyap_ok = 2 * worst + period * r * r < 0
    if ab.multi is not None:
        lyap_ok &= ~ab.multi  # an edge over several frames leaves P: the bound above is on P only
    return dir_ok, lyap_ok


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


def win(ab: Abstraction, period: float, p_T: np.ndarray) -> tuple[np.ndarray, dict]:
    """`Win` `(nodes,)` and counts (components, transient ones and by which rule)."""
    n = len(ab.safe)
    goal = np.repeat(ab.goal, ab.modes)
    W = goal.copy()
    active = ab.safe & ~goal
    dir_ok, lyap_ok = rates(ab, period, p_T)
    comps = tarjan(n, ab.indptr, ab.succ, active)
    stats = {"components": len(comps), "transient_direction": 0, "transient_distance": 0, "won_components": 0}
    member = np.full(n, -1, np.int64)
    for ci, comp in enumerate(comps):
        member[comp] = ci
        outs = np.concatenate([ab.succ[ab.indptr[v]:ab.indptr[v + 1]] for v in comp])
        internal = member[outs] == ci
        if not W[outs[~internal]].all():
            continue
        if internal.any():
            if dir_ok[comp].all(axis=0).any():
                stats["transient_direction"] += 1
            elif lyap_ok[comp].all():
                stats["transient_distance"] += 1
            else:
                continue
        W[comp] = True
        stats["won_components"] += 1
    return W, stats


def certified_cells(ab: Abstraction, W: np.ndarray) -> np.ndarray:
    """Start cells whose every possible initial node is in `Win` `(cells,)`."""
    Wc = W.reshape(-1, ab.modes)
    return (~ab.initial | Wc).all(axis=1) & ab.initial.any(axis=1)
