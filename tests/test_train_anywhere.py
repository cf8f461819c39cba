"""Train and infer anywhere (issue 10): model id rule, devices, folded inference, DDP sharding, loggers,
the Optuna objective, and (slow) DDP, submitit and Optuna sweeps through the CLI."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import torch

from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError

DEVICES = ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def _cfg(*extra):
    return compose("train", ["paths.output_dir=/nonexistent", *extra])


def model_identity(cfg, dataset_name, dataset_id):
    """The map id rule on a composed train config (what the train stage computes)."""
    from pipeline import identity, tracking

    return identity.map_identity(tracking.to_plain_lenient(cfg), dataset_name, dataset_id)


# ----------------------------------------------------------------------------------------- model id
def test_model_identity_placement_vs_weights():
    from pipeline.train.checks import check_settings

    base = model_identity(_cfg(), "clean", "abc")
    assert base == model_identity(_cfg(), "clean", "abc")  # pure and deterministic
    assert base[0] == "clean"
    # where it runs: same id
    for o in (["trainer=cpu"], ["trainer=ddp", "trainer.devices=2", "trainer.accelerator=cpu"], ["logger=none"],
              ["logger=tensorboard"], ["datamodule.num_workers=2"], ["datamodule.pin_memory=true"],
              ["trainer.enable_progress_bar=false"], ["device=cpu"], ["num_threads=1"], ["~callbacks.lr_monitor"]):
        assert model_identity(_cfg(*o), "clean", "abc") == base, o
    # what changes the weights: another id
    changed = set()
    for o in (["trainer.precision=bf16-mixed"], ["trainer.max_epochs=3"], ["datamodule.batch_size=64"],
              ["model.schedule=cosine"], ["seed=1"], ["callbacks.early_stopping.patience=2"],
              ["~callbacks.early_stopping"], ["+trainer.accumulate_grad_batches=2"], ["trainer.max_time=00:00:30:00"]):
        name, id_ = model_identity(_cfg(*o), "clean", "abc")
        assert name == "clean" and id_ != base[1], o
        changed.add(id_)
    assert len(changed) == 9
    assert model_identity(_cfg(), "clean", "xyz")[1] != base[1]  # another dataset
    assert model_identity(_cfg("model=paper"), "clean", "abc")[0] == "clean_paper"
    with pytest.raises(ConfigError, match="name"):  # the name is checked with the stage's settings (the id rule is pure)
        check_settings(_cfg("name=../x"))


def test_trainer_configs_compose_to_lightning_arguments():
    import inspect

    import lightning as L

    params = set(inspect.signature(L.Trainer).parameters)
    for option in ("default", "cpu", "gpu", "ddp", "debug", "paper"):
        cfg = _cfg(f"trainer={option}")
        assert cfg.trainer._target_ == "lightning.Trainer"
        assert set(cfg.trainer) - {"_target_"} <= params, option
    assert _cfg("trainer=paper").datamodule.batch_size == 128


# ------------------------------------------------------------------------------------------ devices
def test_resolve_device():
    from pipeline.perception.maps import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device("auto").type == ("cuda" if torch.cuda.is_available() else "cpu")
    for bad in ("tpu", "cuda:x", 3):
        with pytest.raises(ConfigError) as info:
            resolve_device(bad)
        assert info.value.field == "device"
    if not torch.cuda.is_available():
        with pytest.raises(ConfigError, match="no CUDA"):
            resolve_device("cuda")
    else:
        with pytest.raises(ConfigError):
            resolve_device(f"cuda:{torch.cuda.device_count()}")


def _random_map(**kw):
    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    model = PerceptionMap.of(**kw)
    for m in model.modules():  # non-trivial BatchNorm statistics, as after training
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
            m.weight.data.uniform_(0.5, 1.5)
            m.bias.data.uniform_(-0.1, 0.1)
    return model.eval()


@pytest.mark.parametrize("device", DEVICES)
@pytest.mark.parametrize("kw", [dict(filters=[8, 16, 32], batch_norm=True, coord_channels=True),
                                dict(filters=[8, 16], batch_norm=False, coord_channels=False, hidden=16),
                                dict(filters=[4, 8, 8], batch_norm=True, coord_channels=False, clamp=False)])
def test_folded_inference_matches_the_module_on_every_device(device, kw):
    """BatchNorm and input scaling folded into the convolutions, on CPU (and CUDA when present): the same
    world coordinates as the training module on CPU, up to float tolerance; batch size does not matter."""
    from pipeline.perception.maps import PerceptionMapPredictor

    model = _random_map(**kw)
    images = np.random.default_rng(1).integers(0, 256, (300, 60, 100, 3), dtype=np.uint8)
    with torch.inference_mode():
        ref = model(torch.from_numpy(images)).double().numpy()[:, :2]  # positions (a variance head adds columns)
    fast = PerceptionMapPredictor(model, device=device, batch_size=128)
    out = fast.predict(images)
    assert out.dtype == np.float64 and out.shape == (300, 2)
    assert fast.net.__class__.__name__ == "FoldedPerceptionNet"
    np.testing.assert_allclose(out, ref, atol=2e-3, rtol=0)  # world units: 1 px = 1 unit
    # batch size only changes float rounding (kernels differ per shape); tensors are accepted as well
    np.testing.assert_allclose(fast.predict(images[:7]), out[:7], atol=1e-4, rtol=0)
    np.testing.assert_allclose(fast.predict(torch.from_numpy(images[:5])), out[:5], atol=1e-4, rtol=0)
    np.testing.assert_array_equal(fast.predict(images), out)  # deterministic


def test_compile_falls_back_to_eager(monkeypatch):
    from pipeline.perception.maps import PerceptionMapPredictor

    def broken(*a, **k):
        raise RuntimeError("no compiler\nmore")

    monkeypatch.setattr(torch, "compile", broken)
    model = _random_map(filters=[4, 8])
    pm = PerceptionMapPredictor(model, compile=True)
    assert not pm.compiled
    images = np.zeros((3, 60, 100, 3), np.uint8)
    np.testing.assert_array_equal(pm.predict(images), PerceptionMapPredictor(model).predict(images))


# ------------------------------------------------------------------------------------- DDP sharding
def test_sharded_batches_partition_the_global_batches():
    from pipeline.train.datamodule import ShardedBatchSampler

    n, batch = 103, 12
    one = list(ShardedBatchSampler(n, batch, shuffle=True, seed=3))
    assert len(one) == n // batch and all(len(b) == batch for b in one)
    for world in (2, 3, 4):
        ranks = [list(ShardedBatchSampler(n, batch, shuffle=True, seed=3, rank=r, world=world))
                 for r in range(world)]
        assert all(len(r) == len(one) for r in ranks)
        for s, glob in enumerate(one):  # the same global batches, each sample on exactly one rank
            assert sorted(sum((r[s] for r in ranks), [])) == sorted(glob)
    # a new permutation per epoch, reproducible
    s = ShardedBatchSampler(n, batch, shuffle=True, seed=3)
    s.set_epoch(1)
    assert list(s) != one and list(s) == list(s)
    # evaluation: sequential, nothing dropped, no sample twice
    ev = [list(ShardedBatchSampler(n, 10, shuffle=False, rank=r, world=3)) for r in range(3)]
    assert sorted(i for r in ev for b in r for i in b) == list(range(n))
    with pytest.raises(ConfigError, match="divisible"):
        ShardedBatchSampler(n, 10, shuffle=True, world=3)


# ---------------------------------------------------------------------------------- loggers, search
@pytest.fixture(scope="module")
def tiny(tmp_path_factory):
    from pipeline.data.stage import run as data_run

    root = tmp_path_factory.mktemp("anywhere")
    cfg = compose("data", ["data=clean", *SMALL, f"paths.datasets_dir={root / 'datasets'}"])
    data_run(cfg)
    return root


# the train configs name the same recipe as the dataset they train on (lineage: a recipe means its id)
SMALL = ["data.splits.train=256", "data.splits.val=64", "data.splits.test=64"]


def _short(tiny, tmp_path, *extra):
    return compose("train", [f"paths.datasets_dir={tiny / 'datasets'}", f"paths.models_dir={tmp_path / 'm'}",
                             f"paths.output_dir={tmp_path / 'run'}", "trainer=cpu", "trainer.max_epochs=1",
                             "+trainer.limit_train_batches=2", "trainer.limit_val_batches=1",
                             "trainer.enable_progress_bar=false", "eval_levels=[]", *SMALL, *extra])


def test_tensorboard_logger_writes_events(tiny, tmp_path):
    pytest.importorskip("tensorboard")
    from pipeline.train.stage import objective, run

    out = run(_short(tiny, tmp_path, "logger=tensorboard").copy())
    assert list((tmp_path / "run" / "tensorboard").rglob("events.out.tfevents.*"))
    assert (tmp_path / "run" / "csv" / "version_0" / "metrics.csv").is_file()  # curves still from CSV
    val = objective(out, "val_mae_px")
    assert isinstance(val, float) and val == out["metrics"]["val_mae_px"] > 0
    assert objective(out, "test_split.mae_px") == out["metrics"]["test_split"]["mae_px"]
    with pytest.raises(ConfigError, match="optimized_metric"):
        objective(out, "val_acc")


def test_logger_none_and_missing_package(tiny, tmp_path, monkeypatch):
    import builtins

    from pipeline.train.stage import run

    assert not run(_short(tiny, tmp_path, "logger=none"))["skipped"]
    real_import = builtins.__import__

    def no_mlflow(name, *a, **k):
        if name == "mlflow" or name.startswith("mlflow."):
            raise ModuleNotFoundError("No module named 'mlflow'", name="mlflow")
        return real_import(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", no_mlflow)
    monkeypatch.setattr("lightning.pytorch.loggers.mlflow._MLFLOW_AVAILABLE", False, raising=False)
    with pytest.raises(ConfigError) as info:
        run(_short(tiny, tmp_path, "logger=mlflow", "seed=5"))
    assert info.value.field == "logger.mlflow" and "\n" not in str(info.value)


def _cli(tmp_path, tiny, *args, timeout=540):
    flags = [a for a in args if a.startswith("-")]
    return subprocess.run(
        [sys.executable, "-m", "pipeline.train", *flags, f"paths.datasets_dir={tiny / 'datasets'}",
         f"paths.models_dir={tmp_path / 'm'}", "eval_levels=[]", *SMALL, *(a for a in args if a not in flags)],
        cwd=REPO_ROOT, capture_output=True, text=True, timeout=timeout,
    )


@pytest.mark.slow
def test_ddp_two_cpu_processes(tiny, tmp_path):
    """`trainer=ddp trainer.devices=2 trainer.accelerator=cpu`: two ranks, one saved map, same id as one device."""
    import json

    args = ["trainer=ddp", "trainer.devices=2", "trainer.accelerator=cpu", "trainer.max_epochs=2",
            "datamodule.batch_size=32", "trainer.enable_progress_bar=false", f"hydra.run.dir={tmp_path / 'run'}"]
    proc = _cli(tmp_path, tiny, *args)
    assert proc.returncode == 0, proc.stderr[-3000:]
    folders = [p for p in (tmp_path / "m").iterdir() if not p.name.startswith(".")]
    assert len(folders) == 1
    metrics = json.loads((folders[0] / "metrics.json").read_text())
    assert metrics["world_size"] == 2 and metrics["epochs"] == 2
    from pipeline.data import open_dataset

    ds = open_dataset(folders[0].name and json.loads((folders[0] / "manifest.json").read_text())["dataset_id"],
                      datasets_dir=tiny / "datasets")
    cfg = compose("train", ["trainer=cpu", "trainer.max_epochs=2", "eval_levels=[]", "paths.output_dir=/x", *SMALL])
    assert folders[0].name == "-".join(model_identity(cfg, ds.name, ds.id))


@pytest.mark.slow
def test_submitit_local_two_job_sweep(tiny, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_submitit_launcher")
    proc = _cli(tmp_path, tiny, "-m", "hydra/launcher=submitit_local", "seed=0,1", "trainer=debug",
                f"hydra.sweep.dir={tmp_path / 'sweep'}", "hydra.launcher.timeout_min=10")
    assert proc.returncode == 0, proc.stderr[-3000:]
    folders = [p for p in (tmp_path / "m").iterdir() if not p.name.startswith(".")]
    assert len(folders) == 2


@pytest.mark.slow
def test_optuna_search_tiny_budget(tiny, tmp_path):
    pytest.importorskip("hydra_plugins.hydra_optuna_sweeper")
    proc = _cli(tmp_path, tiny, "-m", "hparams_search=perception_optuna", "hydra.sweeper.n_trials=2",
                "trainer=cpu", "trainer.max_epochs=1", "+trainer.limit_train_batches=2",
                "trainer.limit_val_batches=1", f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    best = (tmp_path / "sweep" / "optimization_results.yaml").read_text()
    assert "best_value" in best and "best_params" in best


def test_default_training_does_not_depend_on_the_clock():
    """Bug: a default wall-clock cap (max_time 12 min) ended the occluded map after 4 of 10 epochs on a busy
    machine: same config, same id, other weights. No trainer option of a default `make paper` caps time."""
    for option in ("default", "cpu", "paper"):
        cfg = compose("train", [f"trainer={option}", "paths.output_dir=/nonexistent"])
        assert cfg.trainer.get("max_time") is None, option


def test_the_epoch_validation_reads_the_first_limit_val_samples():
    """`limit_val_samples` caps the per-epoch validation at the split's first N images (the rest of the split is
    for calibration); the training and test splits are untouched."""
    from pipeline.train.datamodule import PerceptionDataModule
    from pipeline.train.settings import DataModuleSpec

    class Split:
        def __init__(self, n):
            self.sizes = {"train": n, "val": n, "test": n}

        def images(self, name):
            return np.zeros((self.sizes[name], 4, 4, 3), np.uint8)

        def positions(self, name):
            return np.arange(2 * self.sizes[name], dtype=np.float32).reshape(-1, 2)

    dm = PerceptionDataModule(DataModuleSpec(batch_size=8, limit_val_samples=30, eval_batch_size=16), Split(100))
    seen = np.concatenate([pos.numpy() for _, pos in dm.val_dataloader()])
    np.testing.assert_array_equal(seen, Split(100).positions("val")[:30])
    assert sum(len(pos) for _, pos in dm.test_dataloader()) == 100
    assert dm.train_size() == 100
