"""The bracket stage end to end on a tiny configuration, and its bad inputs (one line naming the key)."""

from __future__ import annotations

import numpy as np
import pandas as pd
import pytest

from pipeline.config import compose
from pipeline.errors import ConfigError

TINY = ["bracket.cell=4.0", "bracket.start_cell=20", "bracket.eps=[0.1,0.25]", "bracket.n_bisect=0",
        "bracket.n_dirs=8", "bracket.tail=4", "bracket.lookahead=4", "bracket.commit=4", "sim.horizon=8"]


def test_tiny_bracket_run(tmp_path):
    from pipeline.bracket.stage import run

    cfg = compose("bracket", [*TINY, f"paths.outputs_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"])
    out = run(cfg)
    folder = out["path"]
    assert folder.parent == tmp_path / "bracket" and folder.name.startswith("bracket-") and not out["skipped"]
    df = pd.read_csv(folder / "bracket.csv")
    n = len(df) // 3
    assert list(df.controller.unique()) == ["hybrid", "smooth", "cbf"] and len(df) == 3 * n
    # soundness: no start cell certified at an ε the falsifier broke (the stage's own check, re-read from disk)
    assert not (df.eps_lo > df.eps_hi).any()
    assert (df.eps_lo.dropna().isin([0.1, 0.25])).all()
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
    other = run(compose("bracket", [*TINY, "bracket.eps=[0.1]", f"paths.outputs_dir={tmp_path}",
                                    f"paths.output_dir={tmp_path / 'run'}"]))
    assert other["path"] != folder and not other["skipped"]


@pytest.mark.parametrize("override,field", [
    ("bracket.commit=20", "bracket.commit"),
    ("bracket.eps=[0.5,0.1]", "bracket.eps"),
    ("bracket.cell=-1", "bracket.cell"),
    ("bracket.controllers=[hybrid,pid]", "bracket.controllers"),
    ("bracket.error_map=/nonexistent/map.csv", "bracket.error_map"),
    ("bracket.error_map=clean_keypoint-0000000000", "bracket.error_map"),  # a certify output by name-id, not built
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
    """The tracked output's folder taken by a file: one line naming it, exit 2 (issue 27's rule, in this stage)."""
    import shutil
    import subprocess
    import sys

    from pipeline.bracket.stage import run
    from pipeline.cli import REPO_ROOT

    args = [*TINY, "bracket.controllers=[cbf]", f"paths.outputs_dir={tmp_path}"]
    folder = run(compose("bracket", [*args, f"paths.output_dir={tmp_path / 'run'}"]))["path"]
    shutil.rmtree(folder)
    folder.write_text("x")
    proc = subprocess.run([sys.executable, "-m", "pipeline.bracket", *args, f"hydra.run.dir={tmp_path / 'cli'}"],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and "a file where" in lines[0] and str(folder) in lines[0], \
        proc.stderr[-2000:]


@pytest.mark.parametrize("arg, field", [("controller.saturation=tangent", "controller.saturation"),
                                        ("controller.noise_tolerance=0.3", "controller.noise_tolerance")])
def test_a_hybrid_rule_the_abstraction_does_not_model_is_rejected(arg, field):
    """The certificate's enclosures model §3.3's law; the dense design's rules (the tangent saturation, the side
    hysteresis) would let the real loop leave the abstraction: rejected in one line, exit 2, before any work."""
    import subprocess
    import sys

    from pipeline.cli import REPO_ROOT

    proc = subprocess.run([sys.executable, "-m", "pipeline.bracket", arg], cwd=REPO_ROOT, capture_output=True,
                          text=True, timeout=120)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}:"), proc.stderr[-2000:]
