"""The train stage: `python -m pipeline.train` — a tracked perception map per dataset.

Every object of the run is built from the composed config with `hydra.utils.instantiate`: the model
(`conf/model/`), the DataModule (`conf/datamodule/`), Lightning's Trainer (`conf/trainer/`, Lightning's own
arguments), the callbacks (`conf/callbacks/`) and the loggers (`conf/logger/`). The whole config is checked
before any work: an unknown or misspelled key, a value of the wrong type or range is one `ConfigError`.

Output: `outputs/models/<name>-<id>/` with `model.pt` (weights + hyper-parameters), `best.ckpt` (the
Lightning checkpoint of the best validation epoch), `metrics.json` (test MAE/RMSE in px on the dataset's
test split and re-rendered at each occlusion level, and the best validation MAE), `curves.csv/png`,
`scatter.png`, `config.yaml` and `manifest.json`. The id (`model_identity`) hashes what changes the weights
(model, batch, epochs, precision, schedule, early stopping, dataset id, seed, training code), not where the
run happened (accelerator, devices, strategy, logger, workers), so an unchanged run is skipped. Interrupted
runs resume from `outputs/models/.work-<name>-<id>/ckpt/last.ckpt`.
"""

from __future__ import annotations

import copy
import inspect
import json
import logging
import os
import shutil
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig, OmegaConf

from pipeline import tracking
from pipeline.errors import ConfigError, ModelError, PipelineError
from pipeline.train.metrics import (  # noqa: F401
    HIDDEN_ALPHA,
    NEAR_TARGET_RADIUS,
    error_metrics,
    perception_metrics,
)
from pipeline.train.uncertainty import calibrate, clean_gate, fit_variance_head, flag_metrics

log = logging.getLogger(__name__)

# Trainer arguments that say where/how visibly a run happens, not what it learns: left out of the model id.
PLACEMENT_KEYS = ("_target_", "accelerator", "strategy", "devices", "num_nodes", "enable_progress_bar",
                  "enable_model_summary", "log_every_n_steps", "default_root_dir", "num_sanity_val_steps",
                  "use_distributed_sampler", "sync_batchnorm", "profiler", "logger", "callbacks",
                  "enable_checkpointing", "benchmark", "barebones", "detect_anomaly", "inference_mode",
                  "plugins", "enable_autolog_hparams", "model_registry")
# DataModule arguments that change speed only.
DATAMODULE_SPEED_KEYS = ("_target_", "eval_batch_size", "num_workers", "pin_memory")
# flag rates: real error above error_px, flag above gate_px; and at the gate that flags clean_false_alarm of the
# clean images' good frames (the operating point of issue 11: detection at <= 10% false alarms on clean images),
# fitted on the validation positions and gate_per_val fresh positions per validation image, all without clouds,
# with a one-sided upper confidence bound at gate_confidence (0.5: the plain quantile)
UNCERTAINTY_EVAL = {"error_px": 3.0, "gate_px": 3.0, "clean_false_alarm": 0.1, "gate_per_val": 3,
                    "gate_confidence": 0.95}
# Callbacks that change the saved weights, and which of their arguments do.
_WEIGHT_CALLBACKS = {"ModelCheckpoint": ("monitor", "mode"), "EarlyStopping": None}  # None = all arguments
_GPU_ACCELERATORS = ("gpu", "cuda")


# ---------------------------------------------------------------------------------- config checks
def _plain(node):
    """Plain Python of a config node; a value whose interpolation cannot resolve here (`${hydra:...}`
    outside a Hydra app) is kept as its `${...}` text."""
    if node is None:
        return {}
    if isinstance(node, DictConfig):
        out = {}
        for key in node:
            try:
                out[key] = _plain(OmegaConf.select(node, str(key), throw_on_resolution_failure=True))
            except Exception:  # noqa: BLE001 - InterpolationResolutionError and friends
                out[key] = OmegaConf.to_container(node, resolve=False)[key]
        return out
    return tracking.to_plain(node)


def _target(node: dict, field: str):
    from hydra.utils import get_object

    target = node.get("_target_")
    if not target:
        raise ConfigError(field, "has no _target_ (the class it builds)")
    try:
        return get_object(target)
    except Exception as err:  # noqa: BLE001 - ImportError, AttributeError, missing optional package
        raise ConfigError(f"{field}._target_", f"cannot import {target!r} ({type(err).__name__}: "
                                               f"{str(err).splitlines()[0] if str(err) else ''})") from None


def check_keywords(node, field: str, *, exclude: tuple[str, ...] = ()) -> None:
    """Each key of an instantiable config node must be an argument of its `_target_` (no typo survives)."""
    node = _plain(node)
    obj = _target(node, field)
    kwargs = {k: v for k, v in node.items() if not k.startswith("_") and k not in exclude}
    try:
        sig = inspect.signature(obj)
    except (TypeError, ValueError):  # builtins without a signature: nothing to check
        return
    try:
        sig.bind_partial(**kwargs)
    except TypeError as err:
        bad = next((k for k in kwargs if k not in sig.parameters), None)
        known = ", ".join(p for p in sig.parameters if p not in ("self", "args", "kwargs"))
        where = f"{field}.{bad}" if bad else field
        raise ConfigError(where, f"unknown argument of {node['_target_']} ({err}); known: {known}") from None


def _int(cfg, key: str, lo: int) -> int | None:
    v = cfg.get(key)
    if v is None:
        return None
    if isinstance(v, bool) or not isinstance(v, int) or v < lo:
        raise ConfigError(key, f"must be an integer >= {lo}, got {v!r}")
    return v


def check_name(name, field: str = "name") -> str:
    if not isinstance(name, str) or not name or "/" in name or "\\" in name or name.startswith("."):
        raise ConfigError(field, f"must be a non-empty name without '/', '\\' or a leading '.', got {name!r}")
    return name


def check_config(cfg) -> None:
    """Everything that can be checked without the dataset: raises one `ConfigError` before any work."""
    from hydra.utils import instantiate

    from pipeline.render import occlusion_levels
    from pipeline.train.predict import resolve_device

    _int(cfg, "seed", 0)
    _int(cfg, "num_threads", 1)
    if cfg.get("name") is not None:
        check_name(cfg.name)
    levels = list(_plain(cfg.get("eval_levels")) or [])
    known_levels = occlusion_levels(cfg.occlusions)
    for lv in levels:
        if lv not in known_levels:
            raise ConfigError("eval_levels", f"unknown occlusion level {lv!r}; known: {', '.join(known_levels)}")
    resolve_device(cfg.get("device", "auto"))
    ue = _plain(cfg.get("uncertainty_eval"))
    if ue is not None:
        if not isinstance(ue, dict) or set(ue) != set(UNCERTAINTY_EVAL):
            raise ConfigError("uncertainty_eval", f"must have exactly the keys {', '.join(UNCERTAINTY_EVAL)}, got {ue!r}")
        for k in ("error_px", "gate_px", "clean_false_alarm"):
            v = ue[k]
            if isinstance(v, bool) or not isinstance(v, int | float) or not v > 0:
                raise ConfigError(f"uncertainty_eval.{k}", f"must be a number > 0, got {v!r}")
        if not ue["clean_false_alarm"] < 1:
            raise ConfigError("uncertainty_eval.clean_false_alarm", f"must be a share in (0, 1), got {ue['clean_false_alarm']!r}")
        g = ue["gate_per_val"]
        if isinstance(g, bool) or not isinstance(g, int) or g < 0:
            raise ConfigError("uncertainty_eval.gate_per_val", f"must be an integer >= 0, got {g!r}")
        c = ue["gate_confidence"]
        if isinstance(c, bool) or not isinstance(c, int | float) or not 0.5 <= c < 1:
            raise ConfigError("uncertainty_eval.gate_confidence", f"must be a confidence in [0.5, 1), got {c!r}")
    # model and datamodule: unknown keys, then a dry build with their own value checks
    check_keywords(cfg.model, "model")
    check_keywords(cfg.datamodule, "datamodule")
    _dry_build(lambda: instantiate(cfg.model, _convert_="all"), "model")
    _dry_build(lambda: instantiate(cfg.datamodule, dataset=None, seed=int(cfg.seed)), "datamodule")
    # trainer: Lightning's arguments; the common mistakes in one line before Lightning sees them
    check_keywords(cfg.trainer, "trainer", exclude=("logger", "callbacks"))
    tc = _plain(cfg.trainer)
    me = tc.get("max_epochs")
    if me is not None and (isinstance(me, bool) or not isinstance(me, int) or me <= 0):
        raise ConfigError("trainer.max_epochs", f"must be a positive integer, got {me!r}")
    accel = str(tc.get("accelerator", "auto")).lower()
    if accel in _GPU_ACCELERATORS and not torch.cuda.is_available():
        raise ConfigError("trainer.accelerator", f"{accel!r} requested but no CUDA GPU is available on this "
                                                 "machine (use trainer=cpu or trainer=default)")
    if tc.get("sync_batchnorm") and (accel == "cpu" or not torch.cuda.is_available()):
        raise ConfigError("trainer.sync_batchnorm", "SyncBatchNorm needs CUDA devices; set it false on CPU")
    for group in ("callbacks", "logger"):
        for key, node in (_plain(cfg.get(group)) or {}).items():
            if not isinstance(node, dict):
                raise ConfigError(f"{group}.{key}", f"must be a config with a _target_, got {node!r}")
            check_keywords(node, f"{group}.{key}", exclude=("dirpath",) if group == "callbacks" else ())


def _dry_build(build, field: str):
    from hydra.errors import InstantiationException

    try:
        return build()
    except InstantiationException as err:
        cause = err.__cause__
        if isinstance(cause, PipelineError):
            raise cause from None
        raise ConfigError(field, _first_line(cause or err)) from None


def _first_line(err: BaseException) -> str:
    text = str(err).strip().splitlines()
    msg = next((ln for ln in text if ln.strip() and not ln.startswith("Error in call to target")), "")
    return f"{type(err).__name__}: {msg}" if msg else type(err).__name__


# ------------------------------------------------------------------------------------------- the id
def model_name(dataset_name: str, model_cfg: dict, override: str | None) -> str:
    if override:
        return check_name(str(override))
    parts = [dataset_name]
    if model_cfg.get("name") not in (None, "default"):
        parts.append(str(model_cfg["name"]))
    return check_name("_".join(dict.fromkeys(parts)), "model.name")  # e.g. clean, clean_paper


def _weight_callbacks(callbacks: dict) -> dict:
    out = {}
    for key, node in sorted((callbacks or {}).items()):
        cls = str(node.get("_target_", "")).rsplit(".", 1)[-1]
        if cls in _WEIGHT_CALLBACKS:
            keep = _WEIGHT_CALLBACKS[cls]
            out[key] = {k: v for k, v in node.items() if k != "verbose" and (keep is None or k in keep or
                                                                          k == "_target_")}
    return out


def model_identity(cfg, dataset_name: str, dataset_id: str) -> tuple[str, str]:
    """(model folder name, id) of the map `cfg` (a composed train config) trains on dataset `dataset_id`.

    Pure: reads only the config (and hashes the training code). In the id: the model config (but its
    `name`), the DataModule's batch and sample limit, the Trainer arguments but `PLACEMENT_KEYS`, the
    callbacks that change the saved weights (checkpoint monitor, early stopping), the dataset id, the seed
    and the evaluation levels. Not in it: accelerator, devices, strategy, logger, workers, display.
    """
    model_cfg = _plain(cfg.model)
    name = model_name(dataset_name, model_cfg, cfg.get("name"))
    trainer = {k: v for k, v in _plain(cfg.trainer).items() if k not in PLACEMENT_KEYS}
    datamodule = {k: v for k, v in _plain(cfg.datamodule).items() if k not in DATAMODULE_SPEED_KEYS}
    id_ = tracking.content_id(
        {k: v for k, v in model_cfg.items() if k not in ("name", "image_shape")},
        trainer, datamodule, _weight_callbacks(_plain(cfg.get("callbacks"))),
        dataset_id, int(cfg.seed), list(_plain(cfg.get("eval_levels")) or []), tracking.code_version("train"),
        *([_plain(cfg.uncertainty_eval)] if cfg.get("uncertainty_eval") is not None else []),
    )
    return name, id_


def dataset_camera(ds):
    """The Camera that rendered a dataset (from its manifest)."""
    return ds.camera()


# ------------------------------------------------------------------------------------- evaluation
def evaluate(predictor, ds, levels, seed: int, occlusions=None, near_radius: float = NEAR_TARGET_RADIUS,
             hidden_alpha: float = HIDDEN_ALPHA, uncertainty: dict | None = None) -> tuple[dict, np.ndarray]:
    """Test metrics on the dataset's own test split and on its test positions re-rendered per level (each with
    the near-target and visible/hidden splits of `perception_metrics`, and for a map with an uncertainty head
    the coverage and flag rates of `flag_metrics` with `uncertainty = {error_px, gate_px[, clean_gate_px]}`); also returns the
    test predictions."""
    from pipeline.control import Scene
    from pipeline.render import load_occlusion

    out = {}
    images, pos = ds.images("test"), ds.positions("test")
    target = Scene.from_config(ds.manifest["scene"]).p_T
    split = dict(target=target, near_radius=near_radius, hidden_alpha=hidden_alpha)
    labels = ds.labels[ds.labels["split"] == "test"]
    alpha = labels["leader_alpha"].to_numpy(np.float64) if "leader_alpha" in labels else None
    flags = uncertainty or {}

    def metrics(imgs, leader_alpha):
        pred, sigma = predictor.predict_with_sigma(imgs)
        m = perception_metrics(pred, pos, predictor.px_per_unit, leader_alpha=leader_alpha, **split)
        if sigma is not None:
            m["uncertainty"] = flag_metrics(pred, sigma, pos, predictor.px_per_unit, **flags)
        return m, pred

    out["test_split"], test_pred = metrics(images, alpha)
    for level in levels:
        res = render_split(ds, "test", load_occlusion(level, occlusions, field="eval_levels"), seed)
        out[level] = metrics(res.images, res.leader_alpha)[0]
    return out, test_pred


def render_split(ds, split: str, occlusion, seed: int):
    """A split's positions (leader and follower) re-rendered by the dataset's camera under `occlusion`
    (None: no clouds), clouds drawn from `seed`; returns the camera's render result (images, leader_alpha)."""
    from pipeline.render import Occlusion

    labels = ds.labels[ds.labels["split"] == split]
    follower = labels[["follower_x", "follower_y"]].to_numpy(np.float64) if "follower_x" in labels else None
    return dataset_camera(ds).render(ds.positions(split), follower, occlusion=occlusion or Occlusion(),
                                     rng=np.random.default_rng(seed), return_info=True)


def gate_frames(ds, n: int, seed: int):
    """`n` fresh positions drawn from the dataset's own recipe on its `gate` stream (`pipeline.data.sampling.STREAMS`:
    no split holds them), leader and follower, rendered without clouds; returns (render result, leader positions)."""
    from pipeline.data.sampling import Recipe, plan_split
    from pipeline.render import Occlusion

    cam = dataset_camera(ds)
    plan = plan_split(Recipe.from_config(ds.recipe), "gate", cam, Occlusion(), n=n)
    res = cam.render(plan.leader.astype(np.float64), plan.follower.astype(np.float64), occlusion=Occlusion(),
                     rng=np.random.default_rng(seed), return_info=True)
    return res, plan.leader.astype(np.float64)


def fit_clean_gate(predictor, ds, false_alarm: float, *, error_px: float, per_val: int, confidence: float,
                   seed: int, chunk: int = 4096) -> dict:
    """The flag's operating point (`uncertainty.clean_gate`): the gate that flags `false_alarm` of the clean good
    frames (real error <= `error_px`), with an upper confidence bound at `confidence`, fitted on the validation
    positions and `per_val` fresh positions per validation image (`gate_frames`), all rendered without clouds.
    The gate is a tail quantile: fitted on the 8000 validation frames alone, its rate on new frames was 11.3% for a
    10% target; with the fresh frames and the bound, 9.93% (docs/train.md). Returns the gate and what it was
    fitted on."""
    from pipeline.train.uncertainty import false_alarm_upper_bound

    ppu = predictor.px_per_unit
    val_pos = ds.positions("val")
    pred, sigma = predictor.predict_with_sigma(render_split(ds, "val", None, seed).images)
    errs, sigmas = [np.hypot(*((pred - val_pos) * ppu).T)], [sigma]
    n_fresh = per_val * len(val_pos)
    if n_fresh:
        res, pos = gate_frames(ds, n_fresh, seed)
        for i in range(0, n_fresh, chunk):  # chunks: the float copies of a large set are never all held
            p, s_ = predictor.predict_with_sigma(res.images[i:i + chunk])
            errs.append(np.hypot(*((p - pos[i:i + chunk]) * ppu).T))
            sigmas.append(s_)
    err, sigma = np.concatenate(errs), np.concatenate(sigmas)
    good = err <= error_px
    if not good.any():  # no good frame (a smoke run): all frames
        good = np.ones(len(err), bool)
    gate = clean_gate(sigma, ppu, false_alarm, good, confidence=confidence)
    flagged = int((np.hypot(*(sigma[good] * ppu).T) > gate).sum())
    n = int(good.sum())
    upper = float(false_alarm_upper_bound(flagged, n, confidence))
    if upper > false_alarm:
        print(f"[train] warning: {n} clean frames cannot bound the false alarms at {false_alarm:g} with confidence "
              f"{confidence:g} (upper bound {upper:.3f} with no frame flagged); raise uncertainty_eval.gate_per_val")
    return {"gate_px": gate, "frames": n, "val_images": len(val_pos), "fresh_images": n_fresh,
            "confidence": confidence, "false_alarm": flagged / n,
            "false_alarm_upper": upper}


# ------------------------------------------------------------------------------------------ figures
def _curves(log_csv: Path | None, out: Path) -> pd.DataFrame:
    raw = pd.read_csv(log_csv) if log_csv is not None and log_csv.is_file() else pd.DataFrame()
    if raw.empty or "epoch" not in raw:
        curves = pd.DataFrame(columns=["epoch", "train_loss", "val_loss", "val_mae"])
    else:
        g = raw.groupby("epoch")
        curves = pd.DataFrame({"epoch": sorted(raw["epoch"].dropna().unique().astype(int))})
        for src, dst in (("train_loss_epoch", "train_loss"), ("train_mae", "train_mae_px"),
                         ("val_loss", "val_loss"), ("val_mae", "val_mae_px")):
            if src in raw:
                curves[dst] = g[src].last().reindex(curves["epoch"]).to_numpy()
    curves.to_csv(out / "curves.csv", index=False)
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.2))
    for col in ("train_loss", "val_loss"):
        if col in curves and curves[col].notna().any():
            ax[0].semilogy(curves["epoch"] + 1, curves[col], "o-", label=col)
    for col in ("train_mae_px", "val_mae_px"):
        if col in curves and curves[col].notna().any():
            ax[1].semilogy(curves["epoch"] + 1, curves[col], "o-", label=col)
    ax[0].set(xlabel="epoch", ylabel="loss (normalised MSE)")
    ax[1].set(xlabel="epoch", ylabel="MAE (px)")
    for a in ax:
        if a.get_legend_handles_labels()[0]:
            a.legend(fontsize=8)
        a.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(out / "curves.png", dpi=120)
    plt.close(fig)
    return curves


def _scatter(pred: np.ndarray, true: np.ndarray, path: Path, title: str) -> None:
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(1, 2, figsize=(9, 3.6))
    for k, lab in enumerate("xy"):
        ax[k].scatter(true[:, k], pred[:, k], s=2, alpha=0.4)
        lo, hi = float(true[:, k].min()), float(true[:, k].max())
        ax[k].plot([lo, hi], [lo, hi], "k--", lw=0.8)
        ax[k].set(xlabel=f"true {lab}", ylabel=f"predicted {lab}", aspect="equal")
    fig.suptitle(title, fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)


# ---------------------------------------------------------------------------------------- the stage
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
    return max(1, (os.cpu_count() or 1) // procs)


def _build(node, field: str, **kwargs):
    from hydra.utils import instantiate

    try:
        return instantiate(node, **kwargs)
    except PipelineError:
        raise
    except Exception as err:  # noqa: BLE001 - Lightning's MisconfigurationException, TypeError, missing package
        cause = err.__cause__ or err
        if isinstance(cause, PipelineError):
            raise cause from None
        if isinstance(cause, ModuleNotFoundError | ImportError):
            raise ConfigError(field, f"needs an optional package ({cause}); e.g. "
                                     f".venv/bin/pip install -c constraints.txt -e '.[{field.split('.')[-1]}]'") from None
        raise ConfigError(field, _first_line(cause)) from None


def _run_dir(cfg: DictConfig, fallback: Path) -> DictConfig:
    """`paths.output_dir` is Hydra's run dir; outside `@hydra.main` (tests, the DAG) it is the work dir."""
    cfg = copy.deepcopy(cfg)
    try:
        OmegaConf.select(cfg, "paths.output_dir", throw_on_resolution_failure=True)
    except Exception:  # noqa: BLE001 - `${hydra:...}` without a Hydra app
        cfg.paths.output_dir = str(fallback)
    return cfg


def run(cfg) -> dict:
    import lightning as L
    from lightning.pytorch.callbacks import LearningRateMonitor, ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    from pipeline.data import open_dataset
    from pipeline.train.predict import PerceptionMapPredictor, resolve_device

    t_start = time.perf_counter()
    check_config(cfg)  # one ConfigError before any work
    seed = int(cfg.seed)
    levels = list(_plain(cfg.eval_levels) or [])
    model_cfg = _plain(cfg.model)
    from pipeline.lineage import train_dataset_id

    ds_name, ds_id = train_dataset_id(cfg)  # the dataset this config's recipe renders (or `dataset`, pinned)
    ds = open_dataset(f"{ds_name}-{ds_id}", datasets_dir=cfg.paths.datasets_dir,
                      verify=bool(cfg.get("verify_dataset", True)))
    shape = tuple(int(s) for s in ds.images("train").shape[1:])
    want = model_cfg.get("image_shape")
    if want is not None and tuple(want) != shape:
        raise ModelError(f"model.image_shape {list(want)} does not match dataset {ds.name}-{ds.id} images {list(shape)}")
    arena = [list(a) for a in dataset_camera(ds).arena]

    name, id_ = model_identity(cfg, ds.name, ds.id)
    root = Path(cfg.paths.models_dir)
    final = root / f"{name}-{id_}"
    if tracking.is_complete(final) and not cfg.get("force", False):
        print(f"[train] {final.name} is up to date ({final}); nothing to do (force=true retrains)")
        return {"id": id_, "name": name, "path": str(final), "skipped": True,
                "metrics": json.loads((final / "metrics.json").read_text())}

    dm = _build(cfg.datamodule, "datamodule", dataset=None, seed=seed).attach(ds)  # batch vs split size
    work = root / f".work-{name}-{id_}"
    cfg = _run_dir(cfg, work)
    torch.set_num_threads(_threads(cfg))
    _quiet_lightning()
    L.seed_everything(seed, workers=True, verbose=False)
    model = _build(cfg.model, "model", image_shape=list(shape), arena=arena, name=name, _convert_="all")
    loggers = [_build(node, f"logger.{key}") for key, node in (cfg.get("logger") or {}).items()]
    callbacks = []
    for key, node in (cfg.get("callbacks") or {}).items():
        cls = str(node.get("_target_", "")).rsplit(".", 1)[-1]
        extra = {"dirpath": str(work / "ckpt")} if cls == "ModelCheckpoint" else {}
        cb = _build(node, f"callbacks.{key}", **extra)
        if isinstance(cb, LearningRateMonitor) and not loggers:
            continue  # Lightning refuses a learning-rate monitor without a logger
        callbacks.append(cb)
    ckpt_cb = next((cb for cb in callbacks if isinstance(cb, ModelCheckpoint)), None)
    if ckpt_cb is None:  # the stage needs the best and last checkpoints (saved map, resume)
        ckpt_cb = ModelCheckpoint(dirpath=work / "ckpt", filename="best", monitor="val_mae", mode="min",
                                  save_top_k=1, save_last=True)
        callbacks.append(ckpt_cb)
    # Lightning's bar on a terminal; one line per epoch in logs (a bar written to a file floods it)
    show_bar = bool(cfg.trainer.get("enable_progress_bar", True)) and sys.stderr.isatty()
    work.mkdir(parents=True, exist_ok=True)
    trainer = _build(cfg.trainer, "trainer", logger=loggers or False, callbacks=callbacks,
                     enable_progress_bar=show_bar)

    last = work / "ckpt" / "last.ckpt"
    resume = last if last.is_file() and not cfg.trainer.get("fast_dev_run") else None
    if resume and trainer.is_global_zero:
        print(f"[train] resuming {name}-{id_} from {resume}")
    t_fit = time.perf_counter()
    try:
        trainer.fit(model, datamodule=dm, ckpt_path=str(resume) if resume else None)
    except PipelineError:
        raise
    except (ValueError, TypeError) as err:  # Lightning's late config errors (MisconfigurationException is one)
        if type(err).__module__.startswith(("lightning", "pytorch_lightning")):
            raise ConfigError("trainer", _first_line(err)) from None
        raise
    fit_s = time.perf_counter() - t_fit
    if not trainer.is_global_zero:  # DDP: rank 0 evaluates the test split once and writes the map
        return {"id": id_, "name": name, "path": str(final), "skipped": False, "rank": trainer.global_rank}
    best_path = ckpt_cb.best_model_path
    if best_path and Path(best_path).is_file():
        state = torch.load(best_path, map_location="cpu", weights_only=False)["state_dict"]
        model.load_state_dict(state)
    device = resolve_device(cfg.get("device", "auto"))
    variance_fit = None
    if model.var_head is not None:  # the uncertainty head learns the trained network's own errors
        variance_fit = fit_variance_head(model, ds.images("train"), ds.positions("train"), seed=seed, device=device)
    model = model.to("cpu").eval()
    hparams = {k: v for k, v in _plain(model.hparams).items() if k not in ("image_shape", "arena")}
    predictor = PerceptionMapPredictor(model, manifest={"dataset_id": ds.id, "scene": ds.manifest["scene"],
                                                        "render": ds.manifest["render"]},
                                       device=device)
    calibration = None
    flags = dict(_plain(cfg.get("uncertainty_eval")) or UNCERTAINTY_EVAL)
    false_alarm = flags.pop("clean_false_alarm")
    gate_per_val, confidence = int(flags.pop("gate_per_val", 0)), float(flags.pop("gate_confidence", 0.5))
    if predictor.has_uncertainty:  # fit the sigma scale and the clean-image gate on the validation split
        calibration = {"variance_head": variance_fit,
                       **calibrate(model, predictor, ds.images("val"), ds.positions("val"))}
        calibration["clean_false_alarm"] = false_alarm
        calibration["clean_gate"] = fit_clean_gate(predictor, ds, false_alarm, error_px=flags["error_px"],
                                                   per_val=gate_per_val, confidence=confidence,
                                                   seed=int(cfg.get("eval_seed", 123)))
        calibration["clean_gate_px"] = flags["clean_gate_px"] = calibration["clean_gate"]["gate_px"]
    test_metrics, test_pred = evaluate(predictor, ds, levels, int(cfg.get("eval_seed", 123)), cfg.occlusions,
                                       uncertainty=flags)
    best = ckpt_cb.best_model_score
    batch = int(cfg.datamodule.batch_size)
    metrics = {"dataset": f"{ds.name}-{ds.id}", "epochs": int(trainer.current_epoch),
               "fit_seconds": round(fit_s, 1),
               "train_images_per_s": round(trainer.global_step * batch / max(fit_s, 1e-9), 1),
               "val_mae_px": float(best) if best is not None else None,
               "device": str(trainer.strategy.root_device), "world_size": int(trainer.world_size),
               **({"calibration": calibration} if calibration else {}), **test_metrics}
    meta = {"kind": "perception_map", "dataset_id": ds.id, "dataset_name": ds.name, "seed": seed,
            "model": hparams, "trainer": tracking.to_plain(cfg.trainer),
            "datamodule": tracking.to_plain(cfg.datamodule), "eval_levels": levels,
            "scene": ds.manifest["scene"], "render": ds.manifest["render"],
            "image_shape": list(shape), "arena": arena,
            "code_version": tracking.code_version("train"), "metrics": metrics}
    csv_dir = next((Path(lg.log_dir) for lg in trainer.loggers if isinstance(lg, CSVLogger)), None)
    with tracking.tracked_output(root, name, id_, meta) as out:
        torch.save({"hparams": {**hparams, "image_shape": list(shape), "arena": arena},
                    "state_dict": model.state_dict()}, out / "model.pt")
        if best_path and Path(best_path).is_file():
            shutil.copy2(best_path, out / "best.ckpt")
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=False))
        curves = _curves(csv_dir / "metrics.csv" if csv_dir else None, out)
        _scatter(test_pred, ds.positions("test"), out / "scatter.png",
                 f"{name}-{id_} on {ds.name}-{ds.id} test: MAE {metrics['test_split']['mae_px']:.3f} px")
    shutil.rmtree(work, ignore_errors=True)
    line = ", ".join(f"{k} {v['mae_px']:.3f}" for k, v in metrics.items() if isinstance(v, dict) and "mae_px" in v)
    print(f"[train] {name}-{id_}: test MAE px ({line}); {metrics['epochs']} epochs in {fit_s:.0f} s "
          f"-> {final} ({time.perf_counter() - t_start:.0f} s total)")
    return {"id": id_, "name": name, "path": str(final), "skipped": False, "metrics": metrics,
            "epochs": len(curves)}


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
