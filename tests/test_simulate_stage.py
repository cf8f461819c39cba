"""End-to-end tests of the `simulate` stage: `pipeline.simulate.run(cfg)` and `python -m pipeline.simulate`."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
from shared import run_cli  # tests/shared.py

from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError
from pipeline.simulate import run

COLUMNS = ["controller", "x0", "y0", "success", "collision", "time_to_target", "min_clearance", "jumps",
           "path_length", "final_error", "termination", "outcome", "min_target_distance"]


def _compose(tmp_path, *overrides):
    return compose("simulate", [f"paths.output_dir={tmp_path}", *overrides])


def _check_outputs(run_dir, cfg):
    """metrics.csv has the documented columns and agrees with trajectories.npz; returns both."""
    df = pd.read_csv(run_dir / "metrics.csv")
    assert set(COLUMNS) <= set(df.columns), set(COLUMNS) - set(df.columns)
    assert df.columns[0] == "controller"
    npz = np.load(run_dir / "trajectories.npz")
    p, t, x0, j, q = npz["p"], npz["t"], npz["x0"], npz["j"], npz["q"]
    n = len(df)
    assert p.shape == (len(t), n, 2) and j.shape == q.shape == (len(t), n)
    assert t[0] == 0.0 and np.all(np.diff(t) > 0) and t[-1] <= cfg.sim.horizon + 1e-9
    np.testing.assert_allclose(df[["x0", "y0"]].to_numpy(), x0)
    np.testing.assert_allclose(p[0], x0)
    pT = np.asarray(cfg.scene.target, dtype=float)
    p0 = np.asarray(cfg.scene.obstacles[0].center, dtype=float)
    r = float(cfg.scene.obstacles[0].radius)
    # final error and jump count of the last recorded state (agents stop where they end)
    np.testing.assert_allclose(df.final_error, np.hypot(*(p[-1] - pT).T), rtol=1e-9, atol=1e-9)
    np.testing.assert_array_equal(df.jumps, j[-1])
    assert list(df.termination) == [str(s) for s in npz["termination"]]
    # success <=> reached delta without collision; time within the horizon
    delta = float(cfg.sim.delta)
    succ = df.success.to_numpy(bool)
    assert (df.final_error[succ] <= delta + 1e-9).all()
    assert (df.time_to_target[succ] <= cfg.sim.horizon + 1e-9).all()
    assert df.time_to_target[~succ & ~df.collision].isna().all()
    assert (df.termination[succ] == "target").all()
    # clearance: never above the recorded arcs' minimum distance to the obstacle
    rec_min = np.hypot(*(p - p0).transpose(2, 0, 1)).min(axis=0) - r
    assert (df.min_clearance <= rec_min + 1e-9).all()
    assert ((df.min_clearance < 0) == df.collision).all()
    # path length: at least the straight distance, at least the recorded polyline
    poly = np.hypot(*np.diff(p, axis=0).transpose(2, 0, 1)).sum(axis=0)
    slack = 1e-6 if cfg.sim.get("model", "sampled") == "sampled" else 1e-3 * poly  # continuous: a quadrature
    assert (df.path_length >= poly - slack).all()
    assert (df.path_length >= np.hypot(*(p[-1] - x0).T) - 1e-9).all()
    return df, npz


def test_run_grid_adversarial(tmp_path):
    cfg = _compose(tmp_path, "init=grid", "init.nx=9", "init.ny=5", "disturbance=adversarial",
                   "sim.horizon=30", "plot=false")
    out = run(cfg)
    assert out["run_dir"] == tmp_path
    df, npz = _check_outputs(tmp_path, cfg)
    pd.testing.assert_frame_equal(df, out["metrics"].reset_index(drop=True), check_dtype=False)
    assert (df.controller == "hybrid").all()
    assert len(df) >= 30 and df.success.all() and not df.collision.any()
    assert df.jumps.max() <= 20
    res = out["result"]
    np.testing.assert_allclose(res.p, npz["p"])
    assert not (tmp_path / "trajectories.png").exists()  # plot=false


def test_run_continuous_model(tmp_path):
    """`sim.model=continuous` through the stage: same outputs, arrivals on the delta-circle."""
    cfg = _compose(tmp_path, "sim.model=continuous", "init=grid", "init.nx=7", "init.ny=5",
                   "disturbance=alternating", "sim.horizon=30", "plot=false")
    out = run(cfg)
    df, npz = _check_outputs(tmp_path, cfg)
    assert df.success.all() and not df.collision.any() and (df.outcome == "reached").all()
    np.testing.assert_allclose(df.final_error, 1.0, atol=1e-6)
    assert out["result"].metrics["termination"].tolist() == ["target"] * len(df)
    # camera failures are sampled-only
    with pytest.raises(ConfigError) as info:
        run(_compose(tmp_path / "x", "sim.model=continuous", "camera.p_fail=0.5", "plot=false"))
    assert info.value.field == "sim.model"


def test_run_points_with_plot_and_camera_failures(tmp_path):
    cfg = _compose(tmp_path, "controller=smooth", "disturbance=gaussian", "camera.p_fail=0.5",
                   "sim.horizon=10", "sim.record_every=3", "init.points=[[-12.0,2.0],[-37.0,-17.0]]")
    out = run(cfg)
    df, npz = _check_outputs(tmp_path, cfg)
    assert (df.controller == "smooth").all() and len(df) == 2
    # record_every: 3 steps of 0.01 s between records (the final state aside)
    np.testing.assert_allclose(np.diff(npz["t"][:-1]), 0.03, atol=1e-9)
    png = tmp_path / "trajectories.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 10_000
    assert out["metrics"].shape[0] == 2


def test_run_near_k_contrasts_controllers(tmp_path):
    """Proposition 1 through the stage: smooth stalls near K under the adversary, hybrid does not."""
    rates = {}
    for ctrl in ("hybrid", "smooth", "cbf"):
        d = tmp_path / ctrl
        cfg = _compose(d, f"controller={ctrl}", "disturbance=adversarial", "init=near_k", "init.n=40",
                       "plot=false")
        run(cfg)
        df, _ = _check_outputs(d, cfg)
        rates[ctrl] = df.success.mean()
        assert not df.collision.any()
    assert rates["hybrid"] == 1.0 and rates["smooth"] <= 0.05 and rates["cbf"] <= 0.05


# ------------------------------------------------------------------------------------------ subprocess


def _env():
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["MPLBACKEND"] = "Agg"
    return env


def _stage(*args, timeout=120):
    return subprocess.run([sys.executable, "-m", "pipeline.simulate", *args], cwd=REPO_ROOT, env=_env(),
                          capture_output=True, text=True, timeout=timeout)


def test_cli_run_writes_outputs(tmp_path):
    # in this process (tests/shared.py): the outputs of a run, nothing only a fresh interpreter shows
    proc = run_cli("pipeline.simulate", f"hydra.run.dir={tmp_path}", "controller=cbf",
                   "disturbance=alternating", "sim.horizon=5", "plot=false")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    cfg = _compose(tmp_path, "controller=cbf", "disturbance=alternating", "sim.horizon=5")
    df, _ = _check_outputs(tmp_path, cfg)
    assert (df.controller == "cbf").all() and len(df) == 2
    assert "controller" in (tmp_path / ".hydra" / "config.yaml").read_text()


@pytest.mark.parametrize(
    ("override", "field"),
    [
        ("controller.chi=0.9", "controller.chi"),
        ("controller.lam=0.5", "controller.lam"),
        ("scene.obstacles.0.radius=-1", "scene.obstacles[0].radius"),
        ("scene.obstacles.0.apex=5.0", "scene.obstacles[0].apex"),
        ("scene.obstacle.radius=4", "scene.obstacle.radius: unknown key"),  # the old single-obstacle key
        ("sim.dt=0", "sim.dt"),
        ("scene.target=[5.0,0.0]", "scene.target"),
        ("camera.period=0.015", "camera.period"),
        ("sim.model=exact", "sim.model"),
        ("sim.stall_time=0", "sim.stall_time"),
        ("controller=foo", "controller: unknown option 'foo'"),
    ],
)
def test_cli_invalid_config(tmp_path, override, field):
    args = (override, f"hydra.run.dir={tmp_path}", "sim.horizon=1", "plot=false")
    # the first case in a fresh interpreter, the others through the same entry in this process (tests/shared.py)
    proc = _stage(*args) if override == "controller.chi=0.9" else run_cli("pipeline.simulate", *args)
    assert proc.returncode == 2
    assert field in proc.stderr, proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "Traceback" not in proc.stderr and "Traceback" not in proc.stdout
    assert not (tmp_path / "metrics.csv").exists()


def test_cli_multirun(tmp_path):
    sweep = tmp_path / "sweep"
    # in this process (tests/shared.py): a Hydra `-m` multirun runs its jobs in the launching process anyway
    proc = run_cli("pipeline.simulate", "-m", "controller=hybrid,smooth", "disturbance=adversarial",
                   f"hydra.sweep.dir={sweep}", "init=near_k", "init.n=20", "sim.horizon=20", "plot=false")
    assert proc.returncode == 0, proc.stderr
    assert "Traceback" not in proc.stderr
    csvs = sorted(sweep.glob("*/metrics.csv"))
    assert len(csvs) == 2
    frames = {pd.read_csv(c).controller.iloc[0]: pd.read_csv(c) for c in csvs}
    assert set(frames) == {"hybrid", "smooth"}
    assert all(len(df) == 20 for df in frames.values())
    assert frames["hybrid"].success.mean() > frames["smooth"].success.mean()
