"""Funnels in free space (SPEC §5.4, docs/bracket.md "Funnels"): runs followed frame by frame as a ball while the law
is nearly the saturated attraction, and handed to the abstraction where they enter winning nodes.

The abstraction's cells lose where a run is: over a long flight to the obstacle, abstract paths drift sideways by
about a cell per edge, so from far behind the obstacle they reach the back vertex, where nothing is certified,
though the runs themselves pass it by many units. A funnel keeps the set of positions as a ball `B(c_k, ρ_k)`:

- **The free region** (:func:`free`). Every perceived point `m` of `B(c_k, ρ_k + ε)` gets the velocity `u_max v`, `v`
  a unit vector within the angle `turn` of `(p_T - m)/|p_T - m|`: the hybrid law off the guard's range from the
  mode's wedge `W_q` (no guard, no push-out), its barrier's term `k ∇B` bounded as a turn of the attraction and the
  mode kept (`B_q < (χ - λ - 1) φ`: no jump); the smooth law outside its margin discs, the same turn; the CBF filter
  where every constraint is inactive at `u_nom` (a quadratic bounded below over the ball; no turn). Each held segment
  stays off every obstacle disc and inside the arena.
- **One frame** (:func:`step_ball`). The map `F(p) = p - s (p - p_T)/|p - p_T|` (`s = u_max T_s`) is 1-Lipschitz where
  `|p - p_T| >= s` (its Jacobian `I - (s/r)(I - e_r e_r^T)` has eigenvalues 1 and `1 - s/r`); the error turns the
  direction by at most `asin(ε/r)` and the barrier by at most `turn`, so `c' = F(c)`,
  `ρ' = ρ + s (asin(ε/r_lo) + turn)` (`r_lo = |c - p_T| - ρ`).
- **The hand-off.** At a frame `k` where the ball's grid cells (every cell meeting the ball, in the abstraction's
  frame) are all in `Win` in the funnel's mode, every run is in a winning node at that frame instant (the frame's
  decision keeps the mode: the perceived ball is free): it arrives within `k + max frames(node)` frames. Inside the
  back vertex's refined window the fine cells meeting the ball do the same with the fine `Win`'s bounds (the same
  node semantics, :class:`pipeline.bracket.refine.FineWin`), and the smaller of the two bounds is taken. The funnel
  takes the smallest such bound over its frames.

Used for the abstraction's nodes (:func:`node_funnels`: a node whose cell's funnel hands off joins `Win`) and for
the start cells' sub-squares (:func:`pipeline.bracket.certify_loop.funnel_starts`). `ε` over a ball: the largest
per-cell bound of the certificate over the cells meeting it (with lost frames: the stale bound, as the abstraction's;
a stop of the predicting gate is not modelled here and turns funnels off). One obstacle: on a field of several no
law gets funnels (the hybrid law's locally active obstacle is not followed, and the laws are compared by one method).
"""

from __future__ import annotations

import numpy as np

from pipeline.bracket.enclosures import barrier_value, bp_barrier_g
from pipeline.control import CBFController, HybridController, SmoothController
from pipeline.control.covering import wedge_coords

TOL = 1e-9  # world units: margins of the free-region tests (no directed rounding, as the abstraction)


def _wedge_dist(cov, q: int, c: np.ndarray) -> np.ndarray:
    """Distance from each point to the wedge `W_q` (1-Lipschitz: over a ball at least this less its radius)."""
    u, v = wedge_coords(cov, q, c)
    return np.hypot(np.minimum(u, 0.0), np.minimum(v, 0.0))


def free(law, q: int, c: np.ndarray, rad: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """`(ok, turn)`: whether every perceived point `m` of `B(c, rad)` gets from `law` in mode `q` (frames every
    `period`) a velocity of norm `u_max` within the angle `turn` of the attraction's direction `(p_T - m)/|p_T - m|`,
    without a jump, a push-out or the guard. The barrier's term `k ∇B` (norm `g(D) d <= g(d_lo²) reach`, `g` of
    :func:`pipeline.bracket.enclosures.bp_barrier_g` decreasing) turns the attraction `-2 k w (m - p_T)` by at most
    `asin(G / (2 k w r))`; the hybrid law keeps its mode where `B_q <= B(d_lo²) < (χ - λ - 1) w r²` (then
    `V_q < (χ - λ) V_{3-q}`) and stays off the guard's range; the CBF filter is free where every constraint is
    inactive at `u_nom` (a quadratic bounded below over the ball)."""
    arr = law.scene.arrays
    cov = law.scene.covering(0)
    r = np.hypot(*(c - law.scene.p_T).T) - rad  # |m - p_T| >= r
    a = gain(law) * r  # |attraction| >= a
    G = np.zeros(len(c))
    ok = np.ones(len(c), bool)
    bar = (law.k, cov.barrier_gain, cov.barrier_rho, cov.ell)
    if isinstance(law, HybridController):
        d = _wedge_dist(cov, q, c) - rad
        ok &= d > (law.u_max * period / (1.0 - law.gamma) if law.guard else 0.0) + TOL
        D = np.maximum(d, TOL) ** 2
        G = np.where(d < cov.barrier_reach, bp_barrier_g(D, *bar) * cov.barrier_reach, 0.0)
        ok &= barrier_value(D, *bar[1:]) < (law.chi - law.lam - 1.0) * cov.phi_weight * np.maximum(r, 0.0) ** 2
    else:
        for centre, rr, reach in zip(arr["center"], arr["radius"], arr["reach"]):
            if isinstance(law, SmoothController):
                d = np.hypot(*(c - centre).T) - rad - 2.0 * rr
                ok &= d > TOL
                G = G + np.where(d < reach, bp_barrier_g(np.maximum(d, TOL) ** 2, *bar) * reach, 0.0)
            else:  # CBF: f(m) = -2k (m - c)·(m - p_T) + α (|m - c|² - 4 r²) >= 0 leaves u_nom feasible, hence optimal
                k, al = law.k, law.alpha
                x, t = c - centre, c - law.scene.p_T
                f = -2 * k * np.einsum("ij,ij->i", x, t) + al * (np.einsum("ij,ij->i", x, x) - 4 * rr * rr)
                grad = -2 * k * (x + t) + 2 * al * x
                ok &= f - np.hypot(*grad.T) * rad + min(0.0, al - 2 * k) * rad**2 > TOL * (1 + np.abs(f))
    ok &= np.isfinite(G) & (a - G > law.u_max + TOL)  # saturated, and the turn below is < 90°
    return ok, np.where(ok, np.arcsin(np.clip(G / np.maximum(a, TOL), 0.0, 1.0)), np.pi)


def gain(law) -> float:
    """`g` of the attraction `-g (m - p_T)` before saturation."""
    return law.k if isinstance(law, CBFController) else 2.0 * law.k * law.scene.covering(0).phi_weight


def _cells_of_ball(grid, g: np.ndarray, rad: np.ndarray, width: int):
    """Cells of `grid` meeting balls `B(g, rad)` (grid frame; a cell's closed square within `rad` of the centre):
    `(N, width²)` indices, -1 where none; and rows whose bounding square overflows the grid or `width` cells."""
    lo_x = np.floor((g[:, 0] - rad - grid.x0) / grid.h).astype(np.int64)
    hi_x = np.floor((g[:, 0] + rad - grid.x0) / grid.h).astype(np.int64)
    lo_y = np.floor((g[:, 1] - rad - grid.y0) / grid.h).astype(np.int64)
    hi_y = np.floor((g[:, 1] + rad - grid.y0) / grid.h).astype(np.int64)
    over = (lo_x < 0) | (lo_y < 0) | (hi_x >= grid.nx) | (hi_y >= grid.ny) | (hi_x - lo_x >= width) | \
        (hi_y - lo_y >= width)
    ox, oy = np.meshgrid(np.arange(width), np.arange(width), indexing="ij")
    ix, iy = lo_x[:, None] + ox.ravel(), lo_y[:, None] + oy.ravel()
    x, y = grid.x0 + ix * grid.h, grid.y0 + iy * grid.h  # the cells' lower corners: their distance to the centre
    dx = np.maximum(np.maximum(x - g[:, :1], g[:, :1] - x - grid.h), 0.0)
    dy = np.maximum(np.maximum(y - g[:, 1:], g[:, 1:] - y - grid.h), 0.0)
    meets = np.hypot(dx, dy) <= rad[:, None] + TOL
    inside = (ix <= hi_x[:, None]) & (iy <= hi_y[:, None]) & meets & ~over[:, None]
    return np.where(inside, ix * grid.ny + iy, -1), over


def step_ball(c: np.ndarray, rad: np.ndarray, eps: np.ndarray, p_T: np.ndarray, s: float, turn=0.0):
    """One frame from `B(c, rad)` (module docstring; valid where `|c - p_T| - rad > max(eps, s)`): the ball
    `B(c', rad')` holding every `p + s v`, `v` a unit vector within the angle `turn` of `(p_T - m)/|p_T - m|` for a
    perceived `m` within `eps` of `p` (the attraction saturated, turned by the barrier at most by `turn`)."""
    r = np.hypot(*(c - p_T).T)
    r_lo = r - rad
    nxt = c - s * (c - p_T) / r[:, None]
    return nxt, rad + s * (np.arcsin(np.minimum(1.0, eps / np.maximum(r_lo, TOL))) + turn) + TOL


def run_funnels(cert, law, centres: np.ndarray, rad0: float, q: int, period: float,
                horizon: float, tails: bool = False):
    """Per ball `B(centres_i, rad0)` (world) in mode `q`: the arrival bound in frames through its funnel (inf: none
    hands off within the horizon). `tails`: also, per ball, where its funnel ended without a hand-off (the ball
    `(c, ρ)` holding the runs at frame `k` in mode `q` before that frame's decision; `k` NaN where it handed off or
    ran out of the horizon), for :mod:`pipeline.bracket.polytope` to go on from."""
    p_T, s = law.scene.p_T, law.u_max * period
    (ax0, ax1), (ay0, ay1) = law.scene.bounds
    arr = law.scene.arrays
    c, rad = np.array(centres, float), np.full(len(centres), float(rad0))
    best = np.full(len(c), np.inf)
    alive = np.ones(len(c), bool)
    end_c, end_r, end_k = c.copy(), rad.copy(), np.full(len(c), np.nan)
    modes = cert.abstraction.modes
    node_frames = np.where(cert.won, cert.node_frames, np.inf).reshape(-1, modes)[:, q - 1]
    window = cert.fine
    for k in range(int(min(horizon, 10**6)) + 1):
        rows = np.flatnonzero(alive)
        if rows.size == 0:
            break
        cr, rr = c[rows], rad[rows]
        eps, handed = ball_max(cert, cr, rr, cert.eps_cells, node_frames)
        if window is not None:  # a ball inside the refined window: its fine cells' bounds (each sound: the smaller)
            handed = np.minimum(handed, ball_max(cert, cr, rr, window.frames[:, q - 1], grid=window.grid)[0])
        r_lo = np.hypot(*(cr - p_T).T) - rr
        fine, turn = free(law, q, cr, rr + eps, period)
        ok = np.isfinite(eps) & fine & (r_lo - eps > s + TOL)
        best[rows] = np.where(ok, np.minimum(best[rows], k + handed), best[rows])  # the frame's decision keeps q
        nxt, rn = step_ball(cr, rr, eps, p_T, s, turn)
        seg = rn + s  # the held segment lies in B(c_k, s + ρ_{k+1})
        clear = np.min([np.hypot(*(cr - ctr).T) - seg - r for ctr, r in zip(arr["center"], arr["radius"])], axis=0)
        ok &= (clear > TOL) & (nxt[:, 0] - rn > ax0) & (nxt[:, 0] + rn < ax1) & (nxt[:, 1] - rn > ay0) & \
            (nxt[:, 1] + rn < ay1) & (k < horizon)
        died = rows[~ok]
        end_c[died], end_r[died], end_k[died] = cr[~ok], rr[~ok], k
        c[rows], rad[rows] = nxt, rn
        alive[rows[~ok]] = False
    best = np.where(best <= horizon, best, np.inf)
    if tails:
        end_k[np.isfinite(best) | (end_k >= horizon)] = np.nan
        return best, (end_c, end_r, end_k)
    return best


def ball_max(cert, c: np.ndarray, rad: np.ndarray, *per_cell: np.ndarray, grid=None) -> list[np.ndarray]:
    """For balls `B(c, rad)` (world), the largest value of each per-cell array of `grid` (the certificate's, or
    another in its frame: the refined window's) over the cells meeting the ball (inf where the ball leaves it)."""
    grid = cert.grid if grid is None else grid
    rad = np.broadcast_to(np.asarray(rad, float), (len(c),))
    width = int(np.ceil(2 * rad.max() / grid.h)) + 2 if len(c) else 1
    cells, over = _cells_of_ball(grid, cert.frame.to_grid(c), rad, width)
    idx = np.maximum(cells, 0)
    return [np.where(over, np.inf, np.where(cells >= 0, v[idx], -np.inf).max(axis=1)) for v in per_cell]


def node_funnels(cert, law, period: float, horizon: float) -> np.ndarray:
    """Per node `(cell, q)` of the abstraction, the arrival bound in frames through the funnel of its cell's
    circumscribed ball in mode `q` (inf: none; nodes outside the view or in the goal: inf)."""
    ab = cert.abstraction
    centres = cert.frame.to_world(cert.grid.centres())
    out = np.full((cert.grid.n, ab.modes), np.inf)
    cells = np.flatnonzero(~ab.goal & (np.hypot(*(centres - law.scene.p_T).T) > law.u_max / gain(law)))
    for q in range(1, ab.modes + 1):
        safe = ab.safe.reshape(-1, ab.modes)[cells, q - 1]
        rows = cells[safe]
        out[rows, q - 1] = run_funnels(cert, law, centres[rows], cert.grid.h * np.sqrt(0.5), q, period, horizon)
    return out.ravel()
