"""Finer cells at the back vertex (pipeline/bracket/refine.py, docs/bracket.md "The back vertex, refined"): the pieces'
enclosures and speed floors against the law's own decided inputs (sampling, with mutations that must be caught), the
barrier's one-face range, and the window's certificate run by the ordinary simulator with this suite's error signals."""

from __future__ import annotations

import numpy as np
import pytest
from budget import examples  # tests/budget.py: more examples under make test-explore
from hypothesis import given, settings
from hypothesis import strategies as st
from test_bracket_loop_that_runs import run_certified_points

import pipeline.bracket.certify_loop as certify_loop
import pipeline.bracket.inputs as inputs
from pipeline.bracket.abstraction import build
from pipeline.bracket.bounds import Uniform
from pipeline.bracket.certify_loop import certified_starts, certify
from pipeline.bracket.enclosures import DIRS, bp_barrier_g, split
from pipeline.bracket.falsifier import Search, run_adversary
from pipeline.bracket.loop import REACHED, FrameLoop
from pipeline.bracket.starts import start_cells
from pipeline.control import HybridController, Scene, in_diamond

SCENE = Scene(target=[40.0, 0.0], obstacles=[{"center": [0.0, 0.0], "radius": 4.0}])
PERIOD = 0.05
N_SPLIT = 4


def _vertex_boxes(rng, n):
    """Perceived boxes of the refined window's size around the back vertex and along both back faces."""
    c = SCENE.covering(0).c
    t = rng.uniform(-4, 4, n)
    side = rng.choice([-1.0, 1.0], n)
    along = np.stack([-c + np.abs(t) * np.sqrt(0.5), side * t * np.sqrt(0.5)], 1)  # on a back face or its extension
    cen = along + rng.normal(0, 0.3, (n, 2))
    w = 10 ** rng.uniform(-1.5, -0.4, n)
    return np.stack([cen[:, 0] - w, cen[:, 0] + w, cen[:, 1] - w, cen[:, 1] + w], 1)


def _outside_pieces(law, boxes, rng, draws=12):
    """Sampled perceived points of each sub-box, both modes before the frame: the inputs outside both of their
    sub-box's pieces (flow, push-out) in the mode after the decision, and those below the piece's speed floor."""
    loop = FrameLoop(SCENE, law)
    pieces = {q: inputs.support(law, boxes, q, PERIOD, N_SPLIT, parts=True) for q in (1, 2)}
    subs = split(boxes, N_SPLIT)  # (N, S, 4)
    S = subs.shape[1]
    outside = slow = 0
    for before in (1, 2):
        for _ in range(draws):
            k = rng.integers(0, S, len(boxes))
            sb = subs[np.arange(len(boxes)), k]
            m = sb[:, [0, 2]] + rng.uniform(0, 1, (len(boxes), 2)) * (sb[:, [1, 3]] - sb[:, [0, 2]])
            after, u = loop.decided(m, {"q": np.full(len(m), before, np.int8), "i": np.zeros(len(m), np.int64)})
            for q in (1, 2):
                rows = np.flatnonzero(after["q"] == q)
                U, floor = pieces[q]
                proj = u[rows] @ DIRS.T
                fits = [(proj <= U[rows, j] + 1e-9).all(axis=1) & (np.hypot(*u[rows].T) >= floor[rows, j] - 1e-9)
                        for j in (k[rows], k[rows] + S)]
                inside = [(proj <= U[rows, j] + 1e-9).all(axis=1) for j in (k[rows], k[rows] + S)]
                outside += int((~(inside[0] | inside[1])).sum())
                slow += int(((inside[0] | inside[1]) & ~(fits[0] | fits[1])).sum())
    return outside, slow


def test_every_decided_input_lies_in_its_pieces_above_its_speed_floor():
    """The refined window's claim: a perceived point of sub-box `i` gives, in the mode after the frame's decision, an
    input inside sub-box `i`'s flow piece or push-out piece, of norm at least that piece's floor."""
    law = HybridController(SCENE)
    outside, slow = _outside_pieces(law, _vertex_boxes(np.random.default_rng(5), 1500), np.random.default_rng(6))
    assert outside == 0 and slow == 0


@pytest.mark.parametrize("mutation", ["floor", "push", "product"])
def test_the_piece_check_catches_a_loosened_rule(mutation, monkeypatch):
    """Mutations the sampling above must catch: a floor of `u_max` where the guard slows the approach, no push-out
    piece at all, the barrier's one-face range taken at the wrong ends."""
    if mutation == "floor":
        monkeypatch.setattr(inputs, "guard_floor", lambda floor, *a: floor)
    elif mutation == "push":
        monkeypatch.setattr(inputs, "wedge_ranges", _no_diamond(inputs.wedge_ranges))
    else:
        def wrong(c, mu, alone, k, cov):
            g = bp_barrier_g(mu[0] * mu[0], k, cov.barrier_gain, cov.barrier_rho, cov.ell)
            return np.where(alone, np.minimum(g * mu[0], -1e-9), c[0]), c[1]
        monkeypatch.setattr(inputs, "one_face", wrong)
    law = HybridController(SCENE)
    outside, slow = _outside_pieces(law, _vertex_boxes(np.random.default_rng(5), 1500), np.random.default_rng(6))
    assert outside + slow > 0


def _no_diamond(wedge_ranges):
    """`wedge_ranges` whose second call in `hybrid_support` (the other mode's wedge, for the diamond test) says the
    sub-box is never inside it: no push-out piece anywhere."""
    calls = {"n": 0}

    def patched(sub, cov, q):
        calls["n"] += 1
        out = wedge_ranges(sub, cov, q)
        if calls["n"] % 2 == 0:
            (u_lo, _), (v_lo, v_hi), du, dv = out
            return (u_lo, np.full_like(u_lo, -1.0)), (v_lo, v_hi), du, dv
        return out
    return patched


@settings(max_examples=examples(60), deadline=None)
@given(rho=st.floats(0.032, 1.0), d=st.lists(st.floats(1e-6, 20.0), min_size=2, max_size=2, unique=True),
       ell=st.floats(0.5, 20.0))
def test_the_barrier_term_on_one_face_decreases_with_the_distance(rho, d, ell):
    """`one_face`'s exact range rests on `d ↦ d g(d²)` decreasing (its docstring's proof): checked on random pairs."""
    lo, hi = sorted(d)
    g = [bp_barrier_g(np.array([x * x]), 1.0, 1.0, rho, ell)[0] * x for x in (lo, hi)]
    assert g[0] >= g[1] - 1e-9 * max(1.0, g[1])


def test_the_window_certifies_the_vertex_and_its_starts_survive_the_simulator(monkeypatch):
    """Without the window no start cell on the axis behind the obstacle is in `Win` (the vertex's component); with
    it (cells of 1/8 unit, ε = 0.1, no horizon) those within 7.5 units of the axis are, and 2 random accepted points
    of each, run by `pipeline.sim.simulate` under this suite's error signals for 100 s, and 2 more under the trap
    adversary aimed at the vertex, reach the goal disc by their certified bound without a collision."""
    law = HybridController(SCENE)
    kw = dict(h=1.0, angle=45.0, period=PERIOD, goal_radius=5.0, window=12, frames=4, horizon=2000, funnels=False)
    starts = start_cells(SCENE, 5.0)
    centre = (starts[:, :2].mean(1) < -12) & (np.abs(starts[:, 2:].mean(1)) <= 7.5)
    built = []  # both certificates build the same coarse abstraction (same law, cells, ε, settings): built once

    def build_once(*args, **kwargs):
        if not built:
            built.append(build(*args, **kwargs))
        return built[0]
    monkeypatch.setattr(certify_loop, "build", build_once)
    before = certified_starts(certify(law, Uniform(0.1), **kw), starts)[0]
    cert = certify(law, Uniform(0.1), refine_half=3.0, refine_factor=8, **kw)
    ok, bound, _ = certified_starts(cert, starts)
    assert not before[centre].any() and ok[centre].mean() > 0.5
    assert cert.stats["refined_nodes"] > 0
    rng = np.random.default_rng(8)
    cells = np.repeat(np.flatnonzero(ok & centre), 2)
    run_certified_points(SCENE, law, starts, cells, bound, horizon=100.0, delta=5.0, period=PERIOD, eps=0.1, rng=rng,
                         seed=9)
    # the adversary aimed at the vertex (it holds runs from K there at ε = 0.5) lets them arrive by their bound
    lo, hi = starts[cells][:, [0, 2]], starts[cells][:, [1, 3]]
    p0 = lo + rng.uniform(0, 1, (len(cells), 2)) * (hi - lo)
    keep = ~in_diamond(SCENE, p0)
    loop = FrameLoop(SCENE, law, period=PERIOD, horizon=100.0, delta=5.0)
    st = run_adversary(loop, p0[keep], np.full(int(keep.sum()), 0.1), "trap", Search(), record=False)
    assert (st["outcome"] == REACHED).all(), p0[keep][st["outcome"] != REACHED]
    assert (st["t_end"] <= np.maximum(bound[cells[keep]], 1) * PERIOD + 1e-9).all()
