"""Funnels through free space (pipeline/bracket/funnel.py, docs/bracket.md "Funnels"): the one-frame ball map and the
free region checked against the law itself (sampling), and the start cells certified through funnels run by the
ordinary simulator (`pipeline.sim.simulate`) with this suite's own error signals."""

from __future__ import annotations

import dataclasses
import functools

import numpy as np
import pytest
from budget import examples  # tests/budget.py: more examples under make test-explore
from hypothesis import given, settings
from hypothesis import strategies as st
from test_bracket_loop_that_runs import default_certificate, run_certified_points

from pipeline.bracket.bounds import Uniform
from pipeline.bracket.certify_loop import certified_starts, certify, funnel_starts
from pipeline.bracket.funnel import free, step_ball
from pipeline.control import CBFController, HybridController, Scene, SmoothController

SCENE = Scene(target=[40.0, 0.0], obstacles=[{"center": [0.0, 0.0], "radius": 4.0}])
P_T = SCENE.p_T


def _disc(rng, n, radius):
    ang = rng.uniform(0, 2 * np.pi, n)
    return radius * np.sqrt(rng.uniform(0, 1, n))[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)


@settings(max_examples=examples(60), deadline=None)
@given(x=st.floats(-50, 30), y=st.floats(-30, 30), rad=st.floats(0.0, 3.0), eps=st.floats(0.0, 2.0),
       s=st.floats(0.05, 2.0), turn=st.floats(0.0, 0.5), seed=st.integers(0, 2**16))
def test_one_frame_keeps_every_run_in_the_next_ball(x, y, rad, eps, s, turn, seed):
    """Every `p` of `B(c, rad)`, error `|e| <= eps` and direction turned from the attraction's by at most `turn` lands
    in `step_ball`'s ball (where the map is defined: `|c - p_T| - rad > max(eps, s)`). Without the error's term
    `s asin(ε/r)` the points pushed sideways leave it."""
    c = np.array([[x, y]])
    r_lo = np.hypot(*(c[0] - P_T)) - rad
    if r_lo <= max(eps, s) + 1e-6:
        return
    nxt, rn = step_ball(c, np.array([rad]), np.array([eps]), P_T, s, turn)
    rng = np.random.default_rng(seed)
    n = 400
    p = c + _disc(rng, n, rad)
    e = _disc(rng, n, eps)
    e[: n // 4] *= eps / np.maximum(np.hypot(*e[: n // 4].T), 1e-300)[:, None]  # on the error's edge
    v = P_T - (p + e)
    ang = np.arctan2(v[:, 1], v[:, 0]) + turn * rng.choice([-1.0, 1.0, rng.uniform(-1, 1)], n)
    p1 = p + s * np.stack([np.cos(ang), np.sin(ang)], 1)
    assert (np.hypot(*(p1 - nxt[0]).T) <= rn[0] + 1e-9).all()


def test_the_error_term_is_needed():
    """A start point on the axis, the error across it: the run leaves `B(F(c), rad)` sideways (the mutation
    `rad' = rad`; a ball of radius 0, since the attraction itself draws the ball's sides together)."""
    c, rad, eps, s = np.array([[-40.0, 0.0]]), 0.0, 1.0, 0.5
    nxt, rn = step_ball(c, np.array([rad]), np.array([eps]), P_T, s)
    p = c.copy()
    v = p + np.array([0.0, eps]) - P_T
    p1 = p - s * v / np.hypot(*v.T)[:, None]
    assert np.hypot(*(p1[0] - nxt[0])) > rad
    assert np.hypot(*(p1[0] - nxt[0])) <= rn[0]


@pytest.mark.parametrize("law", [HybridController(SCENE), SmoothController(SCENE), CBFController(SCENE)],
                         ids=["hybrid", "smooth", "cbf"])
def test_the_free_region_is_the_attraction_turned_by_at_most_turn(law):
    """Where `free` holds over a ball, every sampled perceived point of it gets from the law (the flow map through the
    guard) a velocity of norm `u_max` within the angle `turn` of `(p_T - m)/|p_T - m|`, and no jump; balls are drawn
    everywhere, near the wedges and the discs too (the barrier's layer included)."""
    rng = np.random.default_rng(3)
    period = 0.05
    c = np.stack([rng.uniform(-50, 35, 6000), rng.uniform(-30, 30, 6000)], 1)
    rad = rng.uniform(0, 3, 6000)
    checked, turned = 0, 0
    for q in (1, 2) if law.hybrid else (1,):
        ok, turn = free(law, q, c, rad, period)
        rows = np.repeat(np.flatnonzero(ok), 8)
        m = c[rows] + _disc(rng, len(rows), 1.0) * rad[rows, None]
        xd = {"i": np.zeros(len(m), np.int64), "q": np.full(len(m), q, np.int8)} if law.hybrid else \
            {"q": np.full(len(m), q, np.int8)}
        ev = law.evaluate(m, xd)
        u = law.flow_map(m, xd, ev=ev)
        if law.hybrid:
            assert not law.jump_set(m, xd, ev=ev).any()
            u, acted = law.hold(u, m, xd, ev, period)
            assert not acted.any()
        assert np.abs(np.hypot(*u.T) - law.u_max).max() < 1e-9
        want = (P_T - m) / np.hypot(*(P_T - m).T)[:, None]
        angle = np.arccos(np.clip(np.einsum("ij,ij->i", u / law.u_max, want), -1.0, 1.0))
        assert (angle <= turn[rows] + 1e-7).all(), (angle - turn[rows]).max()
        checked += len(m)
        turned += int((turn[rows] > 1e-6).sum())
    assert checked > 1000 and (turned > 100 or isinstance(law, CBFController)), (checked, turned)


@functools.lru_cache(maxsize=4)  # the hybrid law's at 0.5 serves two tests (on one worker: computed once)
def _funnel_cells(law, eps, funnels=True):
    from pipeline.bracket.stage import objects
    from pipeline.bracket.starts import start_cells
    from pipeline.config import compose

    scene, laws, bs, sim_cfg, camera, _, _, lost = objects(compose("bracket", []))
    law = laws[law]
    n_frames = int(round(sim_cfg.horizon / camera.period))
    cert = certify(law, Uniform(eps), h=bs.cell, angle=bs.angle, period=camera.period, goal_radius=bs.goal_radius,
                   n_split=bs.n_split, window=bs.window, frames=bs.frames, horizon=n_frames, lost=lost[law.name],
                   funnels=funnels)
    starts = start_cells(scene, bs.start_cell)
    return scene, law, bs, sim_cfg, camera, cert, starts, n_frames


@pytest.mark.parametrize("name", ["hybrid", "smooth"])
def test_start_cells_certified_through_funnels_hold_in_the_simulator(name, tmp_path_factory, worker_id):
    """`make bracket`'s settings at ε = 0.5: the funnels (of the abstraction's nodes, then of start cells' sub-squares)
    certify start cells the abstraction alone does not (behind the obstacle for the hybrid law), and 6 random accepted
    points of each, run by `pipeline.sim.simulate` under this suite's error signals (random directions, a constant
    bias, §3.5's direction, a flipping bias), reach the goal disc by their certified bound without a collision."""
    eps = 0.5
    alone = default_certificate(tmp_path_factory, worker_id, name, eps)  # the same settings, funnels=False
    scene, law, bs, sim_cfg, camera, cert, starts, n_frames = _funnel_cells(name, eps)
    before = certified_starts(alone, starts)[0]
    by_nodes = certified_starts(cert, starts)[0]
    ok, bound, _, by_funnel = funnel_starts(cert, law, starts, bs.funnel_split, camera.period, n_frames)
    assert by_nodes[before].all() and ok[by_nodes].all() and (by_funnel == (ok & ~by_nodes)).all()
    new = ok & ~before
    assert new.sum() >= 10, new.sum()
    assert (bound[ok] <= n_frames).all()
    cells = np.repeat(np.flatnonzero(new), 6)
    run_certified_points(scene, law, starts, cells, bound, horizon=sim_cfg.horizon, delta=bs.goal_radius,
                         period=camera.period, eps=eps, rng=np.random.default_rng(21), seed=9)


def test_seeded_nodes_are_winning_sinks():
    """`win` with seeds: a seeded node is in `Win` with its bound and its own edges are not followed (a node whose
    only successor is a seeded node of a cycle wins with one frame more)."""
    from pipeline.bracket.abstraction import Abstraction, Grid
    from pipeline.bracket.enclosures import DIRS
    from pipeline.bracket.winning import win

    grid = Grid(0.0, 0.0, 1.0, 4, 1)  # cell 0 the goal; 1 <-> 2 a cycle; 3 -> 2
    U = np.zeros((4, 1, len(DIRS)))
    succ = [np.array([2]), np.array([1]), np.array([2])]
    indptr = np.concatenate([[0, 0], np.cumsum([len(x) for x in succ])])
    ab = Abstraction(grid, 1, U, np.ones(4, bool), np.arange(4) == 0, indptr, np.concatenate(succ),
                     np.ones((4, 1), bool))
    W, _, frames = win(ab, 0.05, np.array([0.5, 0.5]))
    assert not W[1:].any()
    W, _, frames = win(ab, 0.05, np.array([0.5, 0.5]), seeds=np.array([np.inf, np.inf, 7.0, np.inf]))
    assert W.tolist() == [True, True, True, True] and frames.tolist() == [0.0, 8.0, 7.0, 8.0]


def test_a_funnel_hands_off_only_to_winning_nodes():
    """With `Win` emptied outside the goal, no funnel hands off (they end before the goal disc: the attraction
    saturates only beyond it), so nothing more is certified; with the real `Win` it certifies cells."""
    _, law, bs, _, camera, cert, starts, n_frames = _funnel_cells("hybrid", 0.5)
    goal = np.repeat(cert.abstraction.goal, cert.abstraction.modes)
    cert = dataclasses.replace(cert, won=cert.won & goal)  # a copy: the cached certificate serves another test
    ok, _, _, by_funnel = funnel_starts(cert, law, starts, bs.funnel_split, camera.period, n_frames)
    assert not by_funnel.any()


@settings(max_examples=examples(80), deadline=None)
@given(x=st.floats(-3.0, 3.0), y=st.floats(-3.0, 3.0), rad=st.floats(0.0, 2.0), h=st.sampled_from([1.0, 0.125]),
       seed=st.integers(0, 2**16))
def test_a_ball_meets_exactly_the_cells_it_lists(x, y, rad, h, seed):
    """`_cells_of_ball` lists the cells whose closed square lies within `rad` of the centre: every sampled point of
    the ball (its boundary included) lies in a listed cell, every listed cell is that close, and none lies outside the
    ball's bounding square (the rule before, which listed the square's corners' cells too)."""
    from pipeline.bracket.abstraction import Grid
    from pipeline.bracket.funnel import _cells_of_ball

    grid = Grid(-6.0, -6.0, h, int(12 / h), int(12 / h))
    width = int(np.ceil(2 * rad / h)) + 2
    cells, over = _cells_of_ball(grid, np.array([[x, y]]), np.array([rad]), width)
    assert not over[0]
    listed = set(cells[0][cells[0] >= 0].tolist())
    rng = np.random.default_rng(seed)
    ang = rng.uniform(0, 2 * np.pi, 400)
    r = rad * np.sqrt(rng.uniform(0, 1, 400))
    r[:100] = rad  # the boundary too
    pts = np.stack([x + r * np.cos(ang), y + r * np.sin(ang)], 1)
    ix = np.floor((pts[:, 0] - grid.x0) / h).astype(int)
    iy = np.floor((pts[:, 1] - grid.y0) / h).astype(int)
    assert set((ix * grid.ny + iy).tolist()) <= listed
    boxes = grid.boxes()[sorted(listed)]
    dx = np.maximum(np.maximum(boxes[:, 0] - x, x - boxes[:, 1]), 0.0)
    dy = np.maximum(np.maximum(boxes[:, 2] - y, y - boxes[:, 3]), 0.0)
    assert (np.hypot(dx, dy) <= rad + 1e-6).all()
    assert (boxes[:, 1] >= x - rad - 1e-9).all() and (boxes[:, 0] <= x + rad + 1e-9).all()


def test_arrival_bounds_follow_the_edges_after_the_seeds(monkeypatch):
    """`win` takes a funnel's seed as it is (its node's edges not followed); once the window has won its successors
    the edges may give less. After :func:`relax_frames` every node of `Win` whose successors all are in `Win` has a
    bound at most its edges' frames plus their largest bound (the named tuning `wide_barrier`, cells of 1.5, ε = 0.5:
    the window and the funnels both at work), more start cells fit the horizon than without it, and random accepted
    points of the cells it brought under the horizon reach the goal disc by their new bound in the simulator."""
    import pipeline.bracket.certify_loop as loop_mod
    from pipeline.bracket.stage import objects
    from pipeline.bracket.starts import start_cells
    from pipeline.config import compose

    scene, laws, bs, sim_cfg, camera, _, _, lost = objects(compose("bracket", ["tuning=wide_barrier"]))
    law = laws["hybrid"]
    n_frames = int(round(sim_cfg.horizon / camera.period))
    kw = dict(h=1.5, angle=bs.angle, period=camera.period, goal_radius=bs.goal_radius, n_split=bs.n_split,
              window=bs.window, frames=bs.frames, horizon=n_frames, lost=lost["hybrid"], funnels=True,
              refine_half=10.0, refine_factor=4)
    cert = certify(law, Uniform(0.5), **kw)
    ab, W, F = cert.abstraction, cert.won, cert.node_frames
    f = np.where(ab.multi, ab.frames, 1)
    deg = np.diff(ab.indptr)
    rows = np.flatnonzero(W & (deg > 0) & (F > 0))
    worst = np.maximum.reduceat(F[ab.succ], ab.indptr[np.flatnonzero(deg > 0)])[np.searchsorted(np.flatnonzero(deg > 0), rows)]
    assert (F[rows] <= f[rows] + worst + 1e-9).all(), (F[rows] - f[rows] - worst).max()
    monkeypatch.setattr(loop_mod, "relax_frames", lambda ab, W, frames: frames)
    loose = certify(law, Uniform(0.5), **kw)
    assert (loose.won == W).all() and (F <= loose.node_frames).all()
    starts = start_cells(scene, bs.start_cell)
    ok, bound, _ = certified_starts(cert, starts)
    before = certified_starts(loose, starts)[0]
    assert ok[before].all() and (ok & ~before).sum() >= 2, (ok & ~before).sum()
    cells = np.repeat(np.flatnonzero(ok & ~before), 6)
    run_certified_points(scene, law, starts, cells, bound, horizon=sim_cfg.horizon, delta=bs.goal_radius,
                         period=camera.period, eps=0.5, rng=np.random.default_rng(5), seed=11)
