"""A new user's first hour (issue 21): every bad input is one line (exit 2) before torch is imported, Ctrl-C is
one line (exit 130), run folders are named by stage, `outputs/paper/` is written only on purpose, `debug=tiny`
shrinks every stage consistently, long work shows its progress, a multirun ends with one table, the optional
loggers work out of the box."""

from __future__ import annotations

import io
import json
import os
import re
import subprocess
import sys
import types

import pytest
from shared import run_cli  # tests/shared.py

from pipeline.cli import CONF_DIR, REPO_ROOT, compose
from pipeline.errors import ConfigError

STAGES = ["pipeline.data", "pipeline.train", "pipeline.errormap", "pipeline.experiments", "pipeline.simulate",
          "pipeline.paper"]


def _env():
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["MPLBACKEND"] = "Agg"
    return env


def _cli(module, *args, timeout=300):
    return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO_ROOT, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _one_line_exit_2(proc, field: str):
    msg = f"rc {proc.returncode}\n{proc.stderr[-2000:]}"
    assert proc.returncode == 2, msg
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {field}"), msg
    assert "Traceback" not in proc.stderr + proc.stdout, msg


# ------------------------------------------------------------------------------ output paths (item 3)
@pytest.mark.parametrize("module", STAGES)
def test_output_paths_that_cannot_be_created_are_one_line_in_every_stage(tmp_path, module):
    """`/proc` takes no new folder (even for root, whom `os.access` lets through), a file in the way neither:
    the preflight tries a real mkdir before Hydra creates its run folder. The first case in a fresh interpreter,
    the other two through the same entry in this one (`run_cli`: a second of imports less each)."""
    afile = tmp_path / "a_file"
    afile.write_text("x")
    extra = {"pipeline.experiments": ["perception=oracle"], "pipeline.simulate": ["plot=false"]}.get(module, [])
    for i, (override, field) in enumerate(((f"paths.root_dir=/proc/x{os.getpid()}", "paths.root_dir"),
                                           (f"paths.datasets_dir=/proc/x{os.getpid()}", "paths.datasets_dir"),
                                           (f"paths.outputs_dir={afile}/sub", "paths.outputs_dir"))):
        root = [] if "root_dir" in override else [f"paths.root_dir={tmp_path / 'root'}"]
        _one_line_exit_2((_cli if i == 0 else run_cli)(module, override, *root, *extra), field)
    assert not (tmp_path / "root").exists() or not any((tmp_path / "root").rglob("*.yaml"))  # nothing started


def test_an_explicit_run_dir_that_cannot_be_created_is_one_line(tmp_path):
    _one_line_exit_2(run_cli("pipeline.simulate", f"paths.root_dir={tmp_path}", "hydra.run.dir=/proc/run_here"),
                     "hydra.run.dir")


def test_the_path_check_leaves_nothing_behind(tmp_path):
    from pipeline.repo import check_folder

    check_folder(tmp_path / "a" / "b" / "c", "paths.x")
    assert list(tmp_path.iterdir()) == []  # the folders it made to try are removed
    with pytest.raises(ConfigError, match="paths.x: cannot create"):
        check_folder("/proc/not_here/sub", "paths.x")


def test_path_checks_running_at_once_never_meet(tmp_path):
    """CI bug: two test workers checked the missing `data/datasets` at once; one made it, the other's mkdir or
    write-check met the folder the first was removing ('File exists' / 'No such file'), exit 2."""
    import threading

    from pipeline.repo import check_folder

    errors = []
    for k in range(20):
        target = tmp_path / f"r{k}" / "data" / "datasets"

        def check(target=target):
            try:
                check_folder(target, "paths.datasets_dir")
            except ConfigError as err:
                errors.append(err)

        threads = [threading.Thread(target=check) for _ in range(8)]
        for t in threads:
            t.start()
        for t in threads:
            t.join()
    assert errors == []
    assert sorted(p.name for p in tmp_path.iterdir()) == []  # and still nothing left behind


# -------------------------------------------------------------------- already fixed on main: their tests
def test_every_bench_module_imports_and_the_error_map_predictor_gives_positions():
    """`make bench` crashed: two areas' benchmarks imported modules the refactor had removed (errormap.core,
    sim.build), and the untrained map's predictor returned its variance outputs too."""
    import importlib

    import numpy as np

    from pipeline.bench import AREAS

    for area in AREAS:
        importlib.import_module(f"pipeline.{area}.bench")
    predict, camera, _ = importlib.import_module("pipeline.errormap.bench")._predictor()
    assert predict(camera.render(np.array([[0.0, 20.0], [-30.0, 5.0]]))).shape == (2, 2)


def test_bench_trains_the_default_map_with_its_uncertainty_head():
    """`make bench` crashed: the default map has four outputs (position + variance), the loss took them all."""
    from pipeline.config import build
    from pipeline.train.bench import _data, raw_loop
    from pipeline.train.module import PerceptionMap

    images, pos = _data(16)
    assert raw_loop(PerceptionMap(build(compose("train").model, "model")), images, pos, batch=8, steps=1) > 0


def test_every_bench_area_imports_and_its_maps_predict_positions():
    """`make bench` crashed after the refactors: `pipeline.errormap.bench` imported a module that had gone
    (`errormap.core`), `pipeline.experiments.bench` another (`sim.build`), and the error-map bench's untrained
    map returned four columns (position + variance) where positions were expected."""
    import importlib

    import numpy as np

    from pipeline.bench import AREAS
    from pipeline.errormap.bench import _predictor

    for area in AREAS:
        assert callable(importlib.import_module(f"pipeline.{area}.bench").bench), area
    predict, camera, _ = _predictor()
    assert predict(camera.render(np.array([[0.0, 10.0], [-20.0, 5.0], [30.0, -4.0]]))).shape == (3, 2)


@pytest.mark.parametrize("module,args,field", [
    ("pipeline.train", ["trainer.max_epochs=0"], "trainer.max_epochs"),
    ("pipeline.train", ["+trainer.max_epoch=3"], "trainer.max_epoch"),  # Lightning's keys, read from its source
    ("pipeline.train", ["model.position_head=grid"], "model.position_head"),  # the map's spec, imported
    ("pipeline.errormap", ["grid.step=-1"], "grid.step"),
    ("pipeline.experiments", ["experiment=robustness_sweep", "scale=-1"], "scale"),
    ("pipeline.data", ["data.seed=-1"], "data.seed"),
    ("pipeline.train", ["data=clean"], "dataset clean-"),  # a missing input, too
    ("pipeline.experiments", ["experiment=noise_failure"], "perception map 'clean_keypoint'"),  # a missing map
    ("pipeline.paper", ["debug=huge"], "debug"),
])
def test_config_errors_answer_before_torch_is_imported(tmp_path, module, args, field):
    code = ("import atexit, runpy, sys; atexit.register(lambda: print('torch imported' if 'torch' in sys.modules "
            f"else 'no torch', file=sys.stderr)); sys.argv = ['{module}', *{args!r}, 'paths.root_dir={tmp_path}']; "
            f"runpy.run_module('{module}', run_name='__main__')")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, env=_env(), capture_output=True, text=True,
                          timeout=300)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and lines[-1] == "no torch", proc.stderr[-2000:]
    assert len(lines) == 2 and lines[0].startswith(f"error: {field}"), proc.stderr


def test_ctrl_c_is_one_line_and_exit_130(tmp_path, monkeypatch, capsys):
    from pipeline.cli import stage_main

    fake = types.ModuleType("fake_interrupted_stage")

    def run(cfg):
        raise KeyboardInterrupt

    fake.run = run
    monkeypatch.setitem(sys.modules, "fake_interrupted_stage", fake)
    monkeypatch.setattr(sys, "argv", ["simulate", f"paths.root_dir={tmp_path}", f"hydra.run.dir={tmp_path / 'run'}"])
    with pytest.raises(SystemExit) as exit_:
        stage_main("simulate", run="fake_interrupted_stage:run")()
    assert exit_.value.code == 130
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "interrupted" in err[0], err


def test_ctrl_c_sent_to_a_stage_process_is_one_line_exit_130_and_leaves_no_folder(tmp_path):
    """A real SIGINT while the data stage writes its temporary folder: one line, exit 130, no dataset folder, no
    temporary one (a tqdm bar cut in its `__init__` printed an `Exception ignored` traceback after the line)."""
    import signal
    import time

    datasets = tmp_path / "data" / "datasets"
    proc = subprocess.Popen(
        [sys.executable, "-m", "pipeline.data", "data=clean", "debug=tiny", "data.sampling.mode=uniform",
         "data.splits.train=12000", f"paths.root_dir={tmp_path}"], cwd=REPO_ROOT, env=_env(), text=True,
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    def tmp_seen() -> bool:  # the preflight's mkdir probe may create and remove the folder meanwhile
        try:
            return any(d.name.startswith(".tmp-") for d in datasets.iterdir())
        except FileNotFoundError:
            return False

    deadline = time.monotonic() + 300
    while proc.poll() is None and time.monotonic() < deadline and not tmp_seen():
        time.sleep(0.005)
    assert proc.poll() is None, "the stage ended before its temporary folder was seen"
    proc.send_signal(signal.SIGINT)
    out, err = proc.communicate(timeout=300)
    msg = f"rc {proc.returncode}\n{err[-3000:]}"
    lines = [ln for ln in err.strip().splitlines() if " elapsed, " not in ln]  # but its progress lines
    assert proc.returncode == 130 and len(lines) == 1 and lines[0].startswith("interrupted"), msg
    assert "Traceback" not in err + out and "Exception ignored" not in err, msg
    assert list(datasets.iterdir()) == [], list(datasets.iterdir())


_LIGHTNING_CTRL_C = """
import os, signal, sys, types
signal.signal(signal.SIGINT, signal.default_int_handler)  # a terminal's interpreter (a background job inherits SIG_IGN)
import lightning as L
import torch
from pipeline.cli import stage_main
from pipeline.train.stage import _quiet_lightning

class Net(L.LightningModule):
    def __init__(self):
        super().__init__()
        self.w = torch.nn.Linear(1, 1)

    def training_step(self, batch, _):
        os.kill(os.getpid(), signal.SIGINT)  # Ctrl-C in the middle of an epoch
        return self.w(batch[0]).sum()

    def configure_optimizers(self):
        return torch.optim.SGD(self.parameters(), lr=0.1)

def run(cfg):
    _quiet_lightning()  # as the train stage does
    data = torch.utils.data.DataLoader(torch.utils.data.TensorDataset(torch.ones(4, 1)), batch_size=2)
    L.Trainer(max_epochs=3, accelerator="cpu", logger=False, enable_checkpointing=False,
              enable_progress_bar=False, enable_model_summary=False).fit(Net(), data)
    raise AssertionError("training went on after Ctrl-C")

fake = types.ModuleType("fake_lightning_stage")
fake.run = run
sys.modules["fake_lightning_stage"] = fake
before = signal.getsignal(signal.SIGINT)
try:
    stage_main("simulate", run="fake_lightning_stage:run")()
finally:
    assert signal.getsignal(signal.SIGINT) is before, "the stage's handler outlived it"
"""


def test_ctrl_c_during_lightning_training_is_one_line_and_exit_130(tmp_path):
    """Lightning catches Ctrl-C in `fit` and calls `sys.exit(1)` (its graceful shutdown): the stage exited 1,
    silently; it must be the same one line and exit 130 as anywhere else. In a fresh interpreter: the suite's
    own signal handlers (earlier tests) must not decide what a user's Ctrl-C does."""
    proc = subprocess.run([sys.executable, "-c", _LIGHTNING_CTRL_C, f"paths.root_dir={tmp_path}",
                           f"hydra.run.dir={tmp_path / 'run'}"], cwd=REPO_ROOT, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 130, proc.stderr[-3000:]
    assert proc.stderr.strip().splitlines() == ["interrupted (Ctrl-C): nothing half-written was kept"], proc.stderr


def test_ctrl_c_during_make_paper_is_the_stage_s_one_line_only(monkeypatch, capsys):
    """Ctrl-C reaches `make paper` and its running stage alike: the stage prints its line and exits 130; the
    orchestrator, interrupted while it waits, printed a second one."""
    import subprocess as sp

    from pipeline import paper

    def interrupted_wait(*args, **kwargs):
        raise KeyboardInterrupt

    monkeypatch.setattr(sp, "Popen", interrupted_wait)
    with pytest.raises(SystemExit) as exit_:
        paper.run_stage("data", ["data=clean"], {}, stop=True)
    assert exit_.value.code == 130
    assert "interrupted" not in capsys.readouterr().err


@pytest.mark.parametrize("where", ["_supports_unicode", "status_printer", "_get_free_pos"])
def test_a_progress_bar_cut_in_its_init_by_ctrl_c_leaves_no_traceback(monkeypatch, where):
    """Wherever the Ctrl-C lands in tqdm's `__init__` (before `disable` is set, after it but before
    `last_print_t`: seen under a loaded machine), the bar's `__del__` prints nothing."""
    import gc

    import tqdm.std

    from pipeline import progress as pr

    def interrupted(*_):
        raise KeyboardInterrupt

    caught = []
    monkeypatch.setattr(sys, "unraisablehook", caught.append)
    if where == "_supports_unicode":
        monkeypatch.setattr(tqdm.std, where, interrupted)  # called before `self.disable` is set
    else:
        monkeypatch.setattr(tqdm.std.tqdm, where, staticmethod(interrupted))  # after it, before `last_print_t`
    for file in (io.StringIO(), type("Tty", (io.StringIO,), {"isatty": lambda self: True})()):
        with pytest.raises(KeyboardInterrupt):
            pr.progress(total=3, desc="render", file=file)
        gc.collect()
    assert caught == [], [c.exc_value for c in caught]


@pytest.mark.parametrize("stage", ["data", "train", "errormap", "experiments", "simulate", "paper", "dagger"])
def test_run_folders_are_named_by_stage(stage):
    """Not `outputs/runs/__main__/` for every stage; an experiment's runs by experiment id."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir

    with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
        cfg = hydra_compose(stage, ["experiment=coverings"] if stage == "experiments" else [],
                            return_hydra_config=True)
    assert cfg.hydra.job.name == stage
    run_dir = cfg.hydra.run.dir
    assert f"/runs/{stage}/" in run_dir and f"/multirun/{stage}/" in cfg.hydra.sweep.dir
    if stage == "experiments":
        assert "/runs/experiments/coverings/" in run_dir


def test_a_follower_farther_than_the_arena_diagonal_is_rejected(tmp_path):
    from pipeline.data.plan import check

    with pytest.raises(ConfigError, match="data.follower.min_distance"):
        check(compose("data", ["data=leader_follower", "data.follower.min_distance=500", f"paths.root_dir={tmp_path}"]))
    check(compose("data", ["data=leader_follower", "data.follower.min_distance=100", f"paths.root_dir={tmp_path}"]))


def test_the_missing_map_hint_of_the_experiments_stage_is_a_valid_override(tmp_path):
    """The experiments stage's `maps` is a mapping: the hint must say `maps.clean=<name-id>` (`maps=<...>` crashed)."""
    side = tmp_path / "outputs" / "models" / "clean_keypoint-aaaaaaaaaa"
    side.mkdir(parents=True)
    (side / "manifest.json").write_text('{"id": "aaaaaaaaaa", "created": "1"}')
    proc = run_cli("pipeline.experiments", "experiment=noise_failure", f"paths.root_dir={tmp_path}")
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert "maps.clean=<name-id>" in proc.stderr and "maps=<" not in proc.stderr, proc.stderr


def test_a_missing_input_hint_names_a_command_only_where_a_config_makes_that_name(tmp_path):
    """`data.sampling.parent=dagger_r0-<id>` (not built) said "`python -m pipeline.data data=dagger_r0` makes the
    current config's", and an unknown name `mine` "run `python -m pipeline.data data=mine`": no such recipe."""
    from pipeline.errors import DatasetError
    from pipeline.lineage import resolve_dataset

    for ref in ("dagger_r0-0123456789", "mine"):
        with pytest.raises(DatasetError) as err:
            resolve_dataset(ref, tmp_path)
        assert "python -m" not in str(err.value), err.value
    with pytest.raises(DatasetError, match=r"`python -m pipeline.data data=clean` makes the current config's"):
        resolve_dataset("clean-0123456789", tmp_path)


def test_a_launcher_or_sweeper_whose_plugin_is_missing_is_one_line_naming_the_extra(tmp_path):
    """`hydra/launcher=joblib` without the `launchers` extra: Hydra's 9-line error and exit 1."""
    import importlib.util

    from pipeline.preflight import preflight

    if importlib.util.find_spec("hydra_plugins") is not None:
        pytest.skip("Hydra plugins installed: nothing is missing")
    for argv, field, extra in ((["-m", "hydra/launcher=joblib"], "hydra/launcher", "launchers"),
                               (["-m", "hparams_search=perception_optuna"], "hydra/sweeper", "search")):
        with pytest.raises(ConfigError) as err:
            preflight("train", [*argv, f"paths.root_dir={tmp_path}"])
        assert err.value.field == field and f"-e '.[{extra}]'" in err.value.reason, err.value
        assert "\n" not in str(err.value)


# --------------------------------------------------------------------------------- publishing (item 2)
def test_a_debug_run_before_any_paper_lock_writes_nothing_into_the_paper_folder(tmp_path):
    from pipeline.experiments.stage import run

    out = run(compose("experiments", ["experiment=coverings", "debug=tiny", f"paths.root_dir={tmp_path}"]))
    paper = tmp_path / "outputs" / "paper"
    assert not paper.exists() or not any(paper.iterdir())
    side = tmp_path / "outputs" / "side" / out["cache"].name
    assert {f.parent for f in out["files"]} == {side} and (side / "index.md").is_file()
    again = run(compose("experiments", ["experiment=coverings", "debug=tiny", f"paths.root_dir={tmp_path}",
                                        "publish=true"]))
    # on purpose only, and a smoke run's "paper" is its own (issue 32): outputs/debug/paper
    assert {f.parent for f in again["files"]} == {tmp_path / "outputs" / "debug" / "paper"}
    assert not paper.exists() or not any(paper.iterdir())


# ------------------------------------------------------------------------------- scenario keys (item 8)
def test_every_scenario_key_the_docs_override_is_declared_in_its_bundle():
    """`experiment.<key>=...` next to `experiment=<id>` in README/docs needs no `+`: the bundle declares the key."""
    import yaml

    texts = [(REPO_ROOT / "README.md").read_text(), *(p.read_text() for p in sorted((REPO_ROOT / "docs").glob("*.md")))]
    found = set()
    for text in texts:
        for line in text.splitlines():
            exp = re.search(r"experiment=(\w+)", line)
            if not exp or not (CONF_DIR / "experiment" / f"{exp.group(1)}.yaml").is_file():
                continue
            for key in re.findall(r"(?<![+\w.])experiment\.(\w+)=", line):
                found.add((exp.group(1), key))
    found.add(("robustness_sweep", "time_model"))  # issue 21: `experiment.time_model=sampled` needed a `+`
    for exp, key in sorted(found):
        bundle = yaml.safe_load((CONF_DIR / "experiment" / f"{exp}.yaml").read_text())["experiment"]
        assert key in bundle, f"{exp}: experiment.{key} is documented but not declared in conf/experiment/{exp}.yaml"
        compose("experiments", [f"experiment={exp}", f"experiment.{key}={_yaml_value(bundle[key])}"])


def _yaml_value(v) -> str:
    from pipeline.dagger import override_value

    return override_value(v)


# ------------------------------------------------------------------------------- make experiments (item 7)
def test_make_experiments_runs_the_experiments_make_paper_builds_inputs_for():
    """Right after `make paper`: no experiment whose map `make paper` does not build (perception_generalisation)."""
    import yaml

    from pipeline.preflight import _expand

    line = next(ln for ln in (REPO_ROOT / "Makefile").read_text().splitlines()
                if ln.strip().startswith("$(PY) -m pipeline.experiments"))
    override = re.search(r"'(experiment=[^']+)'", line).group(1)
    jobs = {job[0].split("=", 1)[1] for job in _expand([override])}
    paper = yaml.safe_load((CONF_DIR / "paper.yaml").read_text())
    assert jobs == set(paper["experiments"]), sorted(jobs ^ set(paper["experiments"]))


# ----------------------------------------------------------------------------------- debug=tiny (item 1)
def test_debug_tiny_shrinks_every_stage_and_each_finds_the_tiny_upstream_by_id():
    from pipeline import tracking
    from pipeline.identity import map_identity
    from pipeline.lineage import dataset_identity, expected_dataset_id, expected_map_id, train_dataset_id

    data = compose("data", ["data=occluded", "debug=tiny"])
    train = compose("train", ["data=occluded", "debug=tiny"])
    assert dict(data.data.splits) == dict(train.data.splits) and data.data.splits.train < 1000
    assert dataset_identity(data)[1] == dataset_identity(train)[1] == expected_dataset_id("occluded", ["debug=tiny"])
    assert dataset_identity(data)[1] != expected_dataset_id("occluded")
    assert train.trainer.max_epochs == 1 and compose("train").trainer.max_epochs > 1
    assert map_identity(tracking.to_plain_lenient(train), *train_dataset_id(train))[1] == expected_map_id("occluded", ["debug=tiny"]) != expected_map_id("occluded")
    em = compose("errormap", ["debug=tiny"])
    assert em.grid.step > compose("errormap").grid.step and em.train_samples < 1000
    exp = compose("experiments", ["experiment=hysteresis_margin", "debug=tiny"])
    assert exp.scale < 1 and exp.debug == "tiny" and len(exp.experiment.chi) < 5
    assert compose("paper", ["debug=tiny"]).debug == "tiny"


def test_a_name_resolves_to_the_map_of_the_same_debug_size(tmp_path):
    """In a `debug=tiny` run, `maps.clean=clean_keypoint` means the tiny map (and the hint says so)."""
    from pipeline.experiments.context import Context
    from pipeline.lineage import expected_map_id

    tiny = expected_map_id("clean_keypoint", ["debug=tiny"])
    folder = tmp_path / "outputs" / "models" / f"clean_keypoint-{tiny}"
    folder.mkdir(parents=True)
    (folder / "manifest.json").write_text(json.dumps({"id": tiny, "created": "1"}))
    ctx = Context(compose("experiments", ["experiment=noise_failure", "debug=tiny", f"paths.root_dir={tmp_path}"]))
    assert ctx.map_folder("clean") == folder
    big = Context(compose("experiments", ["experiment=noise_failure", f"paths.root_dir={tmp_path}"]))
    from pipeline.errors import ModelError

    with pytest.raises(ModelError, match="python -m pipeline.train data=clean model=keypoint"):
        big.map_folder("clean")
    with pytest.raises(ModelError, match="python -m pipeline.train data=occluded model=keypoint debug=tiny"):
        ctx.map_folder("occluded")


@pytest.mark.slow
def test_make_paper_debug_tiny_runs_every_stage_end_to_end(tmp_path):
    """`make paper ARGS=debug=tiny`: every stage, each finding the tiny upstream outputs by id, in minutes."""
    import yaml

    root = tmp_path / "root"
    proc = _cli("pipeline.paper", "debug=tiny", f"paths.root_dir={root}", timeout=1800)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    lock = yaml.safe_load((root / "outputs" / "debug" / "paper" / "paper.lock.yaml").read_text())
    assert lock["debug"] == "tiny" and not (root / "outputs" / "paper").exists()  # a smoke run: its own folder
    paper = yaml.safe_load((CONF_DIR / "paper.yaml").read_text())
    assert set(lock["datasets"]) == set(paper["datasets"]) and set(lock["maps"]) == set(paper["maps"])
    assert set(lock["experiments"]) == set(paper["experiments"])
    for name, entry in lock["datasets"].items():
        manifest = json.loads((root / "data" / "datasets" / entry["folder"] / "manifest.json").read_text())
        assert manifest["counts"]["train"] < 1000, name


# ------------------------------------------------------------------------------------ progress (item 4)
def test_progress_is_a_bar_on_a_terminal_and_lines_in_a_log(monkeypatch):
    from pipeline import progress as pr

    log = io.StringIO()
    with pr.progress(total=4, desc="sweep", unit="runs", file=log, interval=0) as bar:
        for i in range(4):
            bar.set_postfix_str(f"eps {i}")
            bar.update()
    lines = log.getvalue().splitlines()
    assert "\r" not in log.getvalue() and lines[0].startswith("sweep: 0/4 runs")
    assert lines[-1].startswith("sweep: 4/4 runs") and "eps 3" in lines[-1]
    quiet = io.StringIO()
    with pr.progress(total=4, desc="sweep", file=quiet) as bar:  # the default: a line every LINE_INTERVAL s
        bar.update(4)
    assert quiet.getvalue() == ""

    class Tty(io.StringIO):
        def isatty(self):
            return True

    tty = Tty()
    bar = pr.progress(total=4, desc="sweep", file=tty)
    assert not isinstance(bar, pr._LineBar) and bar.fp is not None
    bar.close()


def test_the_experiments_stage_reports_each_bisection_step(tmp_path, monkeypatch, capsys):
    from pipeline import progress as pr
    from pipeline.experiments.stage import run

    monkeypatch.setattr(pr, "LINE_INTERVAL", 0.0)
    monkeypatch.setattr(pr, "DELAY", 0.0)
    run(compose("experiments", ["experiment=hysteresis_margin", "debug=tiny", "perception=oracle",
                                f"paths.root_dir={tmp_path}"]))
    err = capsys.readouterr().err
    steps = re.findall(r"hysteresis_margin: (\d+)/(\d+) runs", err)
    assert steps and all(t == steps[-1][1] for _, t in steps[1:]), err[-2000:]
    assert int(steps[-1][0]) >= int(steps[-1][1]) - 1 and "chi=" in err


# -------------------------------------------------------------------------------- sweep summary (item 5)
def test_a_multirun_ends_with_one_table_of_overrides_and_headline_metrics(tmp_path):
    sweep = tmp_path / "sweep"
    proc = run_cli("pipeline.simulate", "-m", "controller=hybrid,smooth", "plot=false", "init=near_k", "init.n=4",
                   f"paths.root_dir={tmp_path}", f"hydra.sweep.dir={sweep}")
    assert proc.returncode == 0, proc.stderr[-2000:]
    import pandas as pd

    table = pd.read_csv(sweep / "summary.csv")
    assert list(table["job"]) == [0, 1] and list(table["status"]) == ["ok", "ok"]
    assert ["controller=hybrid" in o for o in table["overrides"]] == [True, False]
    assert {"success_rate", "collision_rate", "agents"} <= set(table.columns) and list(table["agents"]) == [4, 4]
    for job in (0, 1):
        entry = json.loads((sweep / str(job) / "summary.json").read_text())
        assert entry["metrics"]["success_rate"] == table["success_rate"][job]
    assert "| job | overrides |" in proc.stdout and (sweep / "summary.md").read_text() in proc.stdout


def test_each_stage_names_its_headline_metrics():
    import pandas as pd

    from pipeline import sweep

    assert sweep.data_headline({"name": "clean", "id": "x", "counts": {"train": 3, "val": 1, "test": 1},
                                "skipped": True}) == {"dataset": "clean-x", "n_train": 3, "n_val": 1, "n_test": 1,
                                                      "reused": True}
    assert sweep.train_headline({"name": "clean", "id": "x", "metrics": {
        "val_mae_px": 0.5, "test_split": {"mae_px": 0.6}, "heavy": {"mae_px": 2.0}, "epochs": 3}}) == \
        {"map": "clean-x", "val_mae_px": 0.5, "test_mae_px": 0.6, "mae_px[heavy]": 2.0}
    assert sweep.headline_of("pipeline.sweep:train_headline", 0.25) == {"objective": 0.25}  # an Optuna job
    summary = {"name": "clean", "levels": {"none": {"p95": 0.3}, "heavy": {"p95": 4.0}}}
    assert sweep.errormap_headline({"path": "/x/clean-1", "summary": summary}) == \
        {"errormap": "clean-1", "p95[none]": 0.3, "p95[heavy]": 4.0}
    res = types.SimpleNamespace(tables={"sweep": pd.DataFrame({"controller": ["hybrid", "smooth", "hybrid"],
                                                               "success_rate": [1.0, 0.0, 0.5]})})
    assert sweep.experiments_headline({"id": "robustness_sweep", "results": res, "cached": False}) == \
        {"experiment": "robustness_sweep", "cached": False, "success[hybrid]": 0.75, "success[smooth]": 0.0}
    for stage in ("data", "train", "errormap", "experiments", "simulate"):
        from hydra import compose as hydra_compose
        from hydra import initialize_config_dir
        from hydra.core.global_hydra import GlobalHydra

        GlobalHydra.instance().clear()
        with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
            cfg = hydra_compose(stage, return_hydra_config=True)
        assert cfg.hydra.callbacks.summary.headline == f"pipeline.sweep:{stage}_headline"


# ------------------------------------------------------------------------------------- loggers (item 6)
def test_mlflow_logs_into_a_local_store_without_setup(tmp_path):
    pytest.importorskip("mlflow")
    from pipeline.config import build

    cfg = compose("train", ["logger=mlflow", f"paths.root_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"])
    (tmp_path / "outputs").mkdir()
    logger = build(cfg.logger.mlflow, "logger.mlflow")
    logger.log_metrics({"val_mae": 1.5}, step=0)
    logger.finalize("success")
    import mlflow

    client = mlflow.MlflowClient(cfg.logger.mlflow.tracking_uri)
    runs = client.search_runs([client.get_experiment_by_name("perception_map").experiment_id])
    assert [r.data.metrics for r in runs] == [{"val_mae": 1.5}]
    assert (tmp_path / "outputs" / "mlflow.db").is_file() and not (REPO_ROOT / "mlruns").exists()


def test_tensorboard_writes_event_files_into_the_run_folder(tmp_path):
    pytest.importorskip("tensorboard")
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from pipeline.config import build

    cfg = compose("train", ["logger=tensorboard", f"paths.root_dir={tmp_path}", f"paths.output_dir={tmp_path / 'run'}"])
    logger = build(cfg.logger.tensorboard, "logger.tensorboard")
    logger.log_metrics({"val_mae": 1.5}, step=0)
    logger.finalize("success")
    acc = EventAccumulator(str(tmp_path / "run" / "tensorboard" / "version_0"))
    acc.Reload()
    assert [e.value for e in acc.Scalars("val_mae")] == [1.5]


_MONITOR_CTRL_C = """
import sys, threading, tqdm._monitor
def interrupted(self):  # the Ctrl-C lands after TMonitor registered its atexit exit, before the thread started
    if isinstance(self, tqdm._monitor.TMonitor):
        raise KeyboardInterrupt
    return start(self)
start = threading.Thread.start
threading.Thread.start = interrupted
from pipeline.progress import progress
try:
    with progress(total=3, desc="render", file=sys.stderr) as bar:
        bar.update()
except KeyboardInterrupt:
    print("interrupted", file=sys.stderr)
    sys.exit(130)
"""


def test_a_ctrl_c_while_tqdm_starts_its_monitor_thread_leaves_no_traceback_at_exit():
    """Seen in CI: a SIGINT between tqdm's `atexit.register(monitor.exit)` and `monitor.start()` printed
    `Exception ignored in atexit callback ... cannot join thread before it is started` after the one-line
    interruption. The project's bars start no monitor thread."""
    r = subprocess.run([sys.executable, "-c", _MONITOR_CTRL_C], cwd=REPO_ROOT, capture_output=True, text=True,
                       timeout=120)
    assert "Exception ignored" not in r.stderr and "Traceback" not in r.stderr, r.stderr
    assert r.stderr.strip().splitlines()[-1:] in (["interrupted"], []) and r.returncode in (0, 130), r.stderr
