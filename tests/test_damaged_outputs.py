"""Damaged tracked outputs (issue 32) and a file where an output's folder should be (issue 27): every tracked output
is checked against its manifest before a stage uses it; a damaged one is one line naming the file and the command
that rebuilds it, exit 2; `force=true` discards an unreadable resume checkpoint and retrains."""

from __future__ import annotations

import hashlib
import os
import shutil
from types import SimpleNamespace

import pytest
from shared import run_cli  # tests/shared.py

from pipeline import tracking
from pipeline.cli import compose
from pipeline.errors import DatasetError, PipelineError

SMALL = ["data=clean", "data.splits.train=128", "data.splits.val=32", "data.splits.test=32"]
TRAIN = ["trainer=debug", "eval_levels=[none]", "trainer.enable_progress_bar=false"]


@pytest.fixture(scope="module")
def built(tmp_path_factory):
    """A tiny clean dataset and a fast_dev_run map under one root (copied by each test that damages them)."""
    from pipeline.data.stage import run as data_run
    from pipeline.train.stage import run as train_run

    root = tmp_path_factory.mktemp("damaged")
    ds = data_run(compose("data", [*SMALL, f"paths.root_dir={root}"]))
    out = train_run(compose("train", [*SMALL, *TRAIN, f"paths.root_dir={root}"]))
    return root, f"{ds['name']}-{ds['id']}", f"{out['name']}-{out['id']}"


@pytest.fixture
def copy(built, tmp_path):
    root, ds, model = built
    shutil.copytree(root / "data", tmp_path / "data")
    shutil.copytree(root / "outputs" / "models", tmp_path / "outputs" / "models")
    return tmp_path, ds, model


def _one_line(proc, *needles):
    msg = f"rc {proc.returncode}\n{proc.stdout[-1500:]}\n{proc.stderr[-3000:]}"
    assert proc.returncode == 2, msg
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error: "), msg
    assert "Traceback" not in proc.stderr + proc.stdout, msg
    for needle in needles:
        assert needle in lines[0], msg
    return lines[0]


def _flip(path, at: float = 0.6, n: int = 64):
    """Same size, bytes flipped inside (a tensor's data for a torch zip)."""
    data = bytearray(path.read_bytes())
    i = int(len(data) * at)
    data[i:i + n] = bytes(b ^ 0xFF for b in data[i:i + n])
    stat = path.stat()
    path.write_bytes(bytes(data))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))  # even with its time kept: the hash says so
    assert path.stat().st_size == len(data)


# ------------------------------------------------------------------------------------ maps (the reproducers)
def test_a_truncated_map_is_one_line_naming_model_pt_and_the_command_that_rebuilds_it(copy):
    root, _, model = copy
    pt = root / "outputs" / "models" / model / "model.pt"
    pt.write_bytes(pt.read_bytes()[: pt.stat().st_size // 2])
    line = _one_line(run_cli("pipeline.errormap", f"maps={model}", "debug=tiny", "occlusion_levels=[none]",
                             f"paths.root_dir={root}"), str(pt), "size", "force=true")
    assert "python -m pipeline.train data=clean" in line


def test_a_map_corrupted_at_the_same_size_is_rejected_by_its_sha256_in_every_stage_that_reads_it(copy):
    from pipeline.errormap.stage import run as errormap_run
    from pipeline.perception.maps import load_perception_map
    from pipeline.train.stage import run as train_run

    root, _, model = copy
    pt = root / "outputs" / "models" / model / "model.pt"
    _flip(pt)
    with pytest.raises(PipelineError, match="sha256") as err:
        errormap_run(compose("errormap", [f"maps={model}", "debug=tiny", "occlusion_levels=[none]", "force=true",
                                          f"paths.root_dir={root}"]))
    assert str(pt) in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(PipelineError, match="sha256"):
        load_perception_map(model, models_dir=root / "outputs" / "models")
    with pytest.raises(DatasetError, match="sha256") as err:  # not "up to date"
        train_run(compose("train", [*SMALL, *TRAIN, f"paths.root_dir={root}"]))
    assert "force=true" in str(err.value) and "python -m pipeline.train" in str(err.value)


def test_a_damaged_dataset_is_one_line_before_training(copy):
    from pipeline.train.stage import run as train_run

    root, ds, _ = copy
    labels = root / "data" / "datasets" / ds / "labels.csv"
    _flip(labels, at=0.5, n=8)
    with pytest.raises(DatasetError, match="labels.csv") as err:
        train_run(compose("train", [*SMALL, *TRAIN, f"paths.root_dir={root}", "force=true"]))
    assert "python -m pipeline.data data=clean" in str(err.value) and "\n" not in str(err.value)


def test_a_damaged_error_map_and_experiment_result_are_one_line(tmp_path):
    from pipeline.experiments.stage import run as exp_run

    args = ["experiment=coverings", "debug=tiny", f"paths.root_dir={tmp_path}"]
    out = exp_run(compose("experiments", args))
    victim = next(p for p in sorted(out["cache"].iterdir()) if p.suffix == ".csv")
    _flip(victim, at=0.5, n=4)
    with pytest.raises(DatasetError, match="sha256") as err:
        exp_run(compose("experiments", args))
    assert str(victim) in str(err.value) and "experiment=coverings" in str(err.value)
    assert "force=true" in str(err.value)
    again = exp_run(compose("experiments", [*args, "force=true"]))  # the command the line names rebuilds it
    assert not again["cached"] and not tracking.verify(again["cache"])


def test_an_error_map_is_checked_against_its_manifest(tmp_path):
    from pipeline.lineage import resolve_errormap

    with tracking.tracked_output(tmp_path, "clean", "0123456789", {"kind": "errormap"}) as tmp:
        (tmp / "summary.json").write_text('{"eps": 1.0}')
    folder = tmp_path / "clean-0123456789"
    assert resolve_errormap("clean-0123456789", tmp_path) == folder
    (folder / "summary.json").write_text('{"eps": 9.0}')  # same size, altered
    with pytest.raises(DatasetError, match=r"summary.json: sha256 .*python -m pipeline.errormap maps=\[clean\]"):
        resolve_errormap("clean-0123456789", tmp_path)


# ------------------------------------------------------------------------------------ the resume checkpoint
def test_an_unreadable_resume_checkpoint_is_one_line_and_force_retrains_cleanly(copy):
    from pipeline.train.stage import run as train_run

    root, _, model = copy
    shutil.rmtree(root / "outputs" / "models" / model)
    resumable = [*SMALL, *TRAIN, f"paths.root_dir={root}", "trainer.fast_dev_run=false",
                 "trainer.limit_train_batches=1", "trainer.limit_val_batches=1"]
    out = train_run(compose("train", resumable))
    name_id = f"{out['name']}-{out['id']}"
    work = root / "outputs" / "models" / f".work-{name_id}" / "ckpt"
    best = (root / "outputs" / "models" / name_id / "best.ckpt").read_bytes()
    shutil.rmtree(root / "outputs" / "models" / name_id)

    def interrupted(last: bytes, digest: bytes | None = None):
        work.mkdir(parents=True, exist_ok=True)
        (work / "last.ckpt").write_bytes(last)
        if digest is not None:
            (work / "last.ckpt.sha256").write_text(hashlib.sha256(digest).hexdigest() + "\n")

    interrupted(best[:1000])  # an interrupted run's checkpoint, cut short
    with pytest.raises(PipelineError, match="resume checkpoint .* unreadable") as err:
        train_run(compose("train", resumable))
    assert str(work / "last.ckpt") in str(err.value) and "force=true" in str(err.value)
    assert "\n" not in str(err.value)
    flipped = bytearray(best)
    flipped[len(best) // 2] ^= 0xFF
    interrupted(bytes(flipped), digest=best)  # altered at the same size: torch would read it
    with pytest.raises(PipelineError, match="does not match its last.ckpt.sha256"):
        train_run(compose("train", resumable))
    again = train_run(compose("train", [*resumable, "force=true"]))  # discards it: a clean run
    assert not again["skipped"] and again["id"] == out["id"]
    assert not work.parent.exists() and not tracking.verify(root / "outputs" / "models" / name_id)


def test_every_checkpoint_the_train_stage_saves_gets_its_digest(tmp_path, monkeypatch):
    from lightning.pytorch.callbacks import ModelCheckpoint

    from pipeline.train.stage import _with_digests

    monkeypatch.setattr(ModelCheckpoint, "_save_checkpoint", lambda self, trainer, path: open(path, "wb").write(b"ck"))
    cb = ModelCheckpoint(dirpath=tmp_path)
    _with_digests(cb)
    cb._save_checkpoint(SimpleNamespace(is_global_zero=True), str(tmp_path / "last.ckpt"))
    assert (tmp_path / "last.ckpt.sha256").read_text().strip() == hashlib.sha256(b"ck").hexdigest()


# ------------------------------------------------------------------- a file where a folder should be (issue 27)
def test_a_file_where_the_dataset_folder_should_be_is_one_line_in_the_data_stage(tmp_path):
    from pipeline.lineage import dataset_identity

    name, id_, _, _ = dataset_identity(compose("data", ["data=clean", "debug=tiny", f"paths.root_dir={tmp_path}"]))
    blocker = tmp_path / "data" / "datasets" / f"{name}-{id_}"
    blocker.parent.mkdir(parents=True)
    blocker.write_text("not a folder")
    _one_line(run_cli("pipeline.data", "debug=tiny", f"paths.root_dir={tmp_path}"), str(blocker), "a file where")
    _one_line(run_cli("pipeline.data", "debug=tiny", "force=true", f"paths.root_dir={tmp_path}"), "a file where")
    assert blocker.read_text() == "not a folder"  # not ours to replace


def test_a_file_where_an_output_folder_should_be_is_one_line_in_every_stage(copy):
    from pipeline.errormap.stage import run as errormap_run
    from pipeline.experiments.stage import run as exp_run
    from pipeline.lineage import expected_errormap_id
    from pipeline.train.stage import run as train_run

    root, ds, model = copy
    models = root / "outputs" / "models"
    # train: its own output, then its input (the built map moved aside meanwhile: no retraining to get it back)
    shutil.move(models / model, root / "map-aside")
    (models / model).write_text("x")
    with pytest.raises(DatasetError, match="a file where"):
        train_run(compose("train", [*SMALL, *TRAIN, f"paths.root_dir={root}"]))
    (models / model).unlink()
    dsf = root / "data" / "datasets" / ds
    shutil.move(dsf, root / "ds-aside")
    dsf.write_text("x")
    with pytest.raises(DatasetError, match="a file where"):
        train_run(compose("train", [*SMALL, *TRAIN, f"paths.root_dir={root}"]))
    dsf.unlink()
    shutil.move(root / "ds-aside", dsf)
    # errormap: its input map, then its own output
    shutil.move(root / "map-aside", models / model)
    em = ["debug=tiny", "occlusion_levels=[none]", "train_samples=64", f"paths.root_dir={root}"]
    name, eid = expected_errormap_id(models / model, em)
    out = root / "outputs" / "errormaps" / f"{name}-{eid}"
    out.parent.mkdir(parents=True)
    out.write_text("x")
    with pytest.raises(DatasetError, match="a file where"):
        errormap_run(compose("errormap", [f"maps={model}", *em]))
    _one_line(run_cli("pipeline.errormap", f"maps={model}", *em), "a file where")
    # experiments: its cached results
    args = ["experiment=coverings", "debug=tiny", f"paths.root_dir={root}"]
    cache = exp_run(compose("experiments", args))["cache"]
    shutil.rmtree(cache)
    cache.write_text("x")
    with pytest.raises(DatasetError, match="a file where"):
        exp_run(compose("experiments", args))
