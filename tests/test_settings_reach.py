"""Every key reaches the code it configures (issue 27): a setting that is in the cache key but never used turns a
changed experiment into the same numbers under a new id.

- the `sim` and `camera` settings, walked from the composed config through `Context` to the keywords of the
  simulator and of the camera measurement (every field: a new field must be added here and reach its use);
- every key of every experiment bundle, walked to a use in its scenario's code (`self.<key>`; the drawing-only keys
  in its figures);
- the reproducer of the issue, end to end: `camera.p_fail` changes the numbers of `monte_carlo`, and a bundle whose
  runs are continuous-time (no camera frames to lose) rejects it in one line, exit 2.
"""

from __future__ import annotations

import dataclasses
import inspect
import subprocess
import sys
from types import SimpleNamespace

import numpy as np
import pytest
from hydra.utils import get_class

from pipeline.cli import CONF_DIR, REPO_ROOT, compose
from pipeline.config import resolve
from pipeline.errors import ConfigError
from pipeline.sim.settings import CameraSettings, SimSettings

BUNDLES = sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))

# a value off the default for every field of `sim` and `camera` (a field missing here fails the test)
SIM = {"model": "sampled", "dt": 0.02, "horizon": 7.0, "delta": 1.5, "record_every": 3, "stop_on_success": False,
       "seed": 11, "method": "dopri5", "rtol": 1e-5, "atol": 1e-3, "h_max": 0.2, "stall_speed": 0.3, "stall_share": 0.03,
       "stall_time": 4.0}
CAMERA = {"period": 0.04, "p_fail": 0.3, "gate": 1.25, "heading": "imu", "heading_noise": 0.05, "predict": True,
          "drift": 0.2, "max_drift": 3.0, "innovation": 2.5}
TO_SIMULATE = {"period", "p_fail", "predict", "drift", "max_drift", "innovation"}  # camera fields the simulator reads
TO_MEASURE = {"gate": "gate", "heading": "heading", "heading_noise": "heading_noise"}  # ...the camera measurement


def _ctx(tmp_path, *extra):
    from pipeline.experiments.context import Context

    cfg = compose("experiments", [f"paths.outputs_dir={tmp_path}", "perception=oracle", *extra,
                                  *(f"sim.{k}={v}" for k, v in SIM.items()),
                                  *(f"camera.{k}={v}" for k, v in CAMERA.items())])
    return Context(cfg)


def test_the_override_lists_cover_every_field():
    assert set(SIM) == {f.name for f in dataclasses.fields(SimSettings)}
    assert set(CAMERA) == {f.name for f in dataclasses.fields(CameraSettings)} == TO_SIMULATE | set(TO_MEASURE)
    for k, v in {**SIM, **CAMERA}.items():  # off the default: a value dropped for the default is seen
        default = getattr(SimSettings() if k in SIM else CameraSettings(), k)
        assert v != default or k == "model", k


def test_sim_and_camera_settings_reach_the_simulator_and_the_camera(tmp_path, monkeypatch):
    from pipeline.experiments import runs

    calls = []

    def simulate(scene, controller, x0, **kw):
        calls.append(kw)
        steps = 3
        return SimpleNamespace(t=np.arange(steps) * 0.1, p=np.zeros((steps, len(x0), 2)))

    monkeypatch.setattr(runs, "simulate", simulate)
    ctx = _ctx(tmp_path)
    x0 = np.array([[-12.0, 2.0], [-37.0, -17.0]])
    ctx.simulate(ctx.controller(), x0)
    ctx.leader_follower(x0[:1], x0[1:])
    plain, leader, follower = calls
    for k, v in SIM.items():  # the settings objects themselves, passed down
        assert getattr(plain["sim"], k) == v, f"sim.{k} does not reach the simulator: {getattr(plain['sim'], k)!r}"
    assert plain["seed"] == SIM["seed"]
    for k in TO_SIMULATE:
        assert getattr(plain["camera"], k) == CAMERA[k], f"camera.{k} does not reach the simulator"
    assert plain["sim"] is ctx.sim and plain["camera"] is ctx.camera_settings  # not rebuilt (nor re-checked) per run
    assert follower["camera"].p_fail == CAMERA["p_fail"], "camera.p_fail does not reach the follower's camera"
    assert leader["camera"].p_fail == 0.0  # the leader reads its own state: no camera to lose frames of
    assert not leader["sim"].stop_on_success and leader["sim"].horizon == SIM["horizon"]  # its own override only
    assert ctx.simulate(ctx.controller(), x0, p_fail=0.5) is not None and calls[-1]["camera"].p_fail == 0.5
    ctx.simulate(ctx.controller(), x0, innovation=False)  # the paper's loop beside a defended one: every frame used
    assert calls[-1]["camera"].innovation is None and calls[-1]["camera"].p_fail == CAMERA["p_fail"]

    seen = {}
    monkeypatch.setattr(runs, "CameraMeasure", lambda camera, pm, occ, **kw: seen.update(kw) or "measure")
    monkeypatch.setattr(ctx, "perception_map", lambda kind: object())  # a learned map (not the oracle)
    monkeypatch.setattr(ctx, "camera", lambda kind: None)
    assert ctx.camera_measure("clean") == "measure"
    for k, name in TO_MEASURE.items():
        assert seen[name] == CAMERA[k], f"camera.{k} does not reach the camera measurement: {seen[name]!r}"


def _reads(cls, key: str) -> bool:
    src = "".join(inspect.getsource(c) for c in cls.__mro__ if c.__module__.startswith("pipeline."))
    return f"self.{key}" in src


@pytest.mark.parametrize("bundle", BUNDLES)
def test_every_key_of_every_bundle_reaches_its_scenario(bundle):
    cfg = compose("experiments", [f"experiment={bundle}"])
    cls = get_class(cfg.experiment._target_)
    draw = inspect.getsource(sys.modules[resolve(cls.figures).__module__])
    for key in cfg.experiment:
        if key in ("_target_", "id"):
            continue
        if key in cls.DRAW_ONLY:
            assert f"scen.{key}" in draw or key in ("title", "paper"), f"{bundle}: experiment.{key} is never drawn"
            continue
        assert _reads(cls, key), f"{bundle}: experiment.{key} is read nowhere in {cls.__name__}"


def test_p_fail_changes_the_numbers(tmp_path):
    """The issue's reproducer: `experiment=monte_carlo camera.p_fail=0.3` computed the same numbers as 0.0."""
    from pipeline.experiments.stage import run

    def table(p_fail):
        cfg = compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                      "experiment=monte_carlo", "perception=oracle", "debug=tiny", "scale=0.05",
                                      "experiment.controllers=[hybrid]", "experiment.camera=false",
                                      "disturbances.gaussian.sigma=0.5", f"camera.p_fail={p_fail}"])
        s = run(cfg)["results"].tables["summary"].set_index("condition")
        return s.loc["none"]

    clean, lossy = table(0.0), table(0.9)
    assert (clean["median_time"], clean["mean_jumps"]) != (lossy["median_time"], lossy["mean_jumps"]), (clean, lossy)


def test_p_fail_rejected_where_it_does_not_apply(tmp_path):
    from pipeline.experiments.checks import check

    with pytest.raises(ConfigError, match=r"camera\.p_fail.*sample_and_hold"):
        check(compose("experiments", [f"paths.outputs_dir={tmp_path}", "experiment=sample_and_hold",
                                      "perception=oracle", "camera.p_fail=0.3"]))
    with pytest.raises(ConfigError, match=r"camera\.p_fail"):
        check(compose("experiments", [f"paths.outputs_dir={tmp_path}", "experiment=robustness_sweep",
                                      "perception=oracle", "camera.p_fail=0.3"]))
    proc = subprocess.run([sys.executable, "-m", "pipeline.experiments", "experiment=sample_and_hold",
                           "perception=oracle", "camera.p_fail=0.3", f"paths.outputs_dir={tmp_path}"],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
