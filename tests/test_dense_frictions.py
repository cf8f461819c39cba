"""Dense fields beyond the tuned scenes (issue 45): the frictions a new user met (starts on an arc, every start
violation listed, the controller preset in the run summary, fieldcheck's printed inflation, adding a preset to a
bundle from the command line)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys

import numpy as np
import pytest

from pipeline.config import build, compose
from pipeline.errors import ConfigError
from pipeline.repo import REPO_ROOT
from pipeline.sim.starts import SHOWN_STARTS, Circle


def _scene(name: str):
    return build(compose("simulate", [f"scene={name}"]).scene, "scene")


# ---- starts on an arc: `init=circle` takes `angles: [from, to]` (degrees, ends included); the default is unchanged
def test_circle_on_an_arc():
    cfg = compose("simulate", ["scene=case6", "init=circle", "init.n=5", "init.angles=[0,45]"])
    x0 = build(cfg.init, "init")(build(cfg.scene, "scene"))
    th = np.degrees(np.arctan2(x0[:, 1], x0[:, 0]))
    assert np.allclose(th, [0.0, 11.25, 22.5, 33.75, 45.0]) and np.allclose(np.hypot(*x0.T), 7.0)


def test_circle_default_is_the_full_circle():
    full = Circle(n=8, radius=7.0).on_circle([0.0, 0.0])
    assert np.allclose(np.degrees(np.arctan2(full[:, 1], full[:, 0])) % 360, np.arange(8) * 45.0)
    assert compose("simulate", ["init=circle"]).init.angles is None


@pytest.mark.parametrize(("angles", "why"), [("[45,0]", "min < max"), ("[0,400]", "360"), ("[10]", "2 numbers")])
def test_circle_bad_arc_is_one_line_naming_the_key(angles, why):
    with pytest.raises(ConfigError) as err:
        cfg = compose("simulate", ["scene=case6", "init=circle", f"init.angles={angles}"])
        build(cfg.init, "init")
    assert err.value.field == "init.angles" and why in err.value.reason and "\n" not in str(err.value)


# ---- every start violation, not the first alone: the first SHOWN_STARTS listed and all counted by kind
def test_start_rejection_lists_every_violation():
    scene = _scene("case6")   # discs r = 0.5 at (±4.5, 0), (0, ±4.5), apex 1: radius 5.1 hits four diamonds
    with pytest.raises(ConfigError) as err:
        Circle(n=8, radius=5.1)(scene)
    msg = err.value.reason
    assert "4 start-rule violation(s)" in msg and "4 inside a diamond" in msg and "\n" not in msg
    assert len(re.findall(r"start \d+ \(", msg)) == SHOWN_STARTS and "and 1 more" in msg
    with pytest.raises(ConfigError) as err:
        Circle(n=4, radius=4.5)(scene)   # every start at a disc's centre
    assert "4 inside an obstacle, 0 inside a diamond" in err.value.reason


# ---- the run summary names the controller preset (`hybrid_dense`), not the class's name alone
def test_simulate_summary_names_the_controller_preset(tmp_path):
    env = {**{k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}, "MPLBACKEND": "Agg"}
    proc = subprocess.run([sys.executable, "-m", "pipeline.simulate", f"hydra.run.dir={tmp_path}", "scene=case6",
                           "controller=hybrid_dense", "init=circle", "init.n=4", "sim.horizon=0.2", "plot=false"],
                          cwd=REPO_ROOT, env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert re.search(r"simulate \(.*\): hybrid_dense \(hybrid\) / none", proc.stdout + proc.stderr)


# ---- fieldcheck in unicycle mode prints the inflation it used, not d = 0.0
def test_fieldcheck_prints_the_inflation_used(capsys):
    from pipeline.fieldcheck import run
    out = run(compose("fieldcheck", ["scene=case6", "init=circle", "controller=hybrid_dense", "vehicle=unicycle",
                                     "vehicle.lookahead=0.1"]))
    text = capsys.readouterr().out
    assert "grown by vehicle.lookahead = 0.1" in text and "d = 0.1:" in text and "d = 0.0" not in text
    assert out["analysis"].inflation == pytest.approx(0.1)


# ---- adding a preset to a bundle from the command line: the documented syntax composes and reaches the experiment
def test_documented_preset_syntax_reaches_the_experiment():
    doc = (REPO_ROOT / "docs" / "dense.md").read_text()
    line = next(ln for ln in doc.splitlines()
                if ln.startswith("python -m pipeline.experiments") and "+scene@experiment.presets." in ln)
    argv = shlex.split(line.split("#")[0])[3:]
    key, name = re.search(r"\+scene@experiment\.presets\.(\w+)=(\w+)", line).groups()
    cfg = compose("experiments", argv)
    assert cfg.experiment.presets[key] == compose("simulate", [f"scene={name}"]).scene
    assert key in build(cfg.experiment, "experiment").presets
    with pytest.raises(ConfigError):   # the form the docs warn about
        compose("experiments", [a.replace("+scene@", "+/scene@") for a in argv])
