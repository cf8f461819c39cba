"""The logic states of the abstraction's nodes and the frame decisions between them (SPEC §3.3, §3.6, §5.4).

A node is `(P, k)`: the cell and the logic state after the frame's decision. The smooth laws have one (`k = 0`);
the hybrid law has `k = 2 i + (q - 1)`: `i` the active obstacle (SPEC §3.6's locally active obstacle; one obstacle:
`i = 0`, and this is :func:`pipeline.bracket.abstraction.decisions` alone) and `q` its mode. On the perceived box
`M` of a cell a frame in state `(i, q)` may (one jump per frame, :func:`pipeline.hybrid.sampled.frame_update`):

- stay in `(i, q)`, or jump the mode to `(i, 3 - q)` (the interval tests of `decisions` on obstacle `i`), unless a
  cell jump is certain there;
- jump the cell: `dist_i(m) >= min_j dist_j(m) + h` (`dist_j = |m - c_j| - R_j`, the hysteresis `h`) possible on
  `M`, to every `(j, q')` with `j` possibly the nearest (`argmin_j dist_j`) and `q'` possibly the mode with the
  smaller `V_j^q` there (ties below `b = 0`: 1).

Each test is an interval bound over the box, so the edges are a superset of what the law can do (sound). Nodes
`(P, i, ·)` where `i` can be neither kept nor jumped to (nor kept by a lost frame) are unreachable: no input is
computed for them and they are unsafe.
"""

from __future__ import annotations

import numpy as np

from pipeline.bracket.enclosures import DIRS, affine_range, barrier_range, dist_range, split
from pipeline.bracket.inputs import law_kind, support


def first_modes(law, boxes: np.ndarray, obstacle: int = 0) -> np.ndarray:
    """`(N, 2)`: the modes a run can take on entering obstacle `obstacle`'s logic from a perceived box (its initial
    state, or a cell jump): the smaller `V_q` (the smaller barrier: `φ` is common), ties to `q = 1` below `b = 0`
    (SPEC §3.3, :meth:`HybridController.initial_state`, :meth:`HybridController.jump_map`)."""
    cov = law.scene.covering(obstacle)
    (l1, h1), (l2, h2) = barrier_range(boxes, cov, 1), barrier_range(boxes, cov, 2)
    b_lo, b_hi = affine_range(boxes, cov.e_b, -cov.e_b @ cov.p_0)
    tie = (l1 <= h2) & (l2 <= h1)
    return np.stack([(l1 < h2) | (tie & (b_lo < 0)), (l2 < h1) | (tie & (b_hi >= 0))], axis=1)


def decisions(law, boxes: np.ndarray, obstacle: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`(stay, jump)` `(N, 2)`: on perceived boxes, whether a frame in mode `q` (column `q - 1`) can stay / jump.

    SPEC §3.3: jump iff `V_q >= f V_o` (`f = χ - λ`), `V_q > 0`, `V_o` finite. With `V = B + φ` (`φ = |m - p_T|²`
    the same in both modes) that is `B_q - f B_o >= (f - 1) φ`: bounded with `B_q, B_o, φ` intervals separately,
    so that far from both wedges (`B = 0`) no jump is possible, as for the law itself. `obstacle`: the active
    obstacle whose covering decides (several obstacles, SPEC §3.6).
    """
    cov = law.scene.covering(obstacle)
    Bq = [barrier_range(boxes, cov, q) for q in (1, 2)]
    phi_lo, phi_hi = (d**2 for d in dist_range(boxes, cov.p_T))
    f = law.chi - law.lam
    stay, jump = np.zeros((len(boxes), 2), bool), np.zeros((len(boxes), 2), bool)
    for q in (1, 2):
        (q_lo, q_hi), (o_lo, o_hi) = Bq[q - 1], Bq[2 - q]
        with np.errstate(invalid="ignore"):
            can = np.isinf(q_hi) | (q_hi - f * o_lo >= (f - 1) * phi_lo)
            jump[:, q - 1] = can & np.isfinite(o_lo) & ((q_hi > 0) | (phi_hi > 0))
            surely = np.isfinite(o_hi) & (np.isinf(q_lo) | (q_lo - f * o_hi >= (f - 1) * phi_hi)) & (phi_lo > 0)
        stay[:, q - 1] = ~surely
    return stay, jump


def initial_modes(law, boxes: np.ndarray, obstacle: int = 0, n_split: int = 1) -> np.ndarray:
    """`(N, 2)`: modes a run can hold after frame 0 from a perceived box: the smaller `V_q` (the smaller barrier:
    `φ` is common), ties to `q = 1` below `b = 0` (SPEC §3.3, :meth:`HybridController.initial_state`), then frame
    0's jump (of the active obstacle `obstacle`). `n_split > 1`: the tests on `n_split²` sub-boxes of each box, a
    mode possible where it is on one of them (the interval bounds of one perceived point's choice, tighter than
    the whole box's, which pair one point's `B_1` with another's `B_2`)."""
    n = len(boxes)
    if n_split > 1:
        boxes = split(boxes, n_split).reshape(-1, 4)
    q0 = first_modes(law, boxes, obstacle)
    stay, jump = decisions(law, boxes, obstacle)
    out = q0 & stay
    out[:, 0] |= q0[:, 1] & jump[:, 1]
    out[:, 1] |= q0[:, 0] & jump[:, 0]
    return out.reshape(n, -1, 2).any(axis=1)


def cell_ranges(law, boxes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`(leave, must, nearest)` `(N, M)` on perceived boxes: a cell jump away from `i` is possible / certain, and
    `i` may be `argmin_j dist_j` (the target of a cell jump, the initial obstacle)."""
    arr = law.scene.arrays
    ranges = [dist_range(boxes, c) for c in arr["center"]]
    lo = np.stack([r[0] for r in ranges], axis=1) - arr["R"]
    hi = np.stack([r[1] for r in ranges], axis=1) - arr["R"]
    n = lo.shape[1]
    others_lo = np.stack([np.delete(lo, i, axis=1).min(axis=1) for i in range(n)], axis=1)
    others_hi = np.stack([np.delete(hi, i, axis=1).min(axis=1) for i in range(n)], axis=1)
    leave = hi >= others_lo + law.h  # some m, some j != i: dist_i(m) - dist_j(m) >= h
    must = lo >= others_hi + law.h   # some j != i with dist_i >= dist_j + h on the whole box
    nearest = lo <= hi.min(axis=1, keepdims=True)
    return leave, must, nearest


class Modes:
    """The logic states of `law`'s nodes on the perceived boxes `M` of the cells (module docstring): their number,
    the held inputs' supports, the initial states, and the successors' states per endpoint cell."""

    def __init__(self, law, M: np.ndarray, keep_mode: bool = False):
        self.law, self.M, self.keep_mode = law, M, bool(keep_mode)
        self.hybrid = law_kind(law) == "hybrid"
        self.n_obs = law.scene.n_obstacles if self.hybrid else 1
        self.modes = 2 * self.n_obs if self.hybrid else 1
        n = len(M)
        if not self.hybrid:
            self.stay = self.jump = None
            self.initial = np.ones((n, 1), bool)
            self.relevant = np.ones((n, 1), bool)
            return
        per = [decisions(law, M, i) for i in range(self.n_obs)]
        self.stay = np.concatenate([s for s, _ in per], axis=1)  # (N, modes), column 2 i + q - 1
        self.jump = np.concatenate([j for _, j in per], axis=1)
        if self.n_obs == 1:
            self.leave = self.must = np.zeros((n, 1), bool)
            self.nearest = np.ones((n, 1), bool)
            self.initial = initial_modes(law, M)
            self.first = None
        else:
            self.leave, self.must, self.nearest = cell_ranges(law, M)
            self.first = np.concatenate([first_modes(law, M, i) for i in range(self.n_obs)], axis=1)
            self.initial = np.concatenate([initial_modes(law, M, i) & self.nearest[:, [i]]
                                           for i in range(self.n_obs)], axis=1)
        self.relevant = np.repeat(~self.must | self.nearest | self.keep_mode, 2, axis=1)  # a lost frame keeps i

    def obstacle(self, k: int) -> int:
        return k // 2 if self.hybrid else 0

    def inputs(self, period: float, n_split: int) -> np.ndarray:
        """`(N, modes, J)` supports of the held input per node (0 on the unreachable nodes: they are unsafe)."""
        out = []
        for k in range(self.modes):
            rows = np.flatnonzero(self.relevant[:, k])
            if len(rows) == len(self.M):
                out.append(support(self.law, self.M, k % 2 + 1, period, n_split, obstacle=self.obstacle(k)))
                continue
            U = np.zeros((len(self.M), len(DIRS)))
            if len(rows):
                U[rows] = support(self.law, self.M[rows], k % 2 + 1, period, n_split, obstacle=self.obstacle(k))
            out.append(U)
        return np.stack(out, axis=1)

    def no_jump(self, k: int) -> np.ndarray:
        """`(N,)`: cells where a frame in state `k` keeps it (a multi-frame edge may cross them)."""
        if not self.hybrid:
            return np.ones(len(self.M), bool)
        return ~self.jump[:, k] & ~self.leave[:, self.obstacle(k)]

    def successors(self, k: int, c: np.ndarray) -> list[tuple[np.ndarray, int]]:
        """For endpoint cells `c` of edges from state `k`: `(mask over c, next state)` pairs."""
        if not self.hybrid:
            return [(np.ones(len(c), bool), 0)]
        i = self.obstacle(k)
        kept = ~self.must[c, i]
        pairs = [((self.stay[c, k] & kept) | self.keep_mode, k), (self.jump[c, k] & kept, k ^ 1)]
        if self.n_obs > 1:
            leave = self.leave[c, i]
            for j in range(self.n_obs):
                if j != i:
                    for q in (0, 1):
                        pairs.append((leave & self.nearest[c, j] & self.first[c, 2 * j + q], 2 * j + q))
        return pairs
