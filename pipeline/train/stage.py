"""The train stage: `python -m pipeline.train` — a tracked perception map per dataset.

Every object of the run is built from the composed config with `hydra.utils.instantiate`: the model
(`conf/model/`), the DataModule (`conf/datamodule/`), Lightning's Trainer (`conf/trainer/`, Lightning's own
arguments), the callbacks (`conf/callbacks/`) and the loggers (`conf/logger/`). The config is checked before any
work (:mod:`pipeline.train.checks`, in the preflight without torch; here the devices and the constructors).

Output: `outputs/models/<name>-<id>/` with `model.pt` (weights + hyper-parameters), `best.ckpt` (the Lightning
checkpoint of the best validation epoch), `metrics.json` (:mod:`pipeline.train.evaluate`), `curves.csv/png`,
`scatter.png`, `config.yaml` and `manifest.json`. The id (:func:`pipeline.identity.map_identity`) hashes what
changes the weights, not where the run happened, so an unchanged run is skipped (after its files are checked
against its manifest: a damaged map is one line). Interrupted runs resume from
`outputs/models/.work-<name>-<id>/ckpt/last.ckpt` (an unreadable one is one line; `force=true` discards it).
"""

from __future__ import annotations

import copy
import json
import logging
import shutil
import sys
import time
import warnings
from pathlib import Path

import lightning as L
import torch
from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
from lightning.pytorch.loggers import CSVLogger
from omegaconf import DictConfig, OmegaConf

from pipeline import identity, tracking
from pipeline.config import build, resolve
from pipeline.data import open_dataset
from pipeline.errors import ConfigError, ModelError, PipelineError
from pipeline.lineage import debug_overrides, rerun_command, resolve_dataset, train_dataset_id
from pipeline.perception.maps import PerceptionMapPredictor, resolve_device
from pipeline.profiling import phase, record
from pipeline.train.certified import CertifiedTerm
from pipeline.train.checks import check
from pipeline.train.datamodule import PerceptionDataModule
from pipeline.train.evaluate import evaluate, fit_clean_gate
from pipeline.train.figures import curves as plot_curves
from pipeline.train.figures import scatter
from pipeline.train.module import PerceptionMap
from pipeline.train.settings import UncertaintyEval
from pipeline.train.uncertainty import calibrate, fit_variance_head

log = logging.getLogger(__name__)


def _quiet_lightning() -> None:
    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "lightning_fabric"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    warnings.filterwarnings("ignore", ".*LeafSpec.*")
    warnings.filterwarnings("ignore", ".*treespec.*")
    warnings.filterwarnings("ignore", ".*pin_memory.*")
    warnings.filterwarnings("ignore", ".*smaller than the logging interval.*")


def _threads(cfg) -> int:
    if cfg.get("num_threads"):
        return int(cfg.num_threads)
    tc = cfg.trainer
    procs = 1
    if str(tc.get("accelerator", "auto")) == "cpu" and "ddp" in str(tc.get("strategy", "")):
        devices = tc.get("devices", 1)
        procs = devices if isinstance(devices, int) and devices > 0 else 1
    # torch's own default: every core, or OMP_NUM_THREADS where the launcher set it (make paper's jobs side by side)
    return max(1, torch.get_num_threads() // procs)


def _build(node, field: str, **kwargs):
    """`pipeline.config.build`, with Lightning's own errors (and a missing optional package) in one line."""
    try:
        return build(node, field, **kwargs)
    except PipelineError:
        raise
    except Exception as err:  # noqa: BLE001 - Lightning's MisconfigurationException, a missing package
        cause = err.__cause__ or err
        if isinstance(cause, ModuleNotFoundError | ImportError):
            raise ConfigError(field, f"needs an optional package ({cause}); e.g. "
                                     f".venv/bin/pip install -c constraints.txt -e '.[{field.split('.')[-1]}]'") from None
        raise ConfigError(field, _first_line(cause)) from None


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    msg = next((ln for ln in text if ln.strip() and not ln.startswith("Error in call to target")), "")
    return f"{type(err).__name__}: {msg}" if msg else type(err).__name__


def check_devices(cfg) -> None:
    """What only torch can say: a GPU accelerator or SyncBatchNorm without CUDA, an evaluation device not there."""
    accel = str(cfg.trainer.get("accelerator", "auto")).lower()
    if accel in ("gpu", "cuda") and not torch.cuda.is_available():
        raise ConfigError("trainer.accelerator", f"{accel!r} requested but no CUDA GPU is available on this "
                                                 "machine (use trainer=cpu or trainer=default)")
    if cfg.trainer.get("sync_batchnorm") and (accel == "cpu" or not torch.cuda.is_available()):
        raise ConfigError("trainer.sync_batchnorm", "SyncBatchNorm needs CUDA devices; set it false on CPU")
    resolve_device(cfg.get("device", "auto"))


def _run_dir(cfg: DictConfig, fallback: Path) -> DictConfig:
    """`paths.output_dir` is Hydra's run dir; outside `@hydra.main` (tests, the DAG) it is the work dir."""
    cfg = copy.deepcopy(cfg)
    try:
        OmegaConf.select(cfg, "paths.output_dir", throw_on_resolution_failure=True)
    except Exception:  # noqa: BLE001 - `${hydra:...}` without a Hydra app
        cfg.paths.output_dir = str(fallback)
    return cfg


def run(cfg) -> dict:
    """Train (or re-use) the map of a composed train config; returns `{id, name, path, skipped, metrics, ...}`."""
    t_start = time.perf_counter()
    s = check(cfg)  # one ConfigError before any work
    check_devices(cfg)
    ds, shape, arena = _dataset(cfg)
    name, id_ = identity.map_identity(tracking.to_plain_lenient(cfg), ds.name, ds.id)
    root = Path(cfg.paths.models_dir)
    final = root / f"{name}-{id_}"
    command = f"{rerun_command('train', [f'data={ds.name}'], cfg)} force=true"
    if tracking.exists(final, "perception map") and not cfg.get("force", False):
        tracking.check_intact(final, "perception map", command)
        print(f"[train] {final.name} is up to date ({final}); nothing to do (force=true retrains)")
        return {"id": id_, "name": name, "path": str(final), "skipped": True,
                "metrics": json.loads((final / "metrics.json").read_text())}

    dm = PerceptionDataModule(_build(cfg.datamodule, "datamodule", seed=s.seed), ds)  # batch vs split size
    work = root / f".work-{name}-{id_}"
    _resume_point(work, bool(cfg.get("force", False)), command)
    cfg = _run_dir(cfg, work)
    model = _model(cfg, s.seed, shape, arena, name, ds)
    dm.pose = model.pose
    trainer, ckpt_cb = _trainer(cfg, work)
    with phase("fit"):
        fit_s = _fit(cfg, trainer, model, dm, work, f"{name}-{id_}")
    if not trainer.is_global_zero:  # DDP: rank 0 evaluates the test split once and writes the map
        return {"id": id_, "name": name, "path": str(final), "skipped": False, "rank": trainer.global_rank}

    best_path = ckpt_cb.best_model_path
    with phase("uncertainty head"):
        model, predictor, variance_fit = _best_map(cfg, s.seed, model, best_path, ds)
    hparams = {k: v for k, v in tracking.to_plain_lenient(model.hparams).items() if k not in ("image_shape", "arena")}
    with phase("evaluate"):
        calibration, test_metrics, test_pred = _evaluate(cfg, s, model, predictor, ds, variance_fit)
    metrics = _metrics(cfg, trainer, ckpt_cb, ds, fit_s, calibration, test_metrics)
    meta = {"kind": "perception_map", "dataset_id": ds.id, "dataset_name": ds.name, "seed": s.seed,
            "model": hparams, "trainer": tracking.to_plain(cfg.trainer),
            "datamodule": tracking.to_plain(cfg.datamodule), "eval_levels": list(s.eval_levels),
            "scene": ds.manifest["scene"], "render": ds.manifest["render"],
            "image_shape": list(shape), "arena": arena,
            "code_version": tracking.code_version("train"), "metrics": metrics}
    csv_dir = next((Path(lg.log_dir) for lg in trainer.loggers if isinstance(lg, CSVLogger)), None)
    with tracking.tracked_output(root, name, id_, meta) as out:
        curves = _write_map(out, cfg, model, {**hparams, "image_shape": list(shape), "arena": arena}, best_path,
                            metrics, csv_dir)
        scatter(test_pred, ds.positions("test"), out / "scatter.png",
                f"{name}-{id_} on {ds.name}-{ds.id} test: MAE {metrics['test_split']['mae_px']:.3f} px")
    shutil.rmtree(work, ignore_errors=True)
    line = ", ".join(f"{k} {v['mae_px']:.3f}" for k, v in metrics.items() if isinstance(v, dict) and "mae_px" in v)
    if "heading" in metrics["test_split"]:  # a pose map: the heading error beside the position error
        line += f"; heading error mean {metrics['test_split']['heading']['mean_deg']:.2f} deg"
    print(f"[train] {name}-{id_}: test MAE px ({line}); {metrics['epochs']} epochs in {fit_s:.0f} s "
          f"-> {final} ({time.perf_counter() - t_start:.0f} s total)")
    record(f"train {name}")
    return {"id": id_, "name": name, "path": str(final), "skipped": False, "metrics": metrics,
            "epochs": len(curves)}


def _dataset(cfg):
    """The dataset this config's recipe renders (or `dataset`, pinned), its image shape and arena; the model's
    `image_shape`, where given, must match."""
    model_cfg = tracking.to_plain_lenient(cfg.model)
    ds_name, ds_id = train_dataset_id(cfg)
    folder = resolve_dataset(f"{ds_name}-{ds_id}", cfg.paths.datasets_dir, debug_overrides(cfg))  # hints: debug=
    ds = open_dataset(folder, datasets_dir=cfg.paths.datasets_dir, verify=bool(cfg.get("verify_dataset", True)))
    shape = tuple(int(s) for s in ds.images("train").shape[1:])
    want = model_cfg.get("image_shape")
    if want is not None and tuple(want) != shape:
        raise ModelError(f"model.image_shape {list(want)} does not match dataset {ds.name}-{ds.id} images {list(shape)}")
    return ds, shape, [list(a) for a in ds.camera().arena]


def _model(cfg, seed: int, shape, arena, name: str, ds):
    """Threads, quiet Lightning, the seed, then the network (a pose model needs a dataset with headings)."""
    torch.set_num_threads(_threads(cfg))
    _quiet_lightning()
    L.seed_everything(seed, workers=True, verbose=False)
    model = PerceptionMap(_build(cfg.model, "model", image_shape=list(shape), arena=arena, name=name))
    if model.pose and not ds.has_headings:
        raise ConfigError("model.outputs", f"pose: dataset {ds.name}-{ds.id} shows no heading (a recipe with "
                                           "data.vehicle: a unicycle)")
    if cfg.get("certified") is not None:  # certified training: the bound-based term (pipeline.train.certified)
        model.certified_term = CertifiedTerm(build(cfg.certified, "certified"), ds.camera())
    return model


def _trainer(cfg, work: Path):
    """Lightning's Trainer with the config's loggers and callbacks, and the checkpoint callback the stage needs
    (best and last, in `work/ckpt`): `(trainer, checkpoint callback)`."""
    loggers = [_build(node, f"logger.{key}") for key, node in (cfg.get("logger") or {}).items()]
    callbacks = []
    for key, node in (cfg.get("callbacks") or {}).items():
        extra = {"dirpath": str(work / "ckpt")} if _targets(node, ModelCheckpoint) else {}
        cb = _build(node, f"callbacks.{key}", **extra)
        if isinstance(cb, LearningRateMonitor) and not loggers:
            continue  # Lightning refuses a learning-rate monitor without a logger
        callbacks.append(cb)
    ckpt_cb = next((cb for cb in callbacks if isinstance(cb, ModelCheckpoint)), None)
    if ckpt_cb is None:  # the stage needs the best and last checkpoints (saved map, resume)
        ckpt_cb = ModelCheckpoint(dirpath=work / "ckpt", filename="best", monitor="val_mae", mode="min",
                                  save_top_k=1, save_last=True)
        callbacks.append(ckpt_cb)
    _with_digests(ckpt_cb)
    # Lightning's bar on a terminal; one line per epoch in logs (a bar written to a file floods it)
    show_bar = bool(cfg.trainer.get("enable_progress_bar", True)) and sys.stderr.isatty()
    work.mkdir(parents=True, exist_ok=True)
    trainer = _build(cfg.trainer, "trainer", logger=loggers or False, callbacks=callbacks,
                     enable_progress_bar=show_bar)
    return trainer, ckpt_cb


def _targets(node, cls: type) -> bool:
    """Whether the node's `_target_` is `cls` or a subclass (before: its last name compared as a string, so a user's
    subclass of ModelCheckpoint wrote its checkpoints outside the run's folder)."""
    try:
        target = resolve(":".join(str(node.get("_target_")).rsplit(".", 1)))
        return isinstance(target, type) and issubclass(target, cls)
    except Exception:  # noqa: BLE001 - a target that does not import: its build says so in one line
        return False


def _with_digests(cb: ModelCheckpoint) -> None:
    """Each checkpoint the callback writes gets `<file>.sha256` beside it: a resume can tell one altered at the same
    size, which torch loads without complaint (its zip reader checks no CRC)."""
    save = cb._save_checkpoint

    def saving(trainer, filepath):
        save(trainer, filepath)
        if trainer.is_global_zero and Path(filepath).is_file():
            Path(f"{filepath}.sha256").write_text(tracking.sha256_file(Path(filepath)) + "\n")

    cb._save_checkpoint = saving


def _resume_point(work: Path, force: bool, command: str) -> None:
    """An interrupted run's `work/ckpt/last.ckpt` is resumed from only when torch can read it: `force=true` discards
    the work folder (a clean retrain); an unreadable checkpoint without it is one line saying so."""
    last = work / "ckpt" / "last.ckpt"
    if force:
        shutil.rmtree(work, ignore_errors=True)
        return
    if not last.is_file():
        return
    digest = Path(f"{last}.sha256")
    if digest.is_file() and digest.read_text().strip() != tracking.sha256_file(last):
        raise ModelError(f"resume checkpoint {last} of an interrupted run does not match its {digest.name} (altered); "
                         f"`{command}` discards it and retrains")
    try:
        torch.load(last, map_location="cpu", weights_only=False)
    except Exception as err:  # noqa: BLE001 - a truncated zip, a flipped byte: torch's RuntimeError and friends
        raise ModelError(f"resume checkpoint {last} of an interrupted run is unreadable ({_first_line(err)}); "
                         f"`{command}` discards it and retrains") from None


def _fit(cfg, trainer, model, dm, work: Path, label: str) -> float:
    """`trainer.fit`, resumed from `work/ckpt/last.ckpt` when there is one; Lightning's late config errors as one
    ConfigError. Returns the seconds it took."""
    last = work / "ckpt" / "last.ckpt"
    resume = last if last.is_file() and not cfg.trainer.get("fast_dev_run") else None
    if resume and trainer.is_global_zero:
        print(f"[train] resuming {label} from {resume}")
    t_fit = time.perf_counter()
    try:
        trainer.fit(model, datamodule=dm, ckpt_path=str(resume) if resume else None)
    except PipelineError:
        raise
    except (ValueError, TypeError) as err:  # Lightning's late config errors (MisconfigurationException is one)
        if type(err).__module__.startswith(("lightning", "pytorch_lightning")):
            raise ConfigError("trainer", _first_line(err)) from None
        raise
    return time.perf_counter() - t_fit


def _best_map(cfg, seed: int, model, best_path, ds):
    """The best validation epoch's weights, the uncertainty head fitted on the trained network's own errors, and
    the map on the CPU with its predictor: `(model, predictor, variance head fit or None)`."""
    if best_path and Path(best_path).is_file():
        state = torch.load(best_path, map_location="cpu", weights_only=False)["state_dict"]
        model.load_state_dict(state)
    device = resolve_device(cfg.get("device", "auto"))
    variance_fit = None
    if model.var_head is not None:  # the uncertainty head learns the trained network's own errors
        variance_fit = fit_variance_head(model, ds.images("train"), ds.positions("train"), seed=seed, device=device)
    model = model.to("cpu").eval()
    predictor = PerceptionMapPredictor(model, manifest={"dataset_id": ds.id, "scene": ds.manifest["scene"],
                                                        "render": ds.manifest["render"]},
                                       device=device)
    return model, predictor, variance_fit


def _evaluate(cfg, s, model, predictor, ds, variance_fit):
    """With an uncertainty head, the sigma scale and the clean-image gate fitted on the validation split; then
    the test split and every evaluation level: `(calibration or None, test metrics, test predictions)`."""
    calibration = None
    ue = build(cfg.uncertainty_eval, "uncertainty_eval") if cfg.get("uncertainty_eval") is not None else UncertaintyEval()
    flags = {"error_px": ue.error_px, "gate_px": ue.gate_px}
    false_alarm, gate_per_val, confidence = ue.clean_false_alarm, ue.gate_per_val, ue.gate_confidence
    if predictor.has_uncertainty:  # fit the sigma scale and the clean-image gate on the validation split
        calibration = {"variance_head": variance_fit,
                       **calibrate(model, predictor, ds.images("val"), ds.positions("val"))}
        calibration["clean_false_alarm"] = false_alarm
        calibration["clean_gate"] = fit_clean_gate(predictor, ds, false_alarm, error_px=flags["error_px"],
                                                   per_val=gate_per_val, confidence=confidence,
                                                   seed=s.eval_seed)
        calibration["clean_gate_px"] = flags["clean_gate_px"] = calibration["clean_gate"]["gate_px"]
    test_metrics, test_pred = evaluate(predictor, ds, list(s.eval_levels), s.eval_seed, cfg.occlusions,
                                       uncertainty=flags)
    return calibration, test_metrics, test_pred


def _metrics(cfg, trainer, ckpt_cb, ds, fit_s: float, calibration, test_metrics) -> dict:
    """metrics.json: the run (epochs, speed, best validation MAE, device), the calibration, the test numbers."""
    best = ckpt_cb.best_model_score
    batch = int(cfg.datamodule.batch_size)
    return {"dataset": f"{ds.name}-{ds.id}", "epochs": int(trainer.current_epoch),
            "fit_seconds": round(fit_s, 1),
            "train_images_per_s": round(trainer.global_step * batch / max(fit_s, 1e-9), 1),
            "val_mae_px": float(best) if best is not None else None,
            "device": str(trainer.strategy.root_device), "world_size": int(trainer.world_size),
            **({"calibration": calibration} if calibration else {}), **test_metrics}


def _write_map(out: Path, cfg, model, hparams: dict, best_path, metrics: dict, csv_dir) -> list:
    """model.pt, best.ckpt, metrics.json, config.yaml and the training curves into `out`; returns the curves."""
    torch.save({"hparams": hparams, "state_dict": model.state_dict()}, out / "model.pt")
    if best_path and Path(best_path).is_file():
        shutil.copy2(best_path, out / "best.ckpt")
    (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
    (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=False))
    return plot_curves(csv_dir / "metrics.csv" if csv_dir else None, out)


def objective(out: dict, metric: str | None):
    """What a Hydra job returns: `out`, or the value of `metrics[metric]` for a sweeper (`optimized_metric`).

    `metric` may be a dotted path into metrics.json (`test_split.mae_px`). A DDP worker rank returns `out`."""
    if not metric or "metrics" not in out:
        return out
    value = out["metrics"]
    for part in str(metric).split("."):
        if not isinstance(value, dict) or part not in value:
            raise ConfigError("optimized_metric", f"{metric!r} is not a metric of the trained map; "
                                                  f"known: {', '.join(sorted(out['metrics']))}")
        value = value[part]
    return float(value)


def job(cfg):
    """What a Hydra job of the train stage returns: the run's result, or its `optimized_metric` for a sweeper."""
    return objective(run(cfg), cfg.get("optimized_metric"))
