"""The bracket over several obstacles (SPEC §3.6, §5.4; docs/bracket.md, "Several obstacles"): the hybrid law's
nodes carry the active obstacle, the smooth law sums its barriers, the CBF filter solves its QP; the enclosures
contain every sampled held input, the frame decisions (cell jumps included) are covered by the abstraction's
edges, and certified starts hold in the ordinary simulator (`pipeline.sim.simulate`, errors written here)."""

from __future__ import annotations

import numpy as np
import pytest
from test_bracket_loop_that_runs import _lossy_errors  # the error signals written for the simulator test

from pipeline.bracket.abstraction import dilate
from pipeline.bracket.bounds import Uniform
from pipeline.bracket.certify_loop import certified_starts, certify
from pipeline.bracket.enclosures import DIRS
from pipeline.bracket.inputs import support
from pipeline.bracket.loop import FrameLoop
from pipeline.bracket.lost import LostFrames
from pipeline.bracket.modes import Modes
from pipeline.control import CBFController, HybridController, Scene, SmoothController, in_diamond
from pipeline.sim import CameraSettings, SimSettings, simulate

ROW = Scene(target=[40.0, 0.0], obstacles=[{"center": [-14.0, 0.0], "radius": 4.0},
                                           {"center": [20.0, 0.0], "radius": 4.0}])
# three discs whose barriers and CBF constraints overlap (the smooth and CBF laws take any discs)
CLOSE = Scene(target=[40.0, 0.0], obstacles=[{"center": [0.0, -5.0], "radius": 2.0},
                                             {"center": [0.0, 5.0], "radius": 2.0},
                                             {"center": [12.0, 9.0], "radius": 2.5}],
              barrier={"gain": 300.0, "rho": 1.0, "scale": 4.0})
PERIOD = 0.05


def _boxes(rng, n, scene):
    """Boxes over the arena, around the discs, and between each pair of discs (where two barriers act)."""
    centres = np.array([cov.p_0 for cov in scene.coverings])
    near = centres[rng.integers(0, len(centres), n // 3)] + rng.normal(0, 9.0, (n // 3, 2))
    a, b = rng.integers(0, len(centres), (2, n // 3))
    between = centres[a] + rng.uniform(0, 1, (n // 3, 1)) * (centres[b] - centres[a]) + rng.normal(0, 1.5, (n // 3, 2))
    cen = np.concatenate([rng.uniform([-50, -30], [50, 30], (n - 2 * (n // 3), 2)), near, between])
    side = rng.uniform(0.05, 2.5, n)
    return np.stack([cen[:, 0] - side / 2, cen[:, 0] + side / 2, cen[:, 1] - side / 2, cen[:, 1] + side / 2], 1)


def _points(rng, boxes):
    return boxes[:, [0, 2]] + rng.uniform(0, 1, (len(boxes), 2)) * (boxes[:, [1, 3]] - boxes[:, [0, 2]])


@pytest.mark.parametrize("law, scene", [(SmoothController(CLOSE), CLOSE), (CBFController(CLOSE), CLOSE),
                                        (SmoothController(ROW), ROW), (CBFController(ROW), ROW)],
                         ids=["smooth-close", "cbf-close", "smooth-row", "cbf-row"])
def test_the_baselines_enclosures_contain_every_sampled_held_input(law, scene):
    """Boxes all over the arena and around every disc (overlapping barriers, two active CBF constraints, inside the
    margin discs: push-outs): every held input lies in the polytope. Without the other obstacles' terms (one
    obstacle's formula on every box) some input leaves it."""
    rng = np.random.default_rng(2)
    loop = FrameLoop(scene, law)
    boxes = _boxes(rng, 1500, scene)
    h = support(law, boxes, 1, PERIOD)
    lone = Scene(target=list(scene.target), obstacles=[scene.obstacles[0]])
    h_lone = support(type(law)(lone), boxes, 1, PERIOD)
    outside_lone = 0
    for _ in range(8):
        m = _points(rng, boxes)
        xd = {"q": np.ones(len(m), np.int8), "i": np.zeros(len(m), np.int64)}
        u = loop.held(m, {k: xd[k] for k in law.logic})
        assert (u @ DIRS.T <= h + 1e-9).all(), boxes[(u @ DIRS.T > h + 1e-9).any(axis=1)][:3]
        outside_lone += int((u @ DIRS.T > h_lone + 1e-9).any(axis=1).sum())
    assert outside_lone > 0


def test_the_hybrid_enclosure_holds_in_every_state_of_the_active_obstacle():
    """In each state `(i, q)` after a frame's decision (from every state before it, at perceived points where `i`
    stays active), the held input lies in the polytope of obstacle `i`'s mode `q`; obstacle 0's polytope does not
    hold obstacle 1's inputs."""
    rng = np.random.default_rng(3)
    law = HybridController(ROW)
    loop = FrameLoop(ROW, law)
    boxes = _boxes(rng, 1500, ROW)
    missed_by_first = 0
    h = {(i, q): support(law, boxes, q, PERIOD, obstacle=i) for i in range(2) for q in (1, 2)}
    h0 = {q: support(law, boxes, q, PERIOD, obstacle=0) for q in (1, 2)}
    for i in range(2):
        for before in (1, 2):  # the state a node carries is the one after the frame's decision
            for _ in range(6):
                m = _points(rng, boxes)
                xd = {"i": np.full(len(m), i, np.int64), "q": np.full(len(m), before, np.int8)}
                after, u = loop.decided(m, xd)
                for q in (1, 2):
                    keep = (after["i"] == i) & (after["q"] == q)
                    assert (u[keep] @ DIRS.T <= h[i, q][keep] + 1e-9).all()
                    missed_by_first += int(((u[keep] @ DIRS.T) > h0[q][keep] + 1e-9).any(axis=1).sum())
    assert missed_by_first > 0


def test_every_frame_decision_is_an_edge_of_the_abstraction():
    """From every state `(i, q)` on a perceived box, the law's frame decision at a point of the box (a cell jump to
    the nearest obstacle and its mode, a mode jump, or none) is among the states `Modes` allows there; a run's initial
    state after frame 0 is among the initial ones. Cell jumps happen in the sample (the test can fail)."""
    rng = np.random.default_rng(4)
    law = HybridController(ROW)
    boxes = _boxes(rng, 3000, ROW)
    logic = Modes(law, boxes)
    cells = np.arange(len(boxes))
    cell_jumps = 0
    for k in range(logic.modes):
        allowed = np.zeros((len(boxes), logic.modes), bool)
        for mask, k1 in logic.successors(k, cells):
            allowed[mask, k1] = True
        for _ in range(6):
            m = _points(rng, boxes)
            xd = {"i": np.full(len(m), k // 2, np.int64), "q": np.full(len(m), k % 2 + 1, np.int8)}
            ev = law.evaluate(m, xd)
            jump = law.jump_set(m, xd, ev=ev)
            after = law.jump_map(m, xd, ev=ev)
            i1 = np.where(jump, after["i"], xd["i"])
            q1 = np.where(jump, after["q"], xd["q"])
            k1 = 2 * i1 + q1 - 1
            assert allowed[cells, k1].all(), boxes[~allowed[cells, k1]][:3]
            cell_jumps += int((i1 != xd["i"]).sum())
    assert cell_jumps > 50
    m = _points(rng, boxes)
    x0 = law.initial_state(m)
    ev = law.evaluate(m, x0)
    jump = law.jump_set(m, x0, ev=ev)
    after = law.jump_map(m, x0, ev=ev)
    k0 = 2 * np.where(jump, after["i"], x0["i"]) + np.where(jump, after["q"], x0["q"]) - 1
    assert logic.initial[cells, k0].all()


@pytest.mark.parametrize("law_cls, max_lost", [(HybridController, 0), (SmoothController, 0), (CBFController, 0),
                                               (HybridController, 2)])
def test_certified_starts_hold_in_the_simulator_among_two_obstacles(law_cls, max_lost):
    """A coarse certificate on two discs in a row at ε = 0.25 within a 12 s horizon (and with up to 2 frames lost in
    a row, held); random points of its certified start cells, run by `pipeline.sim.simulate` with errors within ε
    (and frames lost at random, never more in a row): every run reaches the goal disc within its certified arrival
    bound, with no collision with either disc."""
    law = law_cls(ROW)
    eps, horizon = 0.25, 12.0
    n_frames = int(round(horizon / PERIOD))
    lost = LostFrames(max_lost, False, PERIOD, max(law.u_max, law.push_speed))
    cert = certify(law, Uniform(eps), h=2.0, angle=45.0, period=PERIOD, goal_radius=5.0, window=12, horizon=n_frames,
                   lost=lost)
    starts = np.array([[x, x + 4, y, y + 4] for x in range(-48, 44, 4) for y in range(-28, 28, 4)], float)
    ok, bound, _ = certified_starts(cert, starts)
    assert ok.sum() >= 8, ok.sum()
    rng = np.random.default_rng(9)
    cells = np.repeat(np.flatnonzero(ok), 4)
    p0 = starts[cells][:, [0, 2]] + rng.uniform(0, 4, (len(cells), 2))
    keep = ~in_diamond(ROW, p0)
    p0, cells = p0[keep], cells[keep]
    res = simulate(ROW, law, p0, sim=SimSettings(horizon=horizon, delta=5.0, record_every=1000),
                   camera=CameraSettings(period=PERIOD), measure=_lossy_errors(len(p0), eps, max_lost, 5, ROW), record=False)
    m = res.metrics
    assert m["success"].all() and not m["collision"].any(), p0[~m["success"]]
    late = m["time_to_target"] > np.maximum(bound[cells], 1) * PERIOD + 1e-9
    assert not late.any(), (p0[late], m["time_to_target"][late], bound[cells][late])


def test_the_nodes_of_an_obstacle_that_cannot_be_active_are_unsafe_and_unreached():
    """A node `(P, i, ·)` where `i` can be neither kept nor jumped to gets no input and is unsafe, and no edge or
    initial state leads to it (the abstraction stays a superset: such a state cannot occur)."""
    law = HybridController(ROW)
    cert = certify(law, Uniform(0.25), h=2.0, angle=45.0, period=PERIOD, goal_radius=5.0, window=12, horizon=600)
    ab = cert.abstraction
    boxes = dilate(ab.grid.boxes(), np.full(ab.grid.n, 0.25))
    relevant = Modes(cert.frame.law(law), boxes).relevant.ravel()
    assert (~relevant).sum() > 100 and not ab.safe[~relevant].any()
    assert not np.isin(ab.succ, np.flatnonzero(~relevant)).any()
    assert not ab.initial.ravel()[~relevant].any()


def test_the_camera_falsifier_is_refused_on_several_obstacles():
    from pipeline.bracket.stage import objects
    from pipeline.config import compose
    from pipeline.errors import ConfigError

    with pytest.raises(ConfigError, match="bracket.camera_map"):
        objects(compose("bracket", ["tuning=two_in_row", "bracket.camera_map=some_map"]))


def test_the_stage_brackets_a_field_end_to_end(tmp_path):
    """`python -m pipeline.bracket tuning=field` on tiny sizes: a row per law and start cell, the soundness columns
    0, starts behind several obstacles counted, and every falsifier start one the simulator accepts."""
    from pipeline.bracket.stage import run
    from pipeline.bracket.starts import falsifier_starts, start_cells
    from pipeline.config import compose
    from pipeline.sim.composed import loop_parts

    tiny = ["tuning=field", "bracket.cell=2.0", "bracket.start_cell=10", "bracket.eps=[0.25]", "bracket.n_bisect=0",
            "bracket.n_dirs=8", "bracket.tail=4", "bracket.lookahead=8", "bracket.commit=8", "sim.horizon=12",
            "bracket.n_random=0", "bracket.trap_dirs=8",  # the falsifier's cheaper search (23.9 -> 21.7 s)
            f"paths.outputs_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"]
    cfg = compose("bracket", tiny)
    out = run(cfg)
    df, tab = out["bracket"], out["table"]
    assert list(tab.controller) == ["hybrid", "smooth", "cbf"]
    assert (tab["soundness: ε_lo > ε_hi"] == 0).all() and (tab["soundness: arrival > bound"] == 0).all()
    scene = loop_parts(cfg).scene
    assert scene.n_obstacles == 5
    behind = tab["behind: certified"].str.extract(r"/(\d+)")[0].astype(int)
    assert (behind > 10).all()  # cells behind more than one obstacle (one obstacle: a few)
    starts = start_cells(scene, 10.0)
    p0, ok = falsifier_starts(scene, starts)
    assert not in_diamond(scene, p0[ok]).any()
    certified = df[df.eps_lo.notna()]
    assert len(certified) and certified.start.all() and certified.arrival_nominal.notna().all()
