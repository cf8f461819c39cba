"""The example stage (pipeline/example_stage.py, conf/example_stage.yaml; docs/stages.md): a newcomer's stage is one
module and one conf file, and it gets what every stage gets: one-line errors before any work, an output named by
its id, a rerun that does nothing, a sweep with -m, nothing left by a failed write."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from pipeline.config import compose
from pipeline.repo import REPO_ROOT


def _stage(tmp_path, *args):
    return subprocess.run([sys.executable, "-m", "pipeline.example_stage", *args, f"paths.root_dir={tmp_path}"],
                          cwd=REPO_ROOT, capture_output=True, text=True, timeout=120)


def _folders(tmp_path):
    root = tmp_path / "outputs" / "example"
    return sorted(p.name for p in root.iterdir() if not p.name.startswith(".")) if root.is_dir() else []


def test_a_run_writes_its_output_by_id_and_a_rerun_does_nothing(tmp_path):
    first = _stage(tmp_path, "example.power=3")
    assert first.returncode == 0, first.stderr[-2000:]
    (name,) = _folders(tmp_path)
    result = json.loads((tmp_path / "outputs" / "example" / name / "result.json").read_text())
    assert result["powers"] == [1.0, 8.0, 27.0]
    again = _stage(tmp_path, "example.power=3")
    assert again.returncode == 0 and "up to date" in again.stdout
    other = _stage(tmp_path, "example.power=2")
    assert other.returncode == 0 and len(_folders(tmp_path)) == 2  # a changed value: a folder of its own


@pytest.mark.parametrize("override, key", [("example.power=9", "example.power"),
                                           ("example.values=[-1.0]", "example.values"),
                                           ("example.pwer=2", "example.pwer")])
def test_bad_input_is_one_line_naming_the_key_exit_2_before_any_work(tmp_path, override, key):
    proc = _stage(tmp_path, override)
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {key}"), proc.stderr
    assert _folders(tmp_path) == []


def test_a_sweep_runs_with_m_and_is_one_line_without_it(tmp_path):
    swept = _stage(tmp_path, "-m", "example.power=1,2")
    assert swept.returncode == 0 and len(_folders(tmp_path)) == 2, swept.stderr[-2000:]
    bare = _stage(tmp_path, "example.power=1,2")
    assert bare.returncode == 2 and "-m" in bare.stderr


def test_a_failed_write_leaves_nothing_under_the_final_name(tmp_path, monkeypatch):
    from pipeline import example_stage

    cfg = compose("example_stage", [f"paths.root_dir={tmp_path}", "paths.output_dir=" + str(tmp_path / "run")])

    def broken(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(example_stage.json, "dumps", broken)
    with pytest.raises(KeyboardInterrupt):
        example_stage.run(cfg)
    assert _folders(tmp_path) == []
    monkeypatch.undo()
    assert example_stage.run(cfg)["computed"] and len(_folders(tmp_path)) == 1
