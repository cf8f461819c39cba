"""The bracket with a clouds table as `ε̄` (pipeline.bracket.clouds, issue 44): read as the clouds app writes it,
refused where its claim would not hold, and each certified start's failure over the clouds bounded by `F δ`."""

from __future__ import annotations

import json
from types import SimpleNamespace

import numpy as np
import pandas as pd
import pytest

from pipeline import tracking
from pipeline.config import compose
from pipeline.errors import ConfigError

TINY = ["bracket.cell=2.0", "bracket.start_cell=20", "bracket.eps=[0.1]", "bracket.n_bisect=0", "bracket.n_dirs=8",
        "bracket.tail=4", "bracket.lookahead=4", "bracket.commit=4", "bracket.refine=0", "bracket.map_bisect=1",
        "bracket.controllers=[hybrid]", "bracket.trap_dirs=8", "bracket.n_random=0", "bracket.funnel_split=0",
        "sim.horizon=12"]


def clouds_output(root, eps, delta=0.01, model="m1", cell=2.0, name="occluded_keypoint_heavy", gate=None):
    """A clouds output as `pipeline.certify.clouds_run` writes it (its own writer and a tracked folder), over the
    default arena in cells of `cell` with `eps_bar_delta = eps(x, y)` at their centres (with `gate`: the gated
    columns too, `eps_bar_delta_gated` a tenth of it)."""
    from pipeline.certify.clouds_run import write

    xs, ys = np.arange(-50.0, 50.0, cell), np.arange(-30.0, 30.0, cell)
    cells = np.array([[x, x + cell, y, y + cell] for x in xs for y in ys])
    e = np.array([eps(x + cell / 2, y + cell / 2) for x, _, y, _ in cells], float)
    arrays = {"eps_bar_delta": e, "share": np.ones(len(e)), "violation_cp": np.full(len(e), delta), "eps_clear": e,
              "eps_bar_delta_gated": e / 10, "flagged_share": np.full(len(e), 0.5), "undecided_share": np.zeros(len(e))}
    summary = {"map": f"occluded_keypoint-{model}", "occlusion": "heavy", "cells": len(e), "layouts": 299,
               "delta": delta, "confidence": 0.95, **({"gated": {"gate": gate}} if gate is not None else {})}
    id_ = tracking.content_id(summary, e.tolist())
    with tracking.tracked_output(root / "clouds", name, id_, {"recipe": summary, "inputs": {"model": model}}) as tmp:
        write(tmp, cells, arrays, summary)
    return root / "clouds" / f"{name}-{id_}"


def test_a_clouds_table_is_read_as_its_eps_bar_delta_alone(tmp_path):
    """By folder, by name-id under `certified_dir/clouds` and by its table.csv: the bound per cell is the table's
    `eps_bar_delta` with the claim (δ, confidence, cells, map) beside it; beside another table, at κ > 0 or with the
    camera's κ_lo: one line naming the field."""
    from pipeline.bracket.maps import error_map

    folder = clouds_output(tmp_path / "c", lambda x, y: 0.25 + 0.01 * abs(x))
    cfg = SimpleNamespace(paths=SimpleNamespace(certified_dir=str(tmp_path / "c")))
    box = np.array([[10.5, 11.5, 0.5, 1.5], [-50.0, -48.0, 4.0, 6.0], [11.0, 13.0, 0.5, 1.5]])
    for ref in (str(folder), folder.name, str(folder / "table.csv")):
        emap = error_map(cfg, SimpleNamespace(error_map=ref, error_map_kappa=0.0))
        np.testing.assert_allclose(emap(box[:, [0, 2]], box), [0.36, 0.74, 0.38])  # the largest of the cells met
        assert emap.clouds.delta == 0.01 and emap.clouds.confidence == 0.95 and emap.clouds.map_id == "m1"
        assert emap.clouds.cells == 1500 and emap.clouds.joint_confidence == 0.0  # 1500 x 5 % > 1: vacuous
    clean = tmp_path / "c" / "m-aaa"
    clean.mkdir()
    (clean / "summary.json").write_text(json.dumps({"model": {"id": "m1"}}))
    pd.DataFrame([[0.0, 1.0, 0.0, 1.0, 0.5]], columns=["x0", "x1", "y0", "y1", "eps_bar"]).to_csv(
        clean / "error_map_kappa0.csv", index=False)
    cases = [(SimpleNamespace(error_map=[str(clean / "error_map_kappa0.csv"), str(folder)], error_map_kappa=0.0), None,
              "bracket.error_map", "read alone"),
             (SimpleNamespace(error_map=str(folder), error_map_kappa=1.0), None, "bracket.error_map_kappa", "kappa 0"),
             (SimpleNamespace(error_map=str(folder), error_map_kappa=0.0), tmp_path, "bracket.camera_map", "clean-image")]
    for bs, cam, field, says in cases:
        with pytest.raises(ConfigError, match=says) as err:
            error_map(cfg, bs, camera_folder=cam)
        assert err.value.field == field
    with pytest.raises(ConfigError) as err:  # a name no output has: still one line naming the field
        error_map(cfg, SimpleNamespace(error_map="occluded_keypoint_heavy-0000000000", error_map_kappa=0.0))
    assert err.value.field == "bracket.error_map"


def test_the_bracket_bounds_each_certified_run_s_failure_over_the_clouds_by_F_delta(tmp_path):
    """With a clouds table, every start certified with it gets `clouds_p_fail = min(1, F δ)`, `F` its certified
    arrival bound in frames (`map_arrival_bound`, which the nominal run keeps); the others NaN; the table and
    `certificate.json` say it; the same bounds at another `δ` are another output."""
    from pipeline.bracket.stage import bracket_id, objects, run

    delta = 0.002
    folder = clouds_output(tmp_path / "c", lambda x, y: 0.1, delta=delta)
    args = [*TINY, f"paths.outputs_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"]
    cfg = compose("bracket", [*args, f"bracket.error_map={folder}"])
    out = run(cfg)
    df, period = out["bracket"], float(cfg.camera.period)
    cert = df.certified_map.astype(bool).to_numpy()
    assert cert.sum() >= 3, df[["x0", "y0", "certified_map", "eps_lo"]]
    frames = df.map_arrival_bound.to_numpy() / period
    np.testing.assert_allclose(frames[cert], np.round(frames[cert]))  # whole frames
    assert (df.arrival_nominal[cert] <= df.map_arrival_bound[cert] + 1e-9).all()
    np.testing.assert_allclose(df.clouds_p_fail[cert], np.minimum(1.0, frames[cert] * delta))
    assert (df.clouds_p_fail[cert] < 1).any()
    assert df.clouds_p_fail[~cert].isna().all() and df.map_arrival_bound[~cert].isna().all()
    assert "clouds: P(fail) per run <=" in (out["path"] / "table.md").read_text()
    stats = json.loads((out["path"] / "certificate.json").read_text())["hybrid"]["error_map"]["clouds"]
    assert stats["delta"] == delta and stats["cells"] == 1500 and stats["joint_confidence"] == 0.0
    other = compose("bracket", [*args, f"bracket.error_map={clouds_output(tmp_path / 'd', lambda x, y: 0.1)}"])
    _, _, bs, _, _, emap, cam, _ = objects(other)
    assert emap.clouds.delta == 0.01 and bracket_id(other, bs, emap, cam)[0] != out["path"].name.split("-")[-1]


def test_the_gated_column_is_read_for_a_loop_that_drops_what_the_table_flags(tmp_path):
    """`bracket.error_map_gated`: the table's `eps_bar_delta_gated`, for a loop gated at most at the table's gate and
    losing frames (`bracket.lost_frames`); a loop gated higher or not at all, a table certified without a gate, or the
    key without a clouds table: one line naming the field."""
    from pipeline.bracket.stage import objects

    root = tmp_path
    gated, plain = (clouds_output(root / k, lambda x, y: 2.0, gate=g) for k, g in (("g", 0.56), ("p", None)))
    base = [*TINY, f"paths.outputs_dir={root}", "bracket.error_map_gated=true", "bracket.lost_frames=2"]
    box = np.array([[10.5, 11.5, 0.5, 1.5]])
    emap = objects(compose("bracket", [*base, f"bracket.error_map={gated}", "camera.gate=0.5"]))[5]
    assert emap(box[:, [0, 2]], box)[0] == pytest.approx(0.2) and emap.clouds.gate == 0.56
    assert "dropped in a row" in emap.clouds.summary()["per_run"]
    ungated = objects(compose("bracket", [*TINY, f"paths.outputs_dir={root}", f"bracket.error_map={gated}"]))[5]
    assert ungated(box[:, [0, 2]], box)[0] == 2.0 and ungated.clouds.gate is None
    for args, field in (([f"bracket.error_map={gated}", "camera.gate=0.6"], "camera.gate"),
                        ([f"bracket.error_map={gated}", "bracket.lost_frames=0", "camera.gate=0.5"], "camera.gate"),
                        ([f"bracket.error_map={plain}", "camera.gate=0.5"], "bracket.error_map_gated")):
        with pytest.raises(ConfigError) as err:
            objects(compose("bracket", [*base, *args]))
        assert err.value.field == field, err.value
    clean = root / "m-aaa"
    clean.mkdir()
    pd.DataFrame([[0.0, 1.0, 0.0, 1.0, 0.5]], columns=["x0", "x1", "y0", "y1", "eps_bar"]).to_csv(
        clean / "table.csv", index=False)
    with pytest.raises(ConfigError) as err:
        objects(compose("bracket", [*base, f"bracket.error_map={clean / 'table.csv'}", "camera.gate=0.5"]))
    assert err.value.field == "bracket.error_map_gated"
