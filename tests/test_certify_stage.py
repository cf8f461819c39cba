"""The certify stage end to end on a tiny config (pipeline.certify.stage), and its bad inputs: one line, exit 2."""

import json
import re

import numpy as np
import pytest
from shared import run_cli, without_figures  # tests/shared.py

from pipeline.cli import compose
from pipeline.errors import PipelineError
from pipeline.preflight import preflight


def _cfg(tiny_maps, tmp_path, *extra):
    root, ids = tiny_maps
    return compose("certify", ["debug=tiny", f"maps={ids['clean']}", f"paths.models_dir={root / 'models'}",
                               f"paths.certified_dir={tmp_path / 'certified'}", "progress=false", *extra])


def test_certify_tiny_end_to_end(tiny_maps, tmp_path):
    from pipeline.certify.stage import run

    out = run(_cfg(tiny_maps, tmp_path))
    s = out["summary"]
    folder = out["path"]
    assert folder.name.startswith("clean-") and (folder / "manifest.json").exists()
    cells = np.load(folder / "cells.npz")
    for k, r in s["kappas"].items():
        eps = cells[f"eps_{k}"][cells["operational"]]
        assert np.all(np.isfinite(eps)) and len(eps) == s["n_cells"] == r["eps_bar"]["n"]
        assert r["eps_bar"]["max"] == pytest.approx(float(eps.max()))
        assert sum(r["depth"].values()) == s["n_cells"]
        assert r["theorem1"]["holds"] == (float(eps.max()) < s["margin_c_minus_r"])
    r0 = s["kappas"]["0"]
    assert r0["soundness"]["violations"] == 0 and r0["soundness"]["samples"] == 4 * s["n_cells"]
    for r in s["kappas"].values():  # the PGD attack ran on 4 cells per kappa and stayed below every bound
        assert r["pgd"]["cells"] == 4 and r["pgd"]["violations"] == 0 and r["pgd"]["counterexample"] is None
        assert 0 < r["pgd"]["share_max"] <= 1 + 1e-6
    emp = cells["emp_0"][cells["operational"]]
    assert np.all(cells["eps_0"][cells["operational"]] >= emp)  # the bound holds the sampled maximum
    assert np.all(cells["eps_1"][cells["operational"]] >= cells["eps_0"][cells["operational"]] - 1e-6)
    assert s["margin_c_minus_r"] == pytest.approx(2 * np.sqrt(2) * 4 - 4)
    from pipeline.bracket.bounds import CellTable

    for k in s["kappas"]:  # the cell table the bracket reads (bracket.error_map=<this folder>: kappa 0's)
        t = np.loadtxt(folder / f"error_map_kappa{k}.csv", delimiter=",", skiprows=1)
        assert len(t) == s["n_cells"]
        np.testing.assert_array_equal(np.sort(t[:, 4]), np.sort(cells[f"eps_{k}"][cells["operational"]]))
    np.testing.assert_array_equal(CellTable(folder).cells, np.loadtxt(folder / "error_map_kappa0.csv", delimiter=",",
                                                                      skiprows=1))
    table = (folder / "table.md").read_text()
    assert f"{r0['eps_bar']['p95']:.3g}" in table
    for f in ("certified_error_map.png", "tightness_map.png", "coverage_curve.png"):
        assert (folder / f).stat().st_size > 1000
    again = run(_cfg(tiny_maps, tmp_path))  # same config, same id: skipped
    assert again["skipped"] and again["path"] == folder
    assert json.loads((folder / "summary.json").read_text())["id"] == s["id"]


@pytest.mark.parametrize("override, field", [
    ("tolerance=-1", "tolerance"), ("kappas=[]", "kappas"), ("mode=exact", "mode"), ("max_depth=-1", "max_depth"),
    ("region=[[1,0],[0,1]]", "region"), ("samples=0", "samples"), ("dtype=half", "dtype"), ("cell=0", "cell"),
    ("pgd_cells=-1", "pgd_cells"), ("pgd_steps=0", "pgd_steps"), ("headings=0", "headings"),
])
def test_bad_settings_are_one_line(override, field, tmp_path):
    from pipeline.certify.checks import check

    with pytest.raises(PipelineError) as err:
        preflight("certify", [override, f"paths.outputs_dir={tmp_path}"], check)
    assert err.value.field == field and "\n" not in str(err.value), str(err.value)


def test_bad_key_on_the_command_line_is_one_line_exit_2(tmp_path):
    # in this process (tests/shared.py): a fresh interpreter's start-up is tests/test_config_truth.py's
    proc = run_cli("pipeline.certify", "tolerence=1", f"paths.root_dir={tmp_path}", f"hydra.run.dir={tmp_path / 'run'}")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "tolerence" in lines[0], proc.stderr
    assert not (tmp_path / "outputs" / "certified").exists()


def test_a_file_where_the_certified_folder_should_be_is_one_line(tiny_maps, tmp_path, monkeypatch):
    """The certified error map's folder taken by a file: one line naming it, exit 2 (issue 27's rule)."""
    import shutil

    from pipeline.certify.stage import run

    root, ids = tiny_maps
    without_figures(monkeypatch, "certify")  # both runs: the claim is the one line
    folder = run(_cfg(tiny_maps, tmp_path, "kappas=[0.0]"))["path"]
    shutil.rmtree(folder)
    folder.write_text("x")
    proc = run_cli("pipeline.certify", "debug=tiny", f"maps={ids['clean']}", f"paths.models_dir={root / 'models'}",
                   f"paths.certified_dir={tmp_path / 'certified'}", "progress=false", "kappas=[0.0]",
                   f"hydra.run.dir={tmp_path / 'cli'}")  # in this process (tests/shared.py)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "a file where" in lines[0], proc.stderr[-2000:]


def test_certify_reports_its_pgd_progress_and_names_the_region(tiny_maps, tmp_path, monkeypatch, capsys):
    """Issue 46: the PGD phase printed nothing (a documented command looked hung for 270 s), and the closing line
    said "over the operational set" when a `region` was given (debug=tiny's: [[30, 46], [-6, 6]])."""
    from pipeline import progress as pr
    from pipeline.certify.stage import run

    without_figures(monkeypatch, "certify")  # the claim: the progress lines and the region's wording
    monkeypatch.setattr(pr, "LINE_INTERVAL", 0.0)
    monkeypatch.setattr(pr, "DELAY", 0.0)
    root, ids = tiny_maps
    out = run(compose("certify", ["debug=tiny", f"maps={ids['clean']}", f"paths.models_dir={root / 'models'}",
                                  f"paths.certified_dir={tmp_path / 'certified'}", "progress=true", "kappas=[0.0]"]))
    cap = capsys.readouterr()
    total = 4 * out["summary"]["kappas"]["0"]["pgd"]["cells"]  # one ascent per cell and direction
    steps = re.findall(rf"PGD kappa=0: (\d+)/{total} ascent", cap.err)
    assert steps and int(steps[-1]) == total, cap.err[-2000:]
    assert re.search(r"certify kappa=0: \d+/\d+ cell", cap.err), cap.err[-2000:]  # the bounds' lines, same style
    n = out["summary"]["n_cells"]
    region = f"over the region x in [30, 46], y in [-6, 6] (its {n} operational cells)"
    closing = [ln for ln in cap.out.splitlines() if "certified eps over" in ln]
    assert len(closing) == 1 and region in closing[0] and "operational set" not in closing[0], cap.out
    assert out["summary"]["region"] == [[30.0, 46.0], [-6.0, 6.0]]
    assert region in (out["path"] / "table.md").read_text()
    from pipeline.certify.figures import scope

    assert scope(None) == "the operational set"  # without a region the wording stays


def test_diamond_include_covers_the_diamond_but_not_the_disc_interior():
    """Issue 48: the hybrid law's runs slide along the diamond's faces and dip into it, and the operational set
    (the errormap stage's) leaves the diamond out, so the bracket found no bound along 51 start cells' runs.
    `diamond=include` certifies its cells too, but not those wholly inside the disc (no run is there)."""
    from pipeline.certify.stage import cells_of
    from pipeline.config import build
    from pipeline.control.covering import in_diamond

    scene = build(compose("bracket", []).scene, "scene")
    arena = ((-50.0, 50.0), (-30.0, 30.0))
    cells, _, _, _, op = cells_of(arena, 0.5, None, scene, 1.5)
    _, _, _, _, inc = cells_of(arena, 0.5, None, scene, 1.5, "include")
    centres = np.column_stack([cells[:, :2].mean(1), cells[:, 2:].mean(1)])
    dia = in_diamond(scene, centres)
    assert not op[dia].any() and inc[dia].any()
    assert np.array_equal(inc[~dia], op[~dia])  # nothing changes outside the diamond
    o = scene.obstacles[0]
    corners = np.stack([np.hypot(cells[:, i] - o.center[0], cells[:, j] - o.center[1])
                        for i in (0, 1) for j in (2, 3)], 1)
    wholly = corners.max(1) <= o.radius
    assert wholly.any() and not inc[wholly].any()
    assert inc[dia & ~wholly].all()  # every diamond cell that a run can reach, the cells meeting the circle too


def test_the_pgd_attacks_the_leaves_a_split_cell_was_bounded_on(tiny_maps, tmp_path, monkeypatch):
    """A split cell's bound is the union of its leaves' bounds, each over the leaf's own relaxation of the renderer;
    the PGD attacked the whole cell's relaxation, wider, and reported "violations" that no image of a leaf has (the
    arena's border, 2026-12-05). With every cell split once (`tolerance=1e-9`) each attacked box is a quarter of a
    drawn cell: one of its leaves."""
    import pipeline.certify.attack as attack
    from pipeline.certify.stage import run

    boxes = []
    real = attack.pgd_worst

    def spy(model, camera, cells, *a, **k):
        boxes.append(np.asarray(cells, float))
        return real(model, camera, cells, *a, **k)

    monkeypatch.setattr(attack, "pgd_worst", spy)
    without_figures(monkeypatch, "certify")  # the claim: the boxes the PGD attacks
    out = run(_cfg(tiny_maps, tmp_path, "kappas=[0.0]", "max_depth=1", "tolerance=1e-9"))
    s = out["summary"]
    assert s["kappas"]["0"]["depth"]["1"] == s["n_cells"]
    b = np.concatenate(boxes)
    assert len(b) == s["kappas"]["0"]["pgd"]["cells"] == 4
    assert np.allclose(b[:, 1] - b[:, 0], s["cell"] / 2) and np.allclose(b[:, 3] - b[:, 2], s["cell"] / 2)
    cells = np.load(out["path"] / "cells.npz")
    x, y = cells["x"], cells["y"]  # each leaf lies in an operational cell of the grid
    for x0, x1, y0, y1 in b:
        i, j = np.argmin(np.abs(y - (y0 + y1) / 2)), np.argmin(np.abs(x - (x0 + x1) / 2))
        assert cells["operational"][i, j] and abs(x[j] - x0) <= s["cell"] / 2 and abs(y[i] - y0) <= s["cell"] / 2
