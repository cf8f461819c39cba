"""The falsifier with the certified error map's own bound (issue 48: the bracket decided with the map's `ε̄`): the
bound at a point is the smallest of the table cells holding it, every played error lies within it frame by frame,
a counterexample needs the map's bound where the run goes (0 where the map is certified nowhere), and the table
counts what the map's bound leaves open."""

from __future__ import annotations

import numpy as np
import pandas as pd
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.bracket.bounds import CellTable, Finest
from pipeline.bracket.falsifier import ADVERSARIES, MapBound, Search, attack, run_adversary, vertex_aims
from pipeline.bracket.loop import REACHED, FrameLoop
from pipeline.control import HybridController, Scene

SCENE = Scene(target=[40.0, 0.0], obstacles=[{"center": [0.0, 0.0], "radius": 4.0}])


def _table(rows) -> CellTable:
    return CellTable(pd.DataFrame(rows, columns=["x0", "x1", "y0", "y1", "eps_bar"]))


def _brute(cells: np.ndarray, p: np.ndarray) -> np.ndarray:
    hold = ((cells[None, :, 0] <= p[:, None, 0]) & (p[:, None, 0] <= cells[None, :, 1])
            & (cells[None, :, 2] <= p[:, None, 1]) & (p[:, None, 1] <= cells[None, :, 3]))
    return np.where(hold, cells[None, :, 4], np.inf).min(axis=1)


@st.composite
def tables_and_points(draw):
    """A grid of square cells (some split in four, some missing, as the certify stage writes them) and points
    drawn anywhere, on the cells' edges and corners included."""
    h = draw(st.sampled_from([0.25, 0.5, 1.0]))
    nx, ny = draw(st.integers(1, 6)), draw(st.integers(1, 6))
    x0, y0 = draw(st.floats(-20, 20)), draw(st.floats(-20, 20))
    rows = []
    for i in range(nx):
        for j in range(ny):
            kind = draw(st.sampled_from(["whole", "split", "missing"]))
            a, b = x0 + i * h, y0 + j * h
            if kind == "whole":
                rows.append((a, a + h, b, b + h, draw(st.floats(0, 5))))
            elif kind == "split":
                rows += [(a + u, a + u + h / 2, b + v, b + v + h / 2, draw(st.floats(0, 5)))
                         for u in (0, h / 2) for v in (0, h / 2)]
    if not rows:
        rows.append((x0, x0 + h, y0, y0 + h, 1.0))
    k = draw(st.integers(1, 30))
    gx = draw(st.lists(st.integers(-1, 2 * nx + 1), min_size=k, max_size=k))
    gy = draw(st.lists(st.integers(-1, 2 * ny + 1), min_size=k, max_size=k))
    on_grid = np.column_stack([x0 + np.array(gx) * h / 2, y0 + np.array(gy) * h / 2])
    free = np.array(draw(st.lists(st.tuples(st.floats(-1, 1), st.floats(-1, 1)), min_size=1, max_size=20)))
    anywhere = np.array([x0, y0]) + (free + 1) / 2 * np.array([nx * h + 1, ny * h + 1]) - 0.5
    return np.array(rows), np.concatenate([on_grid, anywhere])


@given(tables_and_points())
@settings(max_examples=80, deadline=None)
def test_the_bound_at_a_point_is_the_smallest_of_the_cells_holding_it(case):
    cells, points = case
    np.testing.assert_array_equal(_table(cells).at(points), _brute(cells, points))


def test_several_tables_give_the_smallest_bound_at_a_point():
    whole = _table([(x, x + 1.0, y, y + 1.0, 2.0) for x in range(-2, 2) for y in range(-2, 2)])
    region = _table([(0.0, 1.0, 0.0, 1.0, 0.5)])
    p = np.array([[0.5, 0.5], [1.0, 0.5], [-1.5, -1.5], [3.0, 3.0]])
    np.testing.assert_array_equal(Finest([whole, region]).at(p), [0.5, 0.5, 2.0, np.inf])
    np.testing.assert_array_equal(MapBound(Finest([whole, region]))(p), [0.5, 0.5, 2.0, 0.0])


def test_the_map_bound_where_the_run_goes_decides_the_counterexample():
    """The paper's hybrid law from `K`: with the map's `ε̄ = 0.5` around the back vertex (0 elsewhere) the trap
    adversary holds the run there, as with a uniform 0.5; with 0.5 only far from the vertex the run arrives. Every
    error played, by every adversary, lies within the map's bound at that frame's true position."""
    near = MapBound(_table([(-16.0, -7.0, -4.0, 4.0, 0.5)]))
    far = MapBound(_table([(-60.0, -20.0, -8.0, 8.0, 0.5)]))
    p0 = np.array([[-20.0, 0.0]])
    loop = FrameLoop(SCENE, HybridController(SCENE), horizon=15.0, delta=5.0)  # 15 s: the runs that arrive take 7
    held = run_adversary(loop, p0, near, "trap", Search(trap_dirs=32), record=True)
    assert held["outcome"][0] != REACHED
    vertex = vertex_aims(SCENE, 0.0)[0]
    assert np.hypot(*(held["path"][-1, 0] - vertex)) < 1.0
    fast = Search(n_dirs=8, lookahead=8, commit=8, tail=8, n_random=1, trap_dirs=16)
    failed, _, _, _ = attack(loop, p0, far, fast)
    assert not failed.any()
    runs = [(near, held)] + [(b, run_adversary(loop, np.array([[-20.0, 0.3], [-14.0, 3.0]]), b, kind, fast))
                             for b in (near, far) for kind in ADVERSARIES]
    for bound, st_ in runs:
        path, errors = st_["path"], st_["errors"]
        assert len(errors) == len(path) - 1 > 0
        for k in range(len(errors)):  # frame k perceives path[k] + errors[k]
            assert (np.hypot(*errors[k].T) <= bound(path[k]) + 1e-12).all()
        assert (np.hypot(*errors.reshape(-1, 2).T) > 0).any()


def test_table_counts_what_the_maps_bound_decides():
    """`map ε̄: falsified` and `undecided`: start cells falsified (a run within the map's bound failed) and neither
    certified nor falsified with it; a cell both certified and falsified with the map is a soundness bug, counted."""
    from pipeline.bracket.report import table
    from pipeline.config import build, compose

    scene = build(compose("bracket").scene, "scene")
    rows = [(True, False), (False, True), (False, False), (False, False), (True, True)]
    df = pd.DataFrame([{"controller": "hybrid", "x0": -30.0, "x1": -25.0, "y0": -2.5 + 5 * i, "y1": 2.5 + 5 * i,
                        "start": True, "eps_lo": 0.5, "certified_map": cm, "falsified_map": fm, "eps_hi": np.inf}
                       for i, (cm, fm) in enumerate(rows)])
    row = table(df, scene, [0.5], with_map=True).iloc[0]
    assert row["map ε̄: falsified"].startswith("40% (")
    assert row["map ε̄: undecided"] == "40%"
    df["map_eps_start"] = [1.0, 1.0, np.inf, 0.5, 1.0]  # one undecided cell starts where the map has no bound
    row = table(df, scene, [0.5], with_map=True).iloc[0]
    assert row["map ε̄: undecided"] == "40% (1 start where the map has no bound)"
    assert row["soundness: map certified and falsified"] == 1


def test_the_stage_decides_start_cells_with_the_maps_bound(tmp_path, capfd):
    """`python -m pipeline.bracket bracket.error_map=...` on a tiny grid: a map whose bound is 2 on the band behind
    the obstacle and 0.05 elsewhere up to x = 30 (none beyond); the csv says per start cell whether it is certified or falsified with the map,
    never both, each falsified cell with its path (`<law>_map`) and an adversary; the falsified ones lie where the
    map's bound is large (the runs through the band). Each law's phases print a progress line with the counts the
    csv holds (the laws run in processes of their own: read at the file descriptor)."""
    from pipeline.bracket.stage import run
    from pipeline.config import compose

    rows = [(x, x + 2.0, y, y + 2.0, 2.0 if (-30 <= x < -10 and -4 <= y < 4) else 0.05)
            for x in range(-60, 30, 2) for y in range(-40, 40, 2)]
    pd.DataFrame(rows, columns=["x0", "x1", "y0", "y1", "eps_bar"]).to_csv(tmp_path / "map.csv", index=False)
    tiny = ["bracket.cell=4.0", "bracket.start_cell=20", "bracket.eps=[0.1]", "bracket.n_bisect=0",
            "bracket.n_dirs=8", "bracket.tail=4", "bracket.lookahead=8", "bracket.commit=8", "bracket.trap_dirs=16",
            "sim.horizon=8", "bracket.controllers=[hybrid,smooth]", "bracket.polytope_split=0",
            "bracket.funnel_split=0", "bracket.refine=0"]  # cells of 4 certify no start cell: no funnels, no window
    out = run(compose("bracket", [*tiny, f"bracket.error_map={tmp_path / 'map.csv'}",
                                  f"paths.outputs_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"]))
    df = pd.read_csv(out["path"] / "bracket.csv")
    printed = capfd.readouterr().out
    for name in ("hybrid", "smooth"):
        law = df[df.controller == name]
        assert (f"bracket: {name}: ε = 0.1: certified {int((law.eps_lo == 0.1).sum())}/{int(law.start.sum())} "
                f"start cells (") in printed
        assert f"bracket: {name}: the map's ε̄: certified {int(law.certified_map.sum())} start cells (" in printed
        assert (f"bracket: {name}: falsifier: {int(np.isfinite(law.eps_hi).sum())}/{int(law.eps_hi.notna().sum())} start "
                "cells broken (") in printed
    assert not (df.certified_map & df.falsified_map).any()
    assert df.falsified_map.any() and (df.map_adversary[df.falsified_map].isin(ADVERSARIES)).all()
    # the failing scale of the map's bound, bisected twice on (0, 1]: finite exactly where falsified
    assert (df.map_scale_hi.notna() == df.falsified_map).all()
    assert df.map_scale_hi.dropna().isin([0.0, 0.25, 0.5, 0.75, 1.0]).all()
    nominal_fails = (df.eps_hi == 0) & (df.controller == "smooth")  # the smooth law stalls on K without error
    assert nominal_fails.any() and (df.map_scale_hi[nominal_fails] == 0).all()
    paths = np.load(out["path"] / "counterexamples.npz")
    for name in ("hybrid", "smooth"):
        rows_ = (df.falsified_map & (df.controller == name)).to_numpy()[df.controller == name]
        assert np.isfinite(paths[f"{name}_map"][:, rows_]).all()
    tab = (out["path"] / "table.md").read_text()
    assert "map ε̄: undecided" in tab and "soundness: map certified and falsified" in tab
    beyond = (df.x0 + df.x1) / 2 > 30  # the map's table stops at x = 30: no bound at these starts
    assert beyond.any() and np.isinf(df.map_eps_start[beyond & df.start]).all()
    assert np.isfinite(df.map_eps_start[~beyond & df.start]).all()
    smooth = df[df.controller == "smooth"]
    on_axis = (smooth.x1 <= -10) & (smooth.y0 < 0) & (smooth.y1 > 0)
    assert smooth.falsified_map[on_axis].all()  # Proposition 1 with the map's bound where the runs stall


def test_a_uniform_counterexample_inside_the_maps_bound_falsifies_with_the_map():
    """`map_rows` with the uniform falsifier's result: a counterexample at `ε_hi` whose path keeps the map's bound at
    least `ε_hi` is within the map's bound as it is: the cell is falsified with the map without a search (adversary
    "uniform", scale `ε_hi / least bound`); one whose path meets a smaller bound is not taken."""
    from pipeline.bracket.falsifier import falsify
    from pipeline.bracket.stage import map_rows
    from pipeline.control import SmoothController

    loop = FrameLoop(SCENE, SmoothController(SCENE), horizon=30.0, delta=5.0)
    p0 = np.array([[-20.0, 0.4]])
    fast = Search(n_dirs=8, lookahead=8, commit=8, tail=8, n_random=1, trap_dirs=16)
    br = falsify(loop, p0, eps_max=2.0, n_bisect=1, search=fast)  # ε_hi = 1 (the fixed adversary's)
    assert 0 < br.eps_hi[0] <= 2.0
    wide = _table([(-60.0, 60.0, -40.0, 40.0, 2.0)])
    cols, _ = map_rows(loop, wide, fast, p0, np.array([True]), 0, (br.eps_hi, br.path))
    assert cols["falsified_map"][0] and cols["map_adversary"][0] == "uniform"
    assert cols["map_scale_hi"][0] == br.eps_hi[0] / 2.0
    # the same counterexample where the map's bound along its path is below ε_hi: not taken as it is
    thin = _table([(-60.0, 60.0, -40.0, 40.0, 0.5 * br.eps_hi[0])])
    cols, _ = map_rows(loop, thin, fast, p0, np.array([True]), 0, (br.eps_hi, br.path))
    assert cols["map_adversary"][0] != "uniform"


def test_a_start_where_the_maps_bound_is_largest_falsifies_the_cell():
    """A certificate claims every start of its cell; the map's bound is largest where the camera clips the robot
    (the arena's border), not at the centre. `worst_starts` finds the accepted start of largest bound on a 9 x 9
    lattice of the cell, and `map_rows` searches from it where the centre's search found nothing: the smooth law,
    a map whose bound is 0.2 on `K` only, a start cell straddling `K` with its centre off it (that run arrives),
    falsified from its lattice point on `K` (the fixed adversary stalls it at the saddle)."""
    from pipeline.bracket.stage import map_rows
    from pipeline.bracket.starts import worst_starts
    from pipeline.control import SmoothController

    loop = FrameLoop(SCENE, SmoothController(SCENE), horizon=30.0, delta=5.0)
    band = _table([(x, x + 0.5, -0.3, 0.3, 0.2) for x in np.arange(-40.0, -10.0, 0.5)])
    cell = np.array([[-25.0, -20.0, -0.25, 4.25]])  # lattice rows at y = 0, 0.5, ..., 4
    worst, b = worst_starts(SCENE, cell, MapBound(band))  # 0 where the map has no bound: the falsifier's
    assert worst[0, 1] == 0.0 and b[0] == 0.2 and -25.0 < worst[0, 0] < -20.0
    centre = cell[:, [0, 2]] + (cell[:, [1, 3]] - cell[:, [0, 2]]) / 2
    fast = Search(n_dirs=8, lookahead=8, commit=8, tail=8, n_random=1, trap_dirs=16)
    alone, _ = map_rows(loop, band, fast, centre, np.array([True]), 0)
    assert not alone["falsified_map"][0]
    cols, paths = map_rows(loop, band, fast, centre, np.array([True]), 1, alts=(worst,))
    assert cols["falsified_map"][0] and cols["map_adversary"][0] in ADVERSARIES
    assert (cols["map_x"][0], cols["map_y"][0]) == tuple(worst[0]) and cols["map_eps_start"][0] == 0.2
    np.testing.assert_array_equal(paths[0, 0], worst[0])  # the counterexample's path starts there
    # a start the simulator refuses (in the diamond) is never drawn, even where the bound is largest
    far, _ = worst_starts(SCENE, np.array([[-12.0, -6.0, -3.0, 3.0]]), lambda p: -np.abs(p[:, 0] + 9.0))
    assert np.abs(far[0]).sum() > 8 * np.sqrt(2) and far[0, 0] == -9.0  # on x = -9, off the diamond


def test_a_start_nearest_K_falsifies_a_cell_whose_centre_arrives():
    """The hybrid law's trap lives on `K` (the axis behind the obstacle): make bracket's scene and law, a map whose
    bound is 1.75 everywhere, the start cell `[-47.5, -42.5] x [2.5, 7.5]` beside `K`. From its centre (2.5 units
    farther from the axis) every adversary lets the run arrive; `axis_starts` gives the closed cell's accepted lattice
    point nearest `K` (on its edge), and from there the trap adversary holds the run at the vertex within the map's bound."""
    from pipeline.bracket.stage import map_rows, objects
    from pipeline.bracket.starts import axis_starts
    from pipeline.config import compose

    scene, laws, bs, sim, camera, *_ = objects(compose("bracket", []))
    loop = FrameLoop(scene, laws["hybrid"], period=camera.period, horizon=15.0, delta=bs.goal_radius)  # centre: 11 s
    cells = np.array([[-47.5, -42.5, 2.5, 7.5], [20.0, 25.0, 2.5, 7.5]])  # the second lies in front of the obstacle
    near, d = axis_starts(scene, cells)
    assert near[0, 1] == 2.5 and np.isclose(d[0], near[0, 1]) and -47.5 <= near[0, 0] <= -42.5  # the closed cell's edge
    assert np.isinf(d[1])  # no point of it behind an obstacle
    wide = _table([(-60.0, 60.0, -40.0, 40.0, 1.75)])
    fast = Search(n_dirs=8, lookahead=8, commit=8, tail=8, n_random=1, trap_dirs=16)
    centre = np.array([[-45.0, 5.0]])
    cols, paths = map_rows(loop, wide, fast, centre, np.array([True]), 0, alts=(near[:1],))
    assert cols["falsified_map"][0] and cols["map_adversary"][0] == "trap"
    # the counterexample starts at the point nearest K: the searches from the centre (tried first) found nothing
    assert (cols["map_x"][0], cols["map_y"][0]) == tuple(near[0])
    assert np.hypot(*(paths[-1, 0] - vertex_aims(scene, 0.0)[0])) < 1.5  # held at the vertex


def test_the_uniform_falsifier_from_the_point_nearest_K_lowers_eps_hi_and_its_counterexample_replays():
    """`bracket.axis_start`: make bracket's scene and hybrid law, the start cell `[-47.5, -42.5] x [2.5, 7.5]` beside
    `K` and one in front of the obstacle. From the centre the bisection on `[0, 4]` (one step) ends at 4: at 2 every
    adversary lets the run arrive; from the point nearest `K` the trap holds it at 2, so the cell's `ε_hi` falls to
    2 with that start and path, and the trap adversary played again from there at 2 keeps the run from the goal
    disc. The cell in front of the obstacle (no point behind it) is not tried; with `axis_start` below the point's
    distance nothing is."""
    from types import SimpleNamespace

    from pipeline.bracket.falsifier import falsify
    from pipeline.bracket.stage import axis_falsifier, objects
    from pipeline.config import compose

    scene, laws, bs, sim, camera, *_ = objects(compose("bracket", []))
    loop = FrameLoop(scene, laws["hybrid"], period=camera.period, horizon=15.0, delta=bs.goal_radius)  # 15 s: cheaper
    cells = np.array([[-47.5, -42.5, 2.5, 7.5], [20.0, 25.0, 2.5, 7.5]])
    centres = cells.reshape(-1, 2, 2).mean(axis=2)
    fast = Search(n_dirs=8, lookahead=8, commit=8, tail=8, n_random=1, trap_dirs=16)
    br = falsify(loop, centres, 4.0, 1, fast)
    assert br.eps_hi[0] == 4.0, br.eps_hi  # from the centre: broken at 4, not at 2
    settings_ = SimpleNamespace(axis_start=5.0, eps_max=4.0, n_bisect=1)

    def columns():
        return {"eps_hi": br.eps_hi.copy(), "adversary": br.adversary.astype(object), "outcome":
                np.full(2, "", dtype=object), "paths": br.path.copy(), "start": centres.copy()}

    hi = columns()
    info = axis_falsifier(loop, scene, cells, centres, np.array([True, True]), settings_, fast, hi)
    assert info["starts"] == 1 and info["lowered"] == 1  # the cell in front of the obstacle is not tried
    assert hi["eps_hi"][0] == 2.0 and hi["adversary"][0] == "trap" and hi["eps_hi"][1] == br.eps_hi[1]
    start = hi["start"][0]
    assert start[1] == 2.5 and -47.5 <= start[0] <= -42.5  # the closed cell's lattice point nearest K (its edge)
    np.testing.assert_array_equal(hi["paths"][0, 0], start)  # the counterexample's path starts there
    again = run_adversary(loop, start[None], np.array([2.0]), "trap", fast)
    assert again["outcome"][0] != REACHED
    np.testing.assert_allclose(again["path"][-1, 0], hi["paths"][-1, 0])
    assert np.hypot(*(again["path"][-1, 0] - scene.p_T)) > bs.goal_radius
    quiet = columns()
    settings_.axis_start = 2.25  # the point is 2.5 from K: beyond it
    assert axis_falsifier(loop, scene, cells, centres, np.array([True, True]), settings_, fast, quiet)["starts"] == 0
    assert quiet["eps_hi"][0] == 4.0
