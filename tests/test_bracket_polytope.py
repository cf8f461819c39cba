"""Funnels past the free region (pipeline/bracket/polytope.py, docs/bracket.md "Through the guard's range"): one
polytope step against the law's own decided inputs (sampling near the back faces, where the guard and the push-outs
act; mutations that must be caught); the start cells they certify, run by the ordinary simulator, in
tests/test_bracket_loop_that_runs.py (beside the certificate they share)."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from test_bracket_refine import PERIOD, SCENE  # the scene and frame period of the window's own sampling tests

import pipeline.bracket.polytope as polytope
from pipeline.bracket.enclosures import DIRS
from pipeline.bracket.frame import Frame
from pipeline.bracket.loop import FrameLoop
from pipeline.bracket.refine import box_support
from pipeline.control import HybridController

EPS = 0.8


def _balls(rng, n):
    """Balls (world) behind the obstacle along both back faces and their extensions, 0.2-3 units out."""
    c = SCENE.covering(0).c
    t = rng.uniform(-5, 5, n)
    side = np.sign(t) + (t == 0)
    along = np.stack([-c + np.abs(t) * np.sqrt(0.5), side * np.abs(t) * np.sqrt(0.5)], 1)
    out = rng.uniform(0.2, 3.0, n)[:, None] * np.stack([-np.full(n, np.sqrt(0.5)), side * np.sqrt(0.5)], 1)
    return along + out, rng.uniform(0.02, 0.6, n)


def _escapes(law, rng, n=400, draws=32, n_split=16) -> tuple[int, int]:
    """Sampled runs of the step's polytopes (points of their balls, errors within `EPS`, both modes before the
    frame) decided by the law itself (:meth:`FrameLoop.decided`): endpoints outside the next polytope where the
    step kept the mode, and mode changes the step did not flag. 400 balls, 32 draws each per mode (25,600 runs, as
    800 balls with 16 draws: the step over the balls is the cost, the draws are cheap)."""
    frame = Frame(45.0)
    rlaw = frame.law(law)
    loop = FrameLoop(SCENE, law, period=PERIOD)
    centres, rads = _balls(rng, n)
    h = frame.to_grid(centres) @ DIRS.T + rads[:, None]
    outside = unflagged = 0
    for q in (1, 2):
        nxt, swept, jump, unheld = polytope.step(rlaw, h, np.full(n, EPS), q, PERIOD, n_split)
        for _ in range(draws):
            ang, rad = rng.uniform(0, 2 * np.pi, (2, n))
            p = centres + (rads * np.sqrt(rng.uniform(0, 1, n)))[:, None] * np.stack([np.cos(ang), np.sin(ang)], 1)
            e = (EPS * np.sqrt(rng.uniform(0, 1, n)))[:, None] * np.stack([np.cos(rad), np.sin(rad)], 1)
            after, u = loop.decided(p + e, {"q": np.full(n, q, np.int8), "i": np.zeros(n, np.int64)})
            kept = after["q"] == q
            unflagged += int((~kept & ~jump).sum())
            rows = kept & ~jump & ~unheld
            g = frame.to_grid(p[rows] + PERIOD * u[rows])
            outside += int(((g @ DIRS.T) > nxt[rows] + 1e-9).any(axis=1).sum())
            outside += int(((g @ DIRS.T) > swept[rows] + 1e-9).any(axis=1).sum())
    return outside, unflagged


def test_one_step_holds_every_sampled_run():
    """Where the step keeps the mode, every sampled run's endpoint lies in the next polytope (and the held segment's
    set), and every sampled mode change was flagged: through the guard's range, push-outs and the faces."""
    outside, unflagged = _escapes(HybridController(SCENE), np.random.default_rng(3))
    assert outside == 0 and unflagged == 0


@pytest.mark.parametrize("mutation", ["no_error", "no_decision"])
def test_the_step_check_catches_a_loosened_rule(mutation, monkeypatch):
    """Mutations the sampling above must catch: a position perceived in a sub-box taken within that sub-box (the
    error dropped from `X ∩ (M_i ⊕ B(ε))`), the mode's decision not tested. (Dropping the push-out piece, or the
    perceived sub-boxes at the set's edge, is not seen by this sampling: the flow pieces' hulls there hold those
    endpoints too.)"""
    if mutation == "no_error":
        monkeypatch.setattr(polytope, "box_support", lambda B: box_support(B) - EPS)
    elif mutation == "no_decision":
        monkeypatch.setattr(polytope, "decisions", lambda law, boxes: (np.ones((len(boxes), 2), bool),
                                                                       np.zeros((len(boxes), 2), bool)))
    outside, unflagged = _escapes(HybridController(SCENE), np.random.default_rng(3))
    assert outside + unflagged > 0



@given(st.lists(st.integers(0, 7), max_size=40), st.integers(0, 2**32 - 1))
@settings(max_examples=60, deadline=None)
def test_group_max_is_maximum_at_bit_for_bit(rows, seed):
    """The polytope step's scatter-max (`reduceat` over runs of ascending rows) gives `np.maximum.at`'s bits, rows
    that take no value kept, `-inf` and NaN entries included."""
    rows = np.sort(np.array(rows, dtype=np.int64))
    rng = np.random.default_rng(seed)
    vals = rng.normal(size=(len(rows), 5))
    vals[rng.random(vals.shape) < 0.1] = -np.inf
    vals[rng.random(vals.shape) < 0.05] = np.nan
    base = np.where(rng.random((8, 5)) < 0.5, -np.inf, rng.normal(size=(8, 5)))
    want, got = base.copy(), base.copy()
    np.maximum.at(want, rows, vals)
    polytope.group_max(got, rows, vals)
    np.testing.assert_array_equal(got, want)
