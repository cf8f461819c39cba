"""Train stage (issue 4): tiny datasets, fast_dev_run, overfitting, reload, no-op, bad input."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest
from shared import run_cli  # tests/shared.py

from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError, DatasetError, ModelError

# the train configs name the same recipe as the dataset they train on (lineage: a recipe means its id)
SMALL = ["data.splits.train=512", "data.splits.val=64", "data.splits.test=64"]


@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    """A 512/64/64 clean dataset and a models folder, shared by the module's tests."""
    from pipeline.data.stage import run as data_run

    root = tmp_path_factory.mktemp("train")
    ds_dir, models_dir = root / "datasets", root / "models"
    cfg = compose("data", ["data=clean", *SMALL, f"paths.datasets_dir={ds_dir}"])
    out = data_run(cfg)
    return {"datasets": ds_dir, "models": models_dir, "root": root, "id": out["id"]}


def _train_cfg(tiny, *extra):
    return compose("train", [f"paths.datasets_dir={tiny['datasets']}", f"paths.models_dir={tiny['models']}",
                             "trainer.enable_progress_bar=false", *SMALL, *extra])


def test_fast_dev_run_reload_and_noop(tiny):
    from pipeline import identity, tracking
    from pipeline.data import open_dataset
    from pipeline.perception.maps import load_perception_map
    from pipeline.perception.metrics import error_metrics
    from pipeline.train.stage import run

    cfg = _train_cfg(tiny, "trainer=debug", "eval_levels=[none,heavy]")
    out = run(cfg)
    assert not out["skipped"]
    folder = tiny["models"] / f"{out['name']}-{out['id']}"
    manifest = json.loads((folder / "manifest.json").read_text())
    ds = open_dataset(tiny["id"], datasets_dir=tiny["datasets"])
    assert manifest["dataset_id"] == ds.id
    # the stage uses the pure rule
    assert identity.map_identity(tracking.to_plain_lenient(cfg), ds.name, ds.id) == (out["name"], out["id"])
    assert set(out["metrics"]) >= {"test_split", "none", "heavy"}

    # a saved map reloads and predicts the numbers the stage reported
    pm = load_perception_map(out["id"], models_dir=tiny["models"])
    pred = pm.predict(ds.images("test"))
    again = error_metrics(pred, ds.positions("test"), pm.px_per_unit)
    saved = json.loads((folder / "metrics.json").read_text())["test_split"]
    assert again["mae_px"] == pytest.approx(saved["mae_px"], rel=1e-6)
    assert np.array_equal(pred, pm.predict(ds.images("test")))  # inference is deterministic
    # the flag operating point: the gate is fitted on the validation positions re-rendered without clouds
    from pipeline.train.evaluate import gate_frames, render_split
    from pipeline.train.uncertainty import clean_gate

    metrics = json.loads((folder / "metrics.json").read_text())
    # the variance head is fitted after the position network, on every training image
    assert metrics["calibration"]["variance_head"]["images"] == len(ds.positions("train"))
    # and on gate_per_val fresh positions per validation image from the recipe's `gate` stream, with the bound
    ue = cfg.uncertainty_eval
    fresh, fresh_pos = gate_frames(ds, ue.gate_per_val * len(ds.positions("val")), 123)
    assert len(fresh_pos) == ue.gate_per_val * len(ds.positions("val")) > 0
    images = np.concatenate([render_split(ds, "val", None, 123).images, fresh.images])
    pred, sigma = pm.predict_with_sigma(images)
    good = np.hypot(*((pred - np.concatenate([ds.positions("val"), fresh_pos])) * pm.px_per_unit).T) <= ue.error_px
    assert 0 < good.sum()
    gate = clean_gate(sigma, pm.px_per_unit, ue.clean_false_alarm, good, confidence=ue.gate_confidence)
    assert metrics["calibration"]["clean_gate_px"] == pytest.approx(gate, rel=1e-5)
    fit = metrics["calibration"]["clean_gate"]
    assert (fit["frames"], fit["fresh_images"], fit["confidence"]) == (int(good.sum()), len(fresh_pos), ue.gate_confidence)
    assert fit["false_alarm"] <= fit["false_alarm_upper"]
    # the bound is within the target, unless even flagging nothing cannot certify it (this smoke run's few frames)
    assert fit["false_alarm_upper"] <= ue.clean_false_alarm or fit["false_alarm"] == 0
    assert metrics["heavy"]["uncertainty"]["at_clean_gate"]["gate_px"] == metrics["calibration"]["clean_gate_px"]
    # by name: the map the *default* train config makes (not built here), never the newest folder
    with pytest.raises(ModelError, match="current config makes") as err:
        load_perception_map(out["name"], models_dir=tiny["models"])
    assert f"{out['name']}-{out['id']}" in str(err.value)  # listed among the other builds
    assert load_perception_map(f"{out['name']}-{out['id']}", models_dir=tiny["models"]).id == out["id"]

    # second run: a no-op that touches nothing
    mtime = (folder / "model.pt").stat().st_mtime_ns
    again_out = run(cfg)
    assert again_out["skipped"] and again_out["id"] == out["id"]
    assert (folder / "model.pt").stat().st_mtime_ns == mtime
    # and a different seed is a different model (the stage's id is the pure rule's, checked above: not trained again)
    seed1 = tracking.to_plain_lenient(_train_cfg(tiny, "trainer=debug", "eval_levels=[none,heavy]", "seed=1"))
    assert identity.map_identity(seed1, ds.name, ds.id)[1] != out["id"]


def test_overfits_128_images(tiny):
    """The map can memorise 128 images: train MAE below 1 px (the model is able to localise sub-pixel)."""
    from pipeline.data import open_dataset
    from pipeline.perception.maps import load_perception_map
    from pipeline.perception.metrics import error_metrics
    from pipeline.train.stage import run

    # a narrow variant of the default architecture (CoordConv, one-cycle), without dropout and BatchNorm
    cfg = _train_cfg(tiny, "datamodule.limit_train_samples=128", "datamodule.batch_size=16", "trainer.max_epochs=40",
                     "trainer.max_time=null", "~callbacks.early_stopping", "model.lr=2e-3", "model.dropout=0.0", "model.filters=[8,16,32]",
                     "model.batch_norm=false", "eval_levels=[]", "name=overfit")
    out = run(cfg)
    pm = load_perception_map("overfit", models_dir=tiny["models"])
    ds = open_dataset(tiny["id"], datasets_dir=tiny["datasets"])
    m = error_metrics(pm.predict(ds.images("train")[:128]), ds.positions("train")[:128], pm.px_per_unit)
    assert m["mae_px"] < 1.0, m
    assert out["epochs"] >= 1


def test_wrong_image_shape_is_a_model_error(tiny):
    from pipeline.perception.maps import PerceptionMapPredictor
    from pipeline.train.module import PerceptionMap

    pm = PerceptionMapPredictor(PerceptionMap.of())
    assert pm.predict(np.zeros((3, 60, 100, 3), np.uint8)).shape == (3, 2)
    with pytest.raises(ModelError, match="image shape"):
        pm.predict(np.zeros((3, 64, 64, 3), np.uint8))


def test_bad_configs(tiny):
    from pipeline.train.stage import run

    with pytest.raises(DatasetError, match="unknown dataset"):
        run(_train_cfg(tiny, "dataset=nope", "trainer=debug"))
    with pytest.raises(ConfigError, match="trainer.max_epochs"):
        run(_train_cfg(tiny, "trainer.max_epochs=0"))
    with pytest.raises(ConfigError, match="eval_levels"):
        run(_train_cfg(tiny, "trainer=debug", "eval_levels=[fog]"))
    with pytest.raises(ModelError, match="image_shape"):
        run(_train_cfg(tiny, "trainer=debug", "+model.image_shape=[64,64,3]"))
    with pytest.raises(ModelError, match="unknown perception map"):
        from pipeline.perception.maps import load_perception_map

        load_perception_map("nope", models_dir=tiny["models"])


def test_damaged_dataset_is_rejected(tiny, tmp_path):
    """A dataset whose shard was altered fails verification before any training."""
    import shutil

    from pipeline.data import resolve_dataset
    from pipeline.train.stage import run

    src = resolve_dataset(tiny["id"], datasets_dir=tiny["datasets"])
    copy = tmp_path / "datasets" / src.name
    shutil.copytree(src, copy)
    shard = copy / "images_train.npy"
    data = bytearray(shard.read_bytes())
    data[-10] ^= 0xFF
    shard.write_bytes(bytes(data))
    cfg = compose("train", [f"paths.datasets_dir={tmp_path / 'datasets'}", f"paths.models_dir={tmp_path / 'm'}",
                            "trainer=debug", *SMALL])
    with pytest.raises(DatasetError, match="images_train.npy"):
        run(cfg)
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())


def test_cli_unknown_dataset_one_line(tmp_path):
    # refused by the preflight: the entry in this process (the stage's fresh-interpreter case is `+trainer.foo=1`
    # in test_cli_bad_input_one_line_exit_2)
    proc = run_cli("pipeline.train", "dataset=does_not_exist", f"paths.datasets_dir={tmp_path}",
                   f"paths.models_dir={tmp_path / 'm'}", f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode != 0
    assert "Traceback" not in proc.stderr
    err_lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(err_lines) == 1 and "does_not_exist" in err_lines[0]


# One line per bad input, naming the field, before any work (nothing written). `None` field part: the case
# needs no dataset to be rejected, so it also runs through the CLI below.
BAD_INPUTS = [
    (["+model.lrr=0.1"], "model.lrr"),
    (["+trainer.foo=1"], "trainer.foo"),
    (["+callbacks.early_stopping.patiense=3"], "callbacks.early_stopping.patiense"),
    (["model.lr=abc"], "model.lr"),
    (["model.lr=-0.001"], "model.lr"),
    (["model.weight_decay=-1"], "model.weight_decay"),
    (["model.hidden=-5"], "model.hidden"),
    (["model.filters=[16,0]"], "model.filters"),
    (["model.dropout=1.5"], "model.dropout"),
    (["seed=-1"], "seed"),
    (["seed=abc"], "seed"),
    (["datamodule.batch_size=100000"], "datamodule.batch_size"),  # larger than the 512-image split
    (["datamodule.batch_size=0"], "datamodule.batch_size"),
    (["datamodule.limit_train_samples=-3"], "datamodule.limit_train_samples"),
    (["datamodule.limit_val_samples=0"], "datamodule.limit_val_samples"),
    (["datamodule.limit_train_samples=8"], "datamodule.batch_size"),  # 8 samples < one batch of 32
    (["name=a/b"], "name"),
    (["model.name=a/b"], "model.name"),
    (["trainer.max_epochs=0"], "trainer.max_epochs"),
    (["device=tpu"], "device"),
    (["num_threads=0"], "num_threads"),
    (["uncertainty_eval.gate_per_val=-1"], "uncertainty_eval.gate_per_val"),
    (["uncertainty_eval.gate_per_val=1.5"], "uncertainty_eval.gate_per_val"),
    (["uncertainty_eval.gate_confidence=1.0"], "uncertainty_eval.gate_confidence"),
    (["uncertainty_eval.clean_false_alarm=1.5"], "uncertainty_eval.clean_false_alarm"),
]


@pytest.mark.parametrize(("overrides", "field"), BAD_INPUTS, ids=[" ".join(o) for o, _ in BAD_INPUTS])
def test_bad_input_is_one_config_error(tiny, tmp_path, overrides, field):
    from pipeline.train.stage import run

    with pytest.raises(ConfigError) as info:  # at composition (keys and types) or in the run, before any work
        cfg = compose("train", [f"paths.datasets_dir={tiny['datasets']}", f"paths.models_dir={tmp_path / 'm'}",
                                "trainer.max_epochs=1", "eval_levels=[]", *SMALL, *overrides])
        run(cfg)
    assert info.value.field == field
    assert "\n" not in str(info.value)
    assert not (tmp_path / "m").exists() or not any((tmp_path / "m").iterdir())


def test_gpu_trainer_without_gpu_is_one_config_error(tiny, tmp_path):
    import torch

    from pipeline.train.stage import run

    if torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    with pytest.raises(ConfigError, match="no CUDA GPU") as info:
        run(_train_cfg(tiny, "trainer=gpu"))
    assert info.value.field == "trainer.accelerator"


@pytest.mark.parametrize("override", ["+trainer.foo=1", "model.lr=abc", "trainer=gpu", "datamodule.batch_size=-4"])
def test_cli_bad_input_one_line_exit_2(request, tmp_path, override):
    import torch

    if override == "trainer=gpu" and torch.cuda.is_available():
        pytest.skip("this machine has a GPU")
    datasets, extra = tmp_path, []
    if override == "trainer=gpu":
        # the preflight imports no torch: a missing GPU (`check_devices`) is found in the job, after the preflight
        # has found the dataset, so this case needs one (the DataModule's values are its signature's, checked at
        # composition: `batch_size=-4` is rejected before the dataset is looked for)
        datasets, extra = request.getfixturevalue("tiny")["datasets"], SMALL
    args = [override, f"paths.datasets_dir={datasets}", *extra, f"paths.models_dir={tmp_path / 'm'}",
            f"hydra.run.dir={tmp_path / 'run'}"]
    if override in ("model.lr=abc", "datamodule.batch_size=-4"):  # refused by the preflight: the entry in this process
        proc = run_cli("pipeline.train", *args)
    else:  # a fresh interpreter (and the GPU case, refused in the job: Hydra's logging stays out of this process)
        proc = subprocess.run([sys.executable, "-m", "pipeline.train", *args], cwd=REPO_ROOT, capture_output=True,
                              text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr
    assert "Traceback" not in proc.stderr
    lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), proc.stderr
    field = override.lstrip("+").split("=")[0]
    assert (field if field != "trainer" else "trainer.accelerator") in lines[0]


def test_a_subclass_of_model_checkpoint_writes_into_the_runs_folder(tmp_path, monkeypatch):
    """The checkpoint callback is told by its class, not by its last name: a user's subclass of ModelCheckpoint
    (before: its name compared as a string) gets the run's `ckpt` folder, where the stage reads best and last."""
    from pipeline.train.stage import _trainer

    (tmp_path / "my_callbacks.py").write_text(
        "from lightning.pytorch.callbacks import ModelCheckpoint\n\n\nclass EveryEpoch(ModelCheckpoint):\n"
        "    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    cfg = compose("train", ["debug=tiny", "~logger", "callbacks.model_checkpoint._target_=my_callbacks.EveryEpoch",
                            f"paths.root_dir={tmp_path}", f"trainer.default_root_dir={tmp_path}"])
    _, ckpt = _trainer(cfg, tmp_path / "work")
    assert type(ckpt).__name__ == "EveryEpoch" and ckpt.dirpath == str(tmp_path / "work" / "ckpt")
