"""Experiments stage (issue 6): every bundle runs on a tiny config; the scenarios' claims hold; tables carry
the numbers of the raw metrics; cached re-runs only re-draw; camera-in-the-loop with a trained map."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from shared import run_cli  # tests/shared.py

from pipeline.cli import CONF_DIR, REPO_ROOT, compose
from pipeline.errors import ConfigError, ModelError

BUNDLES = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))


def _cfg(tmp_path, *extra):
    publish = [] if any(e.startswith("publish=") for e in extra) else ["publish=true"]  # files in paths.paper_dir
    return compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                   *publish, *extra])


PAPER_FIGURES = {"perception_closeness": "fig1_perception_closeness", "sensitive_set": "fig2_sensitive_set",
                 "coverings": "fig3_coverings", "scheme": "fig4_scheme",
                 "leader_follower": "fig5_leader_follower_level_sets", "occlusion": "fig6_occlusion",
                 "noise_failure": "fig7_robustness_noise_failure"}  # the paper's figures, in its order (issue 12)


def _published(paper, bundles) -> str:
    """index.md of a paper folder, checked for a section per bundle, a figure (pdf + png) per bundle, LaTeX tables."""
    index = (paper / "index.md").read_text()
    for exp in bundles:
        assert f"## {exp} " in index, exp
    figures = sorted(paper.glob("fig*.pdf"))
    assert len(figures) >= len(bundles)
    for f in figures:
        assert f.with_suffix(".png").stat().st_size > 1000
    for tex in paper.glob("tab*.tex"):
        assert tex.read_text().startswith("\\begin{table}")
    return index


def test_the_papers_bundles_run_in_one_multirun_and_keep_its_order(tmp_path):
    """`-m experiment=<the paper's seven bundles> debug=tiny` with a perfect map, in one multirun and one paper
    folder: index.md lists fig1..fig7 in the paper's order whatever order the jobs ran in (the other bundles:
    `test_every_other_bundle_runs_at_debug_tiny`). The multirun runs in this process (`run_cli`, as `-m` runs
    it): nothing here is about a fresh interpreter (`test_bad_input` keeps a subprocess)."""
    proc = run_cli("pipeline.experiments", "-m", f"experiment={','.join(sorted(PAPER_FIGURES))}",
                   "debug=tiny", "perception=oracle", "publish=true", f"paths.paper_dir={tmp_path / 'paper'}",
                   f"paths.outputs_dir={tmp_path / 'out'}", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    index = _published(tmp_path / "paper", PAPER_FIGURES)
    stems = {f.stem for f in (tmp_path / "paper").glob("fig*.pdf")}
    assert stems == set(PAPER_FIGURES.values()), sorted(stems)
    positions = [index.index(f"{stem}.png") for stem in PAPER_FIGURES.values()]
    assert positions == sorted(positions)  # index.md lists them in the paper's order
    assert "paper Fig. 4" in index and (tmp_path / "paper" / "anim6_occlusion.gif").stat().st_size > 10_000


@pytest.mark.parametrize("bundle", [b for b in BUNDLES if b not in PAPER_FIGURES])
def test_every_other_bundle_runs_at_debug_tiny(tmp_path, bundle):
    """Every bundle beyond the paper's figures runs at `debug=tiny` with a perfect map and publishes its figure,
    numbered after the paper's seven (fig8 on)."""
    from pipeline.experiments.stage import run

    run(_cfg(tmp_path, f"experiment={bundle}", "debug=tiny", "perception=oracle"))
    _published(tmp_path / "paper", [bundle])
    stems = [f.stem for f in (tmp_path / "paper").glob("fig*.pdf")]
    assert all(int(s.split("_")[0][3:]) >= 8 for s in stems), stems


def test_noise_failure_perfect_map_succeeds(tmp_path):
    """The bundle's runs (its figure and GIF are drawn by `test_the_papers_bundles_run_in_one_multirun...`)."""
    from pipeline.experiments.checks import check

    scen, ctx = check(_cfg(tmp_path, "experiment=noise_failure", "perception=oracle"))
    m = scen.compute(ctx).tables["metrics"]
    assert set(m["role"]) == {"vehicle", "leader", "follower"}
    assert m["success"].all() and not m["collision"].any(), m
    assert (m["x0"].iloc[:2].tolist(), m["y0"].iloc[:2].tolist()) == ([-12.0, -37.0], [2.0, -17.0])


def test_sweep_smooth_stalls_hybrid_does_not(tmp_path):
    from pipeline.experiments.stage import run

    out = run(_cfg(tmp_path, "experiment=robustness_sweep", "perception=oracle", "scale=0.1",
                   "experiment.eps=[0.5]", "experiment.disturbances=[adversarial]", "sim.horizon=12"))
    sweep = out["results"].tables["sweep"].set_index("controller")
    assert sweep.loc["hybrid", "success_rate"] == 1.0 and sweep.loc["hybrid", "stalled"] == 0.0
    assert sweep.loc["smooth", "success_rate"] == 0.0 and sweep.loc["smooth", "stalled"] == 1.0  # stalled, not late
    assert sweep.loc["cbf", "success_rate"] <= 0.05


def test_tables_carry_the_raw_metrics_and_cache_redraws(tmp_path):
    from pipeline.experiments.stage import run

    cfg = _cfg(tmp_path, "experiment=monte_carlo", "perception=oracle", "scale=0.1",
               "experiment.controllers=[hybrid,smooth]", "experiment.camera=false")
    first = run(cfg)
    paper = tmp_path / "paper"
    raw = pd.read_csv(paper / "metrics_monte_carlo.csv")
    table = pd.read_csv(paper / "tab1_monte_carlo.csv")
    for (cond, ctrl), g in raw.groupby(["condition", "controller"]):
        row = table[(table.condition == cond) & (table.controller == ctrl)].iloc[0]
        assert row["n"] == len(g)
        assert row["success_rate"] == pytest.approx(g["success"].mean())
        assert row["collision_rate"] == pytest.approx(g["collision"].mean())
        ok = g[g["success"]]
        if len(ok):
            assert row["median_time"] == pytest.approx(np.median(ok["time_to_target"]))
        assert row["success_lo"] <= row["success_rate"] <= row["success_hi"]
    md = (paper / "tab1_monte_carlo.md").read_text()
    assert f"{table.iloc[0]['median_time']:.3g}" in md
    assert not first["cached"]

    png = paper / "fig9_monte_carlo.png"
    mtime = png.stat().st_mtime_ns
    second = run(cfg)
    assert second["cached"] and second["cache"] == first["cache"]
    assert png.stat().st_mtime_ns == mtime  # nothing it shows changed: not redrawn (issue 32)
    third = run(_cfg(tmp_path, "experiment=monte_carlo", "perception=oracle", "scale=0.1",
                     "experiment.controllers=[hybrid,smooth]", "experiment.camera=false", "experiment.title=t2"))
    assert third["cached"] and png.stat().st_mtime_ns > mtime  # its title changed: re-drawn from the cache
    pd.testing.assert_frame_equal(pd.read_csv(paper / "metrics_monte_carlo.csv"), raw)


def test_determinism_same_config_same_numbers(tmp_path):
    from pipeline.experiments.stage import run

    a = run(_cfg(tmp_path / "a", "experiment=noise_failure", "perception=oracle", "debug=tiny"))["results"]
    b = run(_cfg(tmp_path / "b", "experiment=noise_failure", "perception=oracle", "debug=tiny"))["results"]
    pd.testing.assert_frame_equal(a.tables["metrics"], b.tables["metrics"])
    np.testing.assert_array_equal(a.arrays["foll_p"], b.arrays["foll_p"])


def test_bad_input(tmp_path):
    from pipeline.experiments.stage import run

    with pytest.raises(ConfigError, match="perception"):
        run(_cfg(tmp_path, "experiment=noise_failure", "perception=psychic"))
    with pytest.raises(ConfigError, match="experiment.nope"):
        run(_cfg(tmp_path, "experiment=noise_failure", "+experiment.nope=1"))
    with pytest.raises(ModelError, match="unknown perception map"):
        run(_cfg(tmp_path, "experiment=noise_failure", "maps.clean=nope", f"paths.models_dir={tmp_path / 'm'}"))
    proc = subprocess.run(
        [sys.executable, "-m", "pipeline.experiments", "experiment=noise_failure", "controller.chi=0.5",
         "perception=oracle", f"paths.paper_dir={tmp_path / 'p'}", f"paths.outputs_dir={tmp_path / 'o'}",
         f"hydra.run.dir={tmp_path / 'run'}"],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=300,
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr
    assert "controller.chi" in proc.stderr


def test_camera_in_the_loop_renders_all_agents_per_frame(tiny_maps):
    root, ids = tiny_maps
    from pipeline.control import HybridController, Scene
    from pipeline.perception.maps import load_perception_map
    from pipeline.perception.measure import CameraMeasure
    from pipeline.sim import CameraSettings, SimSettings, simulate

    pm = load_perception_map(ids["clean"], models_dir=root / "models")
    cam = pm.camera()
    scene = Scene(target=(40.0, 0.0))
    x0 = np.array([[-30.0, 10.0], [-20.0, -15.0], [10.0, 20.0]])
    measure = CameraMeasure(cam, pm)
    res = simulate(scene, HybridController(scene), x0,
                   sim=SimSettings(dt=0.01, horizon=0.5, record_every=5, stop_on_success=False),
                   camera=CameraSettings(period=0.05), measure=measure)
    assert measure.frames == 10 and measure.images == 30  # one batched call per frame, all agents
    # the perceived positions are the map's predictions on the rendered frames
    np.testing.assert_allclose(res.m[0], pm.predict(cam.render(x0)), atol=1e-5)


def test_occlusion_experiment_with_trained_maps(tiny_maps, tmp_path):
    from pipeline.experiments.stage import run

    root, ids = tiny_maps
    out = run(_cfg(tmp_path, "experiment=occlusion", "debug=tiny", f"paths.models_dir={root / 'models'}",
                   f"maps.clean={ids['clean']}", f"maps.occluded={ids['occluded']}"))
    summary = out["results"].tables["summary"]
    assert list(summary["map"]) == ["clean", "occluded"]
    index = (tmp_path / "paper" / "index.md").read_text()
    assert "map:clean" in index and "map:occluded" in index  # the ids of the maps used are listed


def test_margin_map_cell_against_a_direct_simulation(tmp_path):
    """One cell of the hysteresis margin map: robust just below the margin it reports, failing at the ε where
    its bisection stopped, checked by simulating those two ε directly (a bisection to 1 unit, as debug=tiny's:
    4 halvings of [0, 12], not 6)."""
    from pipeline.experiments.context import Context
    from pipeline.experiments.paper.theory import HysteresisMargin
    from pipeline.experiments.scenario import practical_success

    cfg = _cfg(tmp_path, "experiment=hysteresis_margin", "perception=oracle")
    ctx = Context(cfg)
    scen = HysteresisMargin(id="m", title="m", chi=[1.1], lam=[0.09], disturbances=["adversarial"], n_agents=12,
                            tol=1.0, success=0.99)
    res = scen.compute(ctx)
    row = res.tables["margin"].iloc[0]
    assert 0.0 < row.eps_margin < row.eps_fails < scen.eps_max
    assert row.eps_fails - row.eps_margin <= scen.tol
    x0 = res.arrays["x0"]
    for eps, robust in ((row.eps_margin, True), (row.eps_fails, False)):
        sim = ctx.simulate(ctx.controller("hybrid", chi=1.1, lam=0.09), x0,
                           disturbance=ctx.disturbance("adversarial", eps=eps), record=False, model=scen.time_model)
        rate = practical_success(sim, ctx.delta, eps).mean()
        assert (rate >= 0.99) == robust, (eps, rate)


def test_margin_map_cells_in_one_batch_are_each_cells_own_bisection(tmp_path):
    """The margin map's cells bisect in one batch per step (a hysteresis and a disturbance per agent): every
    cell's margin, failing ε and simulation count are those of its own bisection run alone, and every agent of a
    batched run ends as in its own cell's run: outcome, arrival time, jumps (which the hysteresis sets) and the
    practical success the bisection reads (docs/control.md: a batch's last agent to stop may end a few steps
    earlier than it would in a larger batch, so its final position is not compared)."""
    from pipeline.experiments.context import Context
    from pipeline.experiments.paper.theory import HysteresisMargin
    from pipeline.experiments.scenario import practical_success
    from pipeline.sim.disturbances import PerAgent

    ctx = Context(_cfg(tmp_path, "experiment=hysteresis_margin", "perception=oracle"))
    scen = HysteresisMargin(id="m", title="m", chi=[1.05, 1.8], lam=[0.01, 0.4], disturbances=["alternating"],
                            n_agents=8, tol=1.0, success=0.99, eps_max=8.0, time_model="sampled")
    x0, hybrid = scen.starts(ctx), ctx.controller("hybrid")
    cells, eps, n = scen.cells(), [2.0, 1.0, 2.0], len(x0)
    batch = scen.margins(ctx, x0, hybrid, "alternating", cells)
    alone = [scen.margins(ctx, x0, hybrid, "alternating", [cell])[0] for cell in cells]
    np.testing.assert_array_equal(np.array(batch), np.array(alone))
    chi, lam = (np.repeat([c[j] for c in cells], n) for j in (0, 1))
    both = ctx.simulate(hybrid.with_hysteresis(chi, lam), np.tile(x0, (len(cells), 1)), record=False,
                        disturbance=PerAgent([ctx.disturbance("alternating", eps=e) for e in eps], [n] * len(cells)),
                        model="sampled")
    jumps = []
    for k, (cell, e) in enumerate(zip(cells, eps)):
        own = ctx.simulate(hybrid.with_hysteresis(*cell), x0, disturbance=ctx.disturbance("alternating", eps=e),
                           record=False, model="sampled")
        for key in ("outcome", "termination", "success", "collision", "time_to_target", "jumps", "mode_jumps",
                    "pushouts", "guard_frames"):
            np.testing.assert_array_equal(np.asarray(both.metrics[key])[k * n:(k + 1) * n], own.metrics[key],
                                          err_msg=key)
        np.testing.assert_array_equal(practical_success(both, ctx.delta, e)[k * n:(k + 1) * n],
                                      practical_success(own, ctx.delta, e))
        jumps.append(own.metrics["jumps"].sum())
    assert len(set(jumps)) > 1  # the cells' runs differ: a batch that gave every agent one cell's law would show


def test_camera_in_the_loop_is_the_same_on_every_device(tiny_maps):
    """The closed loop with the CNN on each device present (CPU here; CUDA too on a GPU machine) gives the CPU
    run's perceived positions and trajectory up to float tolerance."""
    import torch

    from pipeline.control import HybridController, Scene
    from pipeline.perception.maps import load_perception_map
    from pipeline.perception.measure import CameraMeasure
    from pipeline.sim import CameraSettings, SimSettings, simulate

    root, ids = tiny_maps
    scene = Scene(target=(40.0, 0.0))
    x0 = np.array([[-30.0, 10.0], [-20.0, -15.0], [10.0, 20.0]])
    runs = {}
    for device in ["cpu", "auto"] + (["cuda"] if torch.cuda.is_available() else []):
        pm = load_perception_map(ids["clean"], models_dir=root / "models", device=device)
        runs[device] = simulate(scene, HybridController(scene), x0,
                                sim=SimSettings(dt=0.01, horizon=1.0, record_every=5, stop_on_success=False),
                                camera=CameraSettings(period=0.05), measure=CameraMeasure(pm.camera(), pm))
    for device, res in runs.items():
        np.testing.assert_allclose(res.m, runs["cpu"].m, atol=1e-3, err_msg=device)
        np.testing.assert_allclose(res.p, runs["cpu"].p, atol=1e-3, err_msg=device)


def test_leader_keeps_regulating_after_success(tmp_path):
    """Bug fix: the leader (the follower's moving target) used to stop on success on the delta-circle, so with a
    perfect map the followers' target sat ~delta from p_T and their strict success hung on which side of the
    circle perception noise pushed them. It now settles at p_T."""
    from pipeline.experiments.stage import run

    out = run(_cfg(tmp_path, "experiment=occlusion", "perception=oracle", "scale=0.1"))
    lead = out["results"].arrays["occluded_lead_p"]
    assert np.hypot(*(lead[-1] - np.array([40.0, 0.0]))) < 0.05
    t = out["results"].tables["summary"]
    assert (t["success_rate"] == 1.0).all(), t


def test_a_run_on_the_side_never_replaces_a_pinned_paper_figure(tmp_path):
    """Once make paper has pinned an experiment's computation (`paper.lock.yaml`), a run of it with another config
    writes to `paths.side_dir/<experiment>-<id>/` and leaves the paper's figure, table and index entry as pinned;
    the pinned computation itself, and `publish=true` (what make paper passes), still write to the paper
    (`publish=auto`; the default, false, always writes to the side folder)."""
    import json

    from omegaconf import OmegaConf

    from pipeline.experiments.stage import run

    paper = tmp_path / "paper"
    fig = paper / "fig3_coverings.png"
    pinned = run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "publish=auto"))
    assert fig.is_file() and pinned["files"][0].parent == paper
    OmegaConf.save({"experiments": {"coverings": {"id": pinned["cache"].name.split("-")[-1],
                                                  "folder": pinned["cache"].name}}}, paper / "paper.lock.yaml")
    before, entry = fig.read_bytes(), (paper / "index" / "coverings.json").read_text()

    side = run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "experiment.grid_step=0.5",
                    "publish=auto"))
    assert side["cache"] != pinned["cache"]
    assert fig.read_bytes() == before and (paper / "index" / "coverings.json").read_text() == entry
    side_dir = tmp_path / "out" / "side" / side["cache"].name
    assert (side_dir / "fig3_coverings.png").is_file() and all(f.parent == side_dir for f in side["files"])
    assert json.loads((side_dir / "index" / "coverings.json").read_text())["cache"].endswith(side["cache"].name)

    again = run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "publish=auto"))  # the pinned computation: the paper
    assert again["cached"] and again["files"][0].parent == paper
    run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "experiment.grid_step=0.5", "publish=true"))
    assert fig.read_bytes() != before
    assert run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "publish=false"))["files"][0].parent == \
        tmp_path / "out" / "side" / pinned["cache"].name
    with pytest.raises(ConfigError, match="publish"):
        run(_cfg(tmp_path, "experiment=coverings", "debug=tiny", "publish=maybe"))


def test_experiments_side_by_side_never_read_a_half_written_entry(tmp_path):
    """`make paper` runs experiments two at a time, each writing its index entry and reading every other one to
    rewrite index.md (a tiny run failed on an empty entry, 2026-12-04): each file is written whole."""
    import threading

    from pipeline.experiments.report import publish

    errors = []

    def job(i: int) -> None:
        entry = {"id": f"exp{i}", "title": "t", "command": "c",
                 "items": [{"kind": "table", "files": [f"{'x' * 20_000}{i}.csv"], "caption": "c"}]}
        try:
            for _ in range(200):
                publish(tmp_path, entry, figures={})
        except Exception as err:  # noqa: BLE001 - what the other job's reader met
            errors.append(err)

    threads = [threading.Thread(target=job, args=(i,)) for i in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors, errors[0]
    index = (tmp_path / "index.md").read_text()
    assert all(f"## exp{i}" in index for i in range(3))
    assert sorted(p.name for p in (tmp_path / "index").iterdir()) == ["exp0.json", "exp1.json", "exp2.json"]


@settings(max_examples=30, deadline=None)
@given(values=st.lists(st.floats(-1e6, 1e6, allow_nan=False), min_size=1, max_size=50))
def test_cached_results_load_bit_for_bit(tmp_path_factory, values):
    """A scenario's cached tables load as the floats it saved: a paper whose results come from the cache publishes
    the numbers of one that computed them (pandas' default CSV parser is off by an ulp: a tiny `make paper` that
    reused its experiments, 2026-12-04, published x0 = 13.148321982859612 for 13.148321982859613)."""
    from pipeline.experiments.results import Results

    folder = tmp_path_factory.mktemp("results")
    Results(tables={"metrics": pd.DataFrame({"x": values})}).save(folder)
    loaded = Results.load(folder).tables["metrics"]["x"].to_numpy()
    assert loaded.tolist() == values


def test_a_failed_atomic_write_leaves_the_file_as_it_was(tmp_path):
    from pipeline.repo import write_atomic

    target = write_atomic(tmp_path / "index.md", "before")
    with pytest.raises(TypeError):
        write_atomic(target, None)  # the write itself fails
    assert target.read_text() == "before" and [p.name for p in tmp_path.iterdir()] == ["index.md"]


def test_a_node_read_but_not_in_the_cache_key_is_an_error(tmp_path, monkeypatch):
    """Issue 47: the experiments' cache keys come from each scenario's `uses()`; the stage checks that the
    computation read nothing else (a node read and not keyed would let a changed node reuse a stale result)."""
    from pipeline.experiments.paper.camera_loop import NoiseFailure
    from pipeline.experiments.stage import run

    def no_controllers(self):
        return {"controllers": [], "disturbances": [], "occlusions": []}

    monkeypatch.setattr(NoiseFailure, "uses", no_controllers)
    with pytest.raises(RuntimeError, match=r"read controllers\.hybrid.*uses\(\)"):
        run(_cfg(tmp_path, "experiment=noise_failure", "perception=oracle"))
    assert not list((tmp_path / "out" / "experiments").glob("noise_failure-*"))  # nothing stored under the key


def test_a_table_reads_the_same_fresh_and_from_the_cache(tmp_path):
    """A result's table is drawn from the computation (a fresh run) or from its cached CSV (every later run): both
    must print the same markdown (an empty note was '' fresh and NaN cached: the same table read two ways)."""
    from pipeline.experiments.report import markdown_table
    from pipeline.experiments.results import Results

    df = pd.DataFrame({"note": ["", "cell skipped: the starts meet the diamond"], "eps": [0.5, np.nan],
                       "valid": [True, False]})
    Results(tables={"t": df}).save(tmp_path)
    assert markdown_table(Results.load(tmp_path).tables["t"]) == markdown_table(df)
