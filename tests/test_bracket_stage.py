"""The bracket stage end to end on a tiny configuration, and its bad inputs (one line naming the key)."""

from __future__ import annotations

import json

import numpy as np
import pandas as pd
import pytest

from pipeline.config import compose
from pipeline.errors import ConfigError

TINY = ["bracket.cell=4.0", "bracket.start_cell=20", "bracket.eps=[0.1,0.25]", "bracket.n_bisect=0",
        "bracket.n_dirs=8", "bracket.tail=4", "bracket.lookahead=4", "bracket.commit=4", "sim.horizon=8",
        "bracket.polytope_split=0"]  # the polytopes have their own tests (test_bracket_loop_that_runs.py): 27 s here
# cells of 1.5 without the back vertex's window certify a third of the start cells: the soundness checks bite
CERTIFYING = ["bracket.cell=1.5", "bracket.refine=0"]


def test_tiny_bracket_run(tmp_path):
    from pipeline.bracket.stage import run

    cfg = compose("bracket", [*TINY, *CERTIFYING, f"paths.outputs_dir={tmp_path}",
                              f"paths.output_dir={tmp_path / 'run'}"])
    out = run(cfg)
    folder = out["path"]
    assert folder.parent == tmp_path / "bracket" and folder.name.startswith("bracket-") and not out["skipped"]
    df = pd.read_csv(folder / "bracket.csv")
    n = len(df) // 3
    assert list(df.controller.unique()) == ["hybrid", "smooth", "cbf"] and len(df) == 3 * n
    # soundness: no start cell certified at an ε the falsifier broke (the stage's own check, re-read from disk)
    assert not (df.eps_lo > df.eps_hi).any()
    assert (df.eps_lo.dropna().isin([0.1, 0.25])).all()
    for name in ("hybrid", "smooth", "cbf"):  # not vacuous: each law has certified and falsified start cells
        rows = df[df.controller == name]
        assert rows.eps_lo.notna().any() and np.isfinite(rows.eps_hi).any(), name
    tab = (folder / "table.md").read_text()
    assert tab.count("\n| ") == 3 and "soundness" in tab
    paths = np.load(folder / "counterexamples.npz")
    falsified = np.isfinite(df.eps_hi.to_numpy()) & (df.adversary != "start in obstacle").to_numpy()
    for name in ("hybrid", "smooth", "cbf"):
        rows = falsified[df.controller == name]
        assert np.isfinite(paths[name][:, rows]).all()  # every counterexample comes with its path
    assert out["table"].shape[0] == 3
    # lineage: the same config is the same folder, not recomputed; what changes the numbers changes the id
    again = run(cfg)
    assert again["skipped"] and again["path"] == folder
    pd.testing.assert_frame_equal(again["bracket"], df)
    other = run(compose("bracket", [*TINY, "bracket.eps=[0.1]", "bracket.controllers=[cbf]", "sim.horizon=4",  # cheaper
                                    f"paths.outputs_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"]))
    assert other["path"] != folder and not other["skipped"]


def test_laws_side_by_side_give_the_same_bytes(tmp_path, monkeypatch):
    """The laws run in spawned processes, one per core of the job's share (`OMP_NUM_THREADS`, as `make paper` sets
    it), and the bracket's files are byte-identical to the run one law after another. A 4 s horizon (the laws' rows
    still differ: each law falsified from most start cells, adversaries and ε_hi per row) halves the two runs."""
    from pipeline.bracket import stage

    files = {}
    for cores in ("1", "2"):
        monkeypatch.setenv("OMP_NUM_THREADS", cores)
        assert stage.law_workers(3) == int(cores)
        root = tmp_path / cores
        out = stage.run(compose("bracket", [*TINY, "bracket.refine=0", "bracket.funnel_split=0",  # the laws' workers
                                            "bracket.eps=[0.1]", "sim.horizon=4", f"paths.outputs_dir={root}",
                                            f"paths.output_dir={root / 'run'}"]))
        files[cores] = {f: (out["path"] / f).read_bytes() for f in ("bracket.csv", "table.md")}
    assert files["1"] == files["2"]


@pytest.mark.parametrize("override,field", [
    ("bracket.commit=20", "bracket.commit"),
    ("bracket.eps=[0.5,0.1]", "bracket.eps"),
    ("bracket.cell=-1", "bracket.cell"),
    ("bracket.controllers=[hybrid,pid]", "bracket.controllers"),
    ("bracket.error_map=/nonexistent/map.csv", "bracket.error_map"),
    ("bracket.error_map=clean_keypoint-0000000000", "bracket.error_map"),  # a certify output by name-id, not built
    ("bracket.error_map=[]", "bracket.error_map"),
    ("camera.period=null", "camera.period"),
])
def test_bad_bracket_input_is_one_config_error(tmp_path, override, field):
    from pipeline.bracket.stage import check
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("bracket", [override, f"hydra.run.dir={tmp_path}"], check)
    assert err.value.field.startswith(field) and "\n" not in str(err.value), str(err.value)


def test_settings_defaults_are_the_yaml():
    """What runs is the YAML: `BracketSettings()` built in Python has conf/bracket.yaml's values."""
    from dataclasses import asdict

    import yaml

    from pipeline.bracket.settings import BracketSettings
    from pipeline.cli import CONF_DIR

    node = yaml.safe_load((CONF_DIR / "bracket.yaml").read_text())["bracket"]
    node.pop("_target_")
    assert node == asdict(BracketSettings())


def test_a_file_where_the_bracket_folder_should_be_is_one_line(tmp_path):
    """The tracked output's folder taken by a file: one line naming it, exit 2 (issue 27's rule, in this stage).
    The folder's path is the stage's own (`bracket_id` of the objects it builds; a wrong path would let the run go
    through, exit 0); the command runs in this process (`run_cli`: it ends before any work)."""
    from pathlib import Path

    from shared import run_cli

    from pipeline.bracket.stage import bracket_id, objects

    args = [*TINY, "bracket.controllers=[cbf]", f"paths.outputs_dir={tmp_path}"]
    cfg = compose("bracket", [*args, f"paths.output_dir={tmp_path / 'run'}"])
    _, _, bs, _, _, emap, cam, _ = objects(cfg)
    folder = Path(cfg.paths.bracket_dir) / f"bracket-{bracket_id(cfg, bs, emap, cam)[0]}"
    folder.parent.mkdir(parents=True)
    folder.write_text("x")
    proc = run_cli("pipeline.bracket", *args, f"hydra.run.dir={tmp_path / 'cli'}")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "a file where" in lines[0] and str(folder) in lines[0], \
        proc.stderr[-2000:]


@pytest.mark.parametrize("arg, field", [("controller.saturation=tangent", "controller.saturation"),
                                        ("controller.noise_tolerance=0.3", "controller.noise_tolerance")])
def test_a_hybrid_rule_the_abstraction_does_not_model_is_rejected(tmp_path, arg, field):
    """The certificate's enclosures model §3.3's law; the dense design's rules (the tangent saturation, the side
    hysteresis) would let the real loop leave the abstraction: rejected in one line, exit 2, before any work (run in
    this process: `run_cli`)."""
    from shared import run_cli

    proc = run_cli("pipeline.bracket", arg, f"hydra.run.dir={tmp_path}")
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}:"), proc.stderr[-2000:]


def _certify_output(folder, model_id, rows):
    folder.mkdir(parents=True)
    (folder / "summary.json").write_text(json.dumps({"model": {"id": model_id}}))
    pd.DataFrame(rows, columns=["x0", "x1", "y0", "y1", "eps_bar"]).to_csv(folder / "error_map_kappa0.csv", index=False)
    return folder


def test_several_error_maps_give_the_smallest_bound_per_cell(tmp_path):
    """A whole-arena table and one refined on a region (of one perception map): a grid cell inside the region takes
    the refined bound, one the region covers only in part keeps the whole table's; two maps' tables are refused."""
    from types import SimpleNamespace

    from pipeline.bracket.bounds import Finest
    from pipeline.bracket.maps import error_map

    whole = _certify_output(tmp_path / "c" / "m-aaa", "m1", [[x, x + 1, y, y + 1, 2.0] for x in range(-4, 4)
                                                             for y in range(-4, 4)])
    region = _certify_output(tmp_path / "c" / "m-bbb", "m1", [[x / 2, x / 2 + 0.5, y / 2, y / 2 + 0.5, 0.5]
                                                              for x in range(0, 4) for y in range(0, 4)])
    cfg = SimpleNamespace(paths=SimpleNamespace(certified_dir=str(tmp_path / "c")))
    table = lambda f: str(f / "error_map_kappa0.csv")  # noqa: E731 - a certify output's table, beside its summary
    emap = error_map(cfg, SimpleNamespace(error_map=[table(whole), table(region)], error_map_kappa=0.0))
    assert isinstance(emap, Finest)
    boxes = np.array([[0.0, 1.0, 0.0, 1.0], [1.5, 2.5, 0.0, 1.0], [-3.0, -2.0, 0.0, 1.0], [3.5, 4.5, 0.0, 1.0]])
    np.testing.assert_array_equal(emap(boxes[:, [0, 2]], boxes), [0.5, 2.0, 2.0, np.inf])
    other = _certify_output(tmp_path / "c" / "m-ccc", "m2", [[0.0, 1.0, 0.0, 1.0, 0.1]])
    with pytest.raises(ConfigError, match="different perception maps") as err:
        error_map(cfg, SimpleNamespace(error_map=[table(whole), table(other)], error_map_kappa=0.0))
    assert err.value.field == "bracket.error_map"


def test_error_map_kappa_reads_the_table_at_that_pixel_budget_and_refuses_what_cannot_vouch_for_it(tmp_path):
    """`bracket.error_map_kappa`: a certify output's table at that budget (another budget's bounds differ); a budget the
    output does not hold, a table that is not a certify output's at that budget, or a camera map other than the one
    the tables bound: one line naming the field."""
    from types import SimpleNamespace

    from pipeline.bracket.bounds import CellTable
    from pipeline.bracket.maps import error_map

    folder = _certify_output(tmp_path / "c" / "m-aaa", "m1", [[0.0, 1.0, 0.0, 1.0, 0.5]])
    pd.DataFrame([[0.0, 1.0, 0.0, 1.0, 3.0]], columns=["x0", "x1", "y0", "y1", "eps_bar"]).to_csv(
        folder / "error_map_kappa1.csv", index=False)
    cfg = SimpleNamespace(paths=SimpleNamespace(certified_dir=str(tmp_path / "c")))
    box = np.array([[0.0, 1.0, 0.0, 1.0]])
    assert CellTable(folder).cells[0, 4] == 0.5 and CellTable(folder, kappa=1.0).cells[0, 4] == 3.0
    with pytest.raises(ConfigError, match=r"no table at kappa 2 \(its kappas: 0, 1\)") as err:
        CellTable(folder, kappa=2.0)
    assert err.value.field == "bracket.error_map_kappa"
    at = lambda k, ref=str(folder / "error_map_kappa1.csv"), cam=None: error_map(  # noqa: E731
        cfg, SimpleNamespace(error_map=ref, error_map_kappa=k), camera_folder=cam)(box[:, [0, 2]], box)
    assert at(1.0)[0] == 3.0
    with pytest.raises(ConfigError, match="nothing vouches") as err:
        at(1.0, str(folder / "error_map_kappa0.csv"))
    assert err.value.field == "bracket.error_map_kappa"
    cam = tmp_path / "models" / "other-0123456789"
    cam.mkdir(parents=True)
    (cam / "manifest.json").write_text(json.dumps({"id": "other"}))
    with pytest.raises(ConfigError, match="the attacked map's") as err:
        at(1.0, cam=cam)
    assert err.value.field == "bracket.error_map"
    (cam / "manifest.json").write_text(json.dumps({"id": "m1"}))
    assert at(1.0, cam=cam)[0] == 3.0


def test_a_named_tuning_reaches_every_object_and_the_id_and_an_override_after_it_wins():
    """`tuning=wide_barrier` (conf/tuning/) sets the scene's barrier, the hybrid law's hysteresis and the bracket's
    frames in the objects the stage builds, so the output's id changes; a key given after it on the command line
    wins; `tuning=paper` is the default config, byte for byte."""
    from pipeline.bracket.stage import bracket_id, objects

    def built(*overrides):
        cfg = compose("bracket", list(overrides))
        scene, laws, bs, _, _, emap, cam, _ = objects(cfg)
        return scene, laws["hybrid"], bs, bracket_id(cfg, bs, emap, cam)[0]

    scene, hybrid, bs, paper_id = built()
    assert built("tuning=paper")[3] == paper_id
    w_scene, w_hybrid, w_bs, wide_id = built("tuning=wide_barrier")
    assert (w_scene.barrier.gain, w_scene.barrier.rho, w_bs.frames) == (300.0, 1.0, 3)
    assert (w_hybrid.chi, w_hybrid.lam) == (1.5, 0.2) != (hybrid.chi, hybrid.lam)
    assert scene.barrier.gain == 1.0 and bs.frames == 4 and wide_id != paper_id
    assert built("tuning=wide_barrier", "bracket.frames=4", "scene.barrier.gain=1.0")[2].frames == 4
    assert built("tuning=wide_barrier", "scene.barrier.gain=1.0")[0].barrier.gain == 1.0


def test_table_counts_map_certified_cells_the_clean_camera_loop_breaks():
    """With an error map and a camera map, a start cell certified with the map's ε̄ whose clean camera loop failed
    (κ_hi = 0) contradicts the chain (the map's bound, the certificate): the table counts it; the map column says how
    many of the certified cells lie behind the obstacle."""
    from pipeline.bracket.report import table
    from pipeline.config import build

    scene = build(compose("bracket").scene, "scene")
    rows = [(-30.0, -25.0, -2.5, 2.5, True, 0.0), (-30.0, -25.0, 2.5, 7.5, True, 5.0), (20.0, 25.0, 2.5, 7.5, True, 0.0),
            (20.0, 25.0, 7.5, 12.5, False, 0.0)]
    df = pd.DataFrame([{"controller": "hybrid", "x0": x0, "x1": x1, "y0": y0, "y1": y1, "eps_lo": 0.1,
                        "certified_map": cm, "eps_hi": np.inf, "kappa_hi": k} for x0, x1, y0, y1, cm, k in rows])
    row = table(df, scene, [0.1], with_map=True).iloc[0]
    assert row["soundness: κ_hi <= κ_lo"] == 2 and row["camera: certified (κ_lo)"] == "75% (3 at κ_lo 0)"
    assert row["map ε̄: certified"] == "75% (2/2 behind)"
    assert "soundness: κ_hi <= κ_lo" not in table(df.drop(columns="kappa_hi"), scene, [0.1], True)
    # certified with the map's ε̄ at a pixel budget of 5 levels (κ_lo = 5): a camera failure at 5 or below breaks it
    df["kappa_lo"] = np.where(df.certified_map, 5.0, np.nan)
    df["kappa_hi"] = [6.0, 5.0, np.inf, 1.0]
    row = table(df, scene, [0.1], with_map=True).iloc[0]
    assert row["soundness: κ_hi <= κ_lo"] == 1 and row["camera: certified (κ_lo)"] == "75% (3 at κ_lo 5)"


def test_table_counts_the_start_cells_the_bracket_leaves_open():
    """`undecided at ε`: start cells neither certified at the largest ε nor falsified up to it (the bracket's open
    share, issue 48's measure); cells without a start (wholly in the diamond) are counted apart, not in any share."""
    from pipeline.bracket.report import table
    from pipeline.config import build

    scene = build(compose("bracket").scene, "scene")
    rows = [(0.5, np.inf, True), (np.nan, 0.25, True), (np.nan, np.inf, True), (0.25, np.inf, True),
            (np.nan, np.nan, False)]
    df = pd.DataFrame([{"controller": "hybrid", "x0": 20.0 + 5 * i, "x1": 25.0 + 5 * i, "y0": 10.0, "y1": 15.0,
                        "start": s, "eps_lo": lo, "certified_map": False, "eps_hi": hi}
                       for i, (lo, hi, s) in enumerate(rows)])
    row = table(df, scene, [0.25, 0.5]).iloc[0]
    assert row["undecided at ε=0.5"] == "50%"  # the uncertified-unfalsified one and the one certified only at 0.25
    assert row["start cells"] == "4 (+1 in the diamond)"
