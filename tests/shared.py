"""Helpers several test modules share. `computed_once`: a value the xdist workers of one `make test` compute once: the first worker to ask computes and pickles it under
the session's shared temporary folder (a file lock keeps the others waiting), the others read it. Without xdist
(`worker_id == "master"`) it is computed in place: there is no session folder shared with nobody else."""

from __future__ import annotations

import contextlib
import io
import pickle
import re
import runpy
import subprocess
import sys
import warnings
from pathlib import Path

from filelock import FileLock


def computed_once(tmp_path_factory, worker_id: str, name: str, make):
    if worker_id == "master":
        return make()
    path = tmp_path_factory.getbasetemp().parent / f"{name}.pkl"  # pytest-N/: this session's, shared by its workers
    with FileLock(str(path) + ".lock"):
        if path.is_file():
            return pickle.loads(path.read_bytes())
        value = make()
        path.write_bytes(pickle.dumps(value))
        return value


FIGURE_WRITERS = {"errormap": ("pipeline.errormap.writers", "figures"), "certify": ("pipeline.certify.stage", "write_figures")}


def without_figures(monkeypatch, stage: str) -> None:
    """`stage`'s run without its figures (matplotlib), for a test whose claim is its numbers, id or other files; each
    stage's figures are still drawn and checked by one test (the error map's: `test_stage_recovers_a_constant_bias...`
    and the pose map's; certify's: `test_certify_tiny_end_to_end`)."""
    import importlib

    module, name = FIGURE_WRITERS[stage]
    monkeypatch.setattr(importlib.import_module(module), name, lambda *args, **kwargs: [])


def index_links(index: Path) -> set[str]:
    """The targets of the markdown links of a paper folder's `index.md`."""
    return set(re.findall(r"\]\(([^)]+)\)", index.read_text()))


def run_cli(module: str, *args: str) -> subprocess.CompletedProcess:
    """`python -m <module> <args>` in this process (`runpy`, as `-m` runs it): its exit code, stdout and stderr, for
    checks that end before any work (a bad input: one line, exit 2). A fresh interpreter costs about a second of
    imports per case; what only a fresh process shows (what it imports, start-up warnings, signals) keeps
    `subprocess` (tests/test_first_hour.py, and one subprocess case per stage in tests/test_config_truth.py)."""
    out, err, argv, code = io.StringIO(), io.StringIO(), sys.argv, 0
    sys.argv = [module, *args]
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err), warnings.catch_warnings():
            # runpy's note that a module imported before runs again as `__main__` (what `-m` does in a fresh process)
            warnings.filterwarnings("ignore", "'pipeline.*' found in sys.modules", RuntimeWarning)
            runpy.run_module(module, run_name="__main__", alter_sys=True)
    except SystemExit as done:
        code = done.code if isinstance(done.code, int) else 0 if done.code is None else 1
    finally:
        sys.argv = argv
    return subprocess.CompletedProcess([module, *args], code, out.getvalue(), err.getvalue())
