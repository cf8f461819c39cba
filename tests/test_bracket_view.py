"""The camera's view in the closed loop's certificate (issue 48, docs/bracket.md "The loop that runs"): a grid cell
straddling the arena's edge holds runs on its part inside the arena, and a swept set that may leave the arena is
unsafe. Before, a cell counted only when wholly inside, so no start cell on the arena's edge was ever certified
(the ring of 64 of the 268 start cells: most of the bracket's undecided cells).

Each claim is checked where it can fail: the ring gets certified (0 before), its runs (random points and points on
the edge itself) arrive without leaving the view under the falsifier's adversaries and `simulate`'s error signals;
the rule that keeps swept sets in the arena is dropped (a mutation) and the CBF law's runs from the top edge leave
the view from start cells it then certifies.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.bracket import abstraction
from pipeline.bracket.bounds import Uniform
from pipeline.bracket.certify_loop import certified_starts, certify
from pipeline.bracket.enclosures import DIRS
from pipeline.bracket.falsifier import Search, attack
from pipeline.bracket.frame import Frame
from pipeline.bracket.loop import OUTCOMES, FrameLoop
from pipeline.control import in_diamond
from pipeline.sim import CameraSettings, SimSettings, simulate

ARENA = ((-50.0, 50.0), (-30.0, 30.0))


@given(k=st.integers(0, 31), pts=st.lists(st.tuples(st.floats(-80, 80), st.floats(-80, 80)), min_size=1,
                                          max_size=30))
@settings(max_examples=60, deadline=None)
def test_view_bounds_are_the_rotated_arena(k, pts):
    """`{g: DIRS g <= H}` is the arena in the grid frame, for every angle among the support directions."""
    frame = Frame(k * 360.0 / len(DIRS))
    H = frame.view_bounds(ARENA)
    assert H is not None and np.isfinite(H).sum() == 4
    w = np.array(pts, float)
    (x0, x1), (y0, y1) = ARENA
    inside = (w[:, 0] > x0 + 1e-6) & (w[:, 0] < x1 - 1e-6) & (w[:, 1] > y0 + 1e-6) & (w[:, 1] < y1 - 1e-6)
    outside = (w[:, 0] < x0 - 1e-6) | (w[:, 0] > x1 + 1e-6) | (w[:, 1] < y0 - 1e-6) | (w[:, 1] > y1 + 1e-6)
    member = (frame.to_grid(w) @ DIRS.T <= H + 1e-9).all(axis=1)
    assert member[inside].all() and not member[outside].any()


def test_view_bounds_refuse_an_angle_off_the_directions():
    assert Frame(10.0).view_bounds(ARENA) is None


@given(angle=st.sampled_from([0.0, 45.0, 30.0]), x=st.floats(-60, 60), y=st.floats(-40, 40), h=st.floats(0.2, 3))
@settings(max_examples=80, deadline=None)
def test_a_cell_meets_the_view_iff_some_of_its_interior_is_inside(angle, x, y, h):
    """`meets_view` against points of the cell: a sampled point strictly inside the arena means it meets; a cell
    wholly inside is `in_view`, which implies it meets."""
    frame = Frame(angle)
    box = np.array([[x, x + h, y, y + h]])
    g = np.stack(np.meshgrid(np.linspace(x + 1e-6, x + h - 1e-6, 25), np.linspace(y + 1e-6, y + h - 1e-6, 25)),
                 -1).reshape(-1, 2)
    w = frame.to_world(g)
    (x0, x1), (y0, y1) = ARENA
    strictly = ((w[:, 0] > x0) & (w[:, 0] < x1) & (w[:, 1] > y0) & (w[:, 1] < y1)).any()
    meets = bool(frame.meets_view(box, ARENA)[0])
    if strictly:
        assert meets
    if frame.in_view(box, ARENA)[0]:
        assert meets
    corners_out = ~((w[:, 0] >= x0) & (w[:, 0] <= x1) & (w[:, 1] >= y0) & (w[:, 1] <= y1))
    if corners_out.all() and not meets:  # the cell's own points agree: none strictly inside
        assert not strictly


# ------------------------------------------------------------------------------ the certificate and its runs
@pytest.fixture(scope="module")
def paper():
    """`python -m pipeline.bracket`'s objects at its defaults (the paper's tuning)."""
    from pipeline.bracket.stage import objects
    from pipeline.bracket.starts import start_cells
    from pipeline.config import compose

    scene, laws, bs, sim_cfg, camera, _, _, lost = objects(compose("bracket", []))
    return {"scene": scene, "laws": laws, "bs": bs, "horizon": float(sim_cfg.horizon), "period": camera.period,
            "lost": lost, "starts": start_cells(scene, bs.start_cell)}


def _certified(paper, name: str, eps: float, shared=None) -> tuple[np.ndarray, np.ndarray]:
    """`name`'s certified start cells at `eps` and their bounds at the defaults; `shared`: `(tmp_path_factory,
    worker_id)`, the unchanged certificate read from the session's (:func:`default_certificate`), else certified
    here (under a mutation)."""
    if shared is not None:
        from test_bracket_loop_that_runs import default_certificate

        ok, bound, _ = certified_starts(default_certificate(*shared, name, eps), paper["starts"])
        return ok, bound
    bs, period = paper["bs"], paper["period"]
    cert = certify(paper["laws"][name], Uniform(eps), h=bs.cell, angle=bs.angle, period=period,
                   goal_radius=bs.goal_radius, n_split=bs.n_split, window=bs.window, frames=bs.frames,
                   horizon=int(round(paper["horizon"] / period)), lost=paper["lost"][name])
    ok, bound, _ = certified_starts(cert, paper["starts"])
    return ok, bound


def _on_edge(paper) -> np.ndarray:
    (x0, x1), (y0, y1) = paper["scene"].bounds
    s = paper["starts"]
    return (np.isclose(s[:, 0], x0) | np.isclose(s[:, 1], x1) | np.isclose(s[:, 2], y0) | np.isclose(s[:, 3], y1))


def _points(paper, cells: np.ndarray, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Two random points of each start cell and its point on the arena's edge nearest a random one."""
    rng = np.random.default_rng(seed)
    s = paper["starts"][cells]
    lo, hi = s[:, [0, 2]], s[:, [1, 3]]
    pts = [lo + rng.uniform(0, 1, (len(cells), 2)) * (hi - lo) for _ in range(3)]
    (x0, x1), (y0, y1) = paper["scene"].bounds
    edge = pts[2].copy()
    edge[:, 0] = np.where(np.isclose(s[:, 0], x0), x0, np.where(np.isclose(s[:, 1], x1), x1, edge[:, 0]))
    edge[:, 1] = np.where(np.isclose(s[:, 2], y0), y0, np.where(np.isclose(s[:, 3], y1), y1, edge[:, 1]))
    p0, cell = np.concatenate(pts[:2] + [edge]), np.tile(cells, 3)
    keep = ~in_diamond(paper["scene"], p0)
    return p0[keep], cell[keep]


def _falsified(paper, name: str, p0: np.ndarray, eps: float) -> list:
    """The falsifier's fixed and mode-aware adversaries at `eps` (leaving the view is a failure there)."""
    bs = paper["bs"]
    loop = FrameLoop(paper["scene"], paper["laws"][name], period=paper["period"], horizon=paper["horizon"],
                     delta=bs.goal_radius)
    failed, _, outcome, _ = attack(loop, p0, np.full(len(p0), eps), Search(n_dirs=bs.n_dirs),
                                   adversaries=("fixed", "mode_aware"))
    return [(p0[i].round(3).tolist(), OUTCOMES[int(outcome[i])]) for i in np.flatnonzero(failed)]


def test_start_cells_on_the_arena_edge_are_certified_and_their_runs_stay_in_view(paper, tmp_path_factory, worker_id):
    """The hybrid law at ε = 0.5: start cells on the arena's edge certified (none before), and from their points
    (the edge itself included) no run leaves the view, collides, or arrives after its bound, under the falsifier's
    adversaries and four error signals of `simulate` (whose runs are checked inside the arena at every frame)."""
    from test_bracket_loop_that_runs import _lossy_errors

    eps = 0.5
    ok, bound = _certified(paper, "hybrid", eps, shared=(tmp_path_factory, worker_id))
    ring = ok & _on_edge(paper)
    assert ring.sum() >= 30, int(ring.sum())  # 0 before straddling cells counted
    p0, cell = _points(paper, np.flatnonzero(ring))
    assert not _falsified(paper, "hybrid", p0, eps)
    runs, runs_cell = np.repeat(p0, 4, axis=0), np.repeat(cell, 4)
    sim = SimSettings(horizon=paper["horizon"], delta=paper["bs"].goal_radius, record_every=5)
    res = simulate(paper["scene"], paper["laws"]["hybrid"], runs, sim=sim,
                   camera=CameraSettings(period=paper["period"]), measure=_lossy_errors(len(runs), eps, 0, 3))
    m = res.metrics
    late = m["time_to_target"] > np.maximum(bound[runs_cell], 1) * paper["period"] + 1e-9
    assert not (~m["success"] | m["collision"] | late).any()
    (x0, x1), (y0, y1) = paper["scene"].bounds
    P = res.p.reshape(-1, 2)
    P = P[np.isfinite(P).all(axis=-1)]
    assert ((P[:, 0] >= x0 - 1e-9) & (P[:, 0] <= x1 + 1e-9) & (P[:, 1] >= y0 - 1e-9) & (P[:, 1] <= y1 + 1e-9)).all()


def test_view_rule_mutation_certifies_runs_that_leave_the_view(paper, monkeypatch, tmp_path_factory, worker_id):
    """The CBF law (which turns along the level sets of `h` far from the disc and leaves the view from the left
    corners, docs/bracket.md) at ε = 0.5: its certified edge cells' runs stay in view; with the swept sets no longer
    checked against the arena (`_frames` without `view`), more start cells are certified and runs from them leave
    the view."""
    eps = 0.5
    ok, _ = _certified(paper, "cbf", eps, shared=(tmp_path_factory, worker_id))
    p0, _ = _points(paper, np.flatnonzero(ok & _on_edge(paper)))
    assert len(p0) and not _falsified(paper, "cbf", p0, eps)

    frames = abstraction._frames
    monkeypatch.setattr(abstraction, "_frames", lambda *args: frames(*args[:-1], None))
    loose, _ = _certified(paper, "cbf", eps)
    new = np.flatnonzero(loose & ~ok)
    assert len(new)
    p0, _ = _points(paper, new)
    broken = _falsified(paper, "cbf", p0, eps)
    assert any(outcome == "left_view" for _, outcome in broken), broken
