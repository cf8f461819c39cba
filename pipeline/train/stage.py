"""The train stage: `python -m pipeline.train` — a tracked perception map per dataset.

Output: `outputs/models/<name>-<id>/` with `model.pt` (weights + hyper-parameters), `best.ckpt` (the
Lightning checkpoint of the best validation epoch), `metrics.json` (test MAE/RMSE in px on the dataset's
test split and re-rendered at each occlusion level), `curves.csv/png`, `scatter.png`, `config.yaml` and
`manifest.json`. The id hashes the model and trainer configs (minus volatile keys), the dataset id, the seed
and the training code, so an unchanged run is skipped. Interrupted runs resume from
`outputs/models/.work-<name>-<id>/last.ckpt`.
"""

from __future__ import annotations

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
from omegaconf import OmegaConf

from pipeline import tracking
from pipeline.errors import ConfigError, ModelError
from pipeline.train.model import PerceptionMap

log = logging.getLogger(__name__)

# Trainer keys that change speed or display, not the weights: left out of the model id.
VOLATILE = ("enable_progress_bar", "num_threads", "log_every_n_steps", "eval_batch_size", "num_workers")
_TRAINER_KEYS = ("max_epochs", "max_minutes", "batch_size", "fast_dev_run", "limit_train_batches",
                 "limit_val_batches", "gradient_clip_val", "limit_train_samples")


def _validate_trainer(tc: dict) -> None:
    unknown = set(tc) - set(_TRAINER_KEYS) - set(VOLATILE) - {"name"}
    if unknown:
        raise ConfigError("trainer", f"unknown key(s) {sorted(unknown)}; known: {sorted(_TRAINER_KEYS + VOLATILE)}")
    if not isinstance(tc.get("max_epochs"), int) or tc["max_epochs"] <= 0:
        raise ConfigError("trainer.max_epochs", f"must be a positive integer, got {tc.get('max_epochs')!r}")
    if not isinstance(tc.get("batch_size"), int) or tc["batch_size"] <= 0:
        raise ConfigError("trainer.batch_size", f"must be a positive integer, got {tc.get('batch_size')!r}")
    mm = tc.get("max_minutes")
    if mm is not None and not (isinstance(mm, int | float) and mm > 0):
        raise ConfigError("trainer.max_minutes", f"must be > 0 or null, got {mm!r}")


def model_name(dataset_name: str, model_cfg: dict, trainer_cfg: dict, override: str | None) -> str:
    if override:
        return str(override)
    parts = [dataset_name]
    for cfg in (model_cfg, trainer_cfg):
        if cfg.get("name") not in (None, "default"):
            parts.append(str(cfg["name"]))
    return "_".join(dict.fromkeys(parts))  # e.g. clean, clean_paper


def model_identity(cfg, dataset_name: str, dataset_id: str) -> tuple[str, str]:
    """(folder name, id) of the map a composed train config trains on a dataset: what changes the weights."""
    model_cfg = tracking.to_plain(cfg.model)
    trainer_cfg = tracking.to_plain(cfg.trainer)
    levels = list(tracking.to_plain(cfg.eval_levels) or [])
    name = model_name(dataset_name, model_cfg, trainer_cfg, cfg.get("name"))
    id_ = tracking.content_id(
        {k: v for k, v in model_cfg.items() if k != "name"},
        tracking.strip_keys(trainer_cfg, VOLATILE + ("name",)),
        dataset_id, int(cfg.seed), levels, tracking.code_version("train"),
    )
    return name, id_


def dataset_camera(ds):
    """The Camera that rendered a dataset (from its manifest)."""
    return ds.camera()


# ------------------------------------------------------------------------------------- evaluation
def error_metrics(pred: np.ndarray, true: np.ndarray, px_per_unit: float) -> dict:
    err = (np.asarray(pred, np.float64) - np.asarray(true, np.float64)) * px_per_unit
    dist = np.hypot(err[:, 0], err[:, 1])
    return {
        "mae_px": float(np.abs(err).mean()),  # per coordinate, as Keras' MAE (the authors' metric)
        "rmse_px": float(np.sqrt((err**2).mean())),
        "mean_dist_px": float(dist.mean()),
        "p95_dist_px": float(np.percentile(dist, 95)),
        "max_dist_px": float(dist.max()),
        "n": len(err),
    }


def evaluate(predictor, ds, levels, seed: int, occlusions=None) -> tuple[dict, np.ndarray]:
    """Test metrics on the dataset's own test split and on its test positions re-rendered per level;
    also returns the predictions on the test split."""
    from pipeline.render import load_occlusion

    out = {}
    images, pos = ds.images("test"), ds.positions("test")
    test_pred = predictor.predict(images)
    out["test_split"] = error_metrics(test_pred, pos, predictor.px_per_unit)
    labels = ds.labels[ds.labels["split"] == "test"]
    follower = labels[["follower_x", "follower_y"]].to_numpy(np.float64) if "follower_x" in labels else None
    cam = dataset_camera(ds)
    for level in levels:
        occ = load_occlusion(level, occlusions, field="eval_levels")
        rng = np.random.default_rng(seed)
        imgs = cam.render(pos, follower, occlusion=occ, rng=rng)
        out[level] = error_metrics(predictor.predict(imgs), pos, predictor.px_per_unit)
    return out, test_pred


# ------------------------------------------------------------------------------------------ figures
def _curves(log_csv: Path, out: Path) -> pd.DataFrame:
    raw = pd.read_csv(log_csv) if log_csv.is_file() else pd.DataFrame()
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
def _epoch_line_callback():
    import lightning as L

    class EpochLine(L.Callback):
        """One progress line per epoch when no progress bar is shown (logs, CI)."""

        def __init__(self, name: str):
            self.name, self.t0 = name, time.perf_counter()

        def on_validation_epoch_end(self, trainer, pl_module):
            if trainer.sanity_checking:
                return
            m = {k: float(v) for k, v in trainer.callback_metrics.items() if k in ("val_mae", "train_loss_epoch")}
            print(f"[train] {self.name}: epoch {trainer.current_epoch + 1}/{trainer.max_epochs} "
                  f"val MAE {m.get('val_mae', float('nan')):.3f} px ({time.perf_counter() - self.t0:.0f} s)",
                  flush=True)

    return EpochLine



def _quiet_lightning() -> None:
    for name in ("lightning", "lightning.pytorch", "lightning.fabric", "lightning_fabric"):
        logging.getLogger(name).setLevel(logging.WARNING)
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    warnings.filterwarnings("ignore", ".*LeafSpec.*")
    warnings.filterwarnings("ignore", ".*treespec.*")


def run(cfg) -> dict:
    import lightning as L
    from lightning.pytorch.callbacks import ModelCheckpoint
    from lightning.pytorch.loggers import CSVLogger

    from pipeline.data import open_dataset
    from pipeline.render import occlusion_levels
    from pipeline.train.datamodule import PerceptionDataModule
    from pipeline.train.predict import PerceptionMapPredictor

    EpochLine = _epoch_line_callback()  # noqa: N806 - a class
    t_start = time.perf_counter()
    model_cfg = tracking.to_plain(cfg.model)
    trainer_cfg = tracking.to_plain(cfg.trainer)
    _validate_trainer(trainer_cfg)
    levels = list(tracking.to_plain(cfg.eval_levels) or [])
    known_levels = occlusion_levels(cfg.occlusions)
    for lv in levels:
        if lv not in known_levels:
            raise ConfigError("eval_levels", f"unknown occlusion level {lv!r}; known: {', '.join(known_levels)}")
    from pipeline.lineage import train_dataset_id

    ds_name, ds_id = train_dataset_id(cfg)  # the dataset this config's recipe renders (or `dataset`, pinned)
    ds = open_dataset(f"{ds_name}-{ds_id}", datasets_dir=cfg.paths.datasets_dir,
                      verify=bool(cfg.get("verify_dataset", True)))
    shape = tuple(int(s) for s in ds.images("train").shape[1:])
    want = model_cfg.get("image_shape")
    if want is not None and tuple(want) != shape:
        raise ModelError(f"model.image_shape {list(want)} does not match dataset {ds.name}-{ds.id} images {list(shape)}")
    arena = dataset_camera(ds).arena

    name, id_ = model_identity(cfg, ds.name, ds.id)
    seed = int(cfg.seed)
    root = Path(cfg.paths.models_dir)
    final = root / f"{name}-{id_}"
    if tracking.is_complete(final) and not cfg.get("force", False):
        print(f"[train] {final.name} is up to date ({final}); nothing to do (force=true retrains)")
        return {"id": id_, "name": name, "path": str(final), "skipped": True,
                "metrics": json.loads((final / "metrics.json").read_text())}

    torch.set_num_threads(int(trainer_cfg.get("num_threads") or os.cpu_count() or 1))
    _quiet_lightning()
    L.seed_everything(seed, workers=True, verbose=False)
    hparams = {k: v for k, v in model_cfg.items() if k not in ("image_shape",)}
    hparams["name"] = name
    model = PerceptionMap(image_shape=shape, arena=arena, **hparams)
    dm = PerceptionDataModule(ds, batch_size=trainer_cfg["batch_size"],
                              eval_batch_size=int(trainer_cfg.get("eval_batch_size") or 512), seed=seed,
                              limit_train=trainer_cfg.get("limit_train_samples"))

    work = root / f".work-{name}-{id_}"
    work.mkdir(parents=True, exist_ok=True)
    # Lightning's bar on a terminal; one line per epoch in logs (a bar written to a file floods it)
    show_bar = bool(trainer_cfg.get("enable_progress_bar", True)) and sys.stderr.isatty()
    ckpt_cb = ModelCheckpoint(dirpath=work / "ckpt", filename="best", monitor="val_mae", mode="min",
                              save_top_k=1, save_last=True)
    logger = CSVLogger(save_dir=str(work), name="logs", version=0)
    mm = trainer_cfg.get("max_minutes")
    trainer = L.Trainer(
        accelerator="cpu", devices=1, max_epochs=trainer_cfg["max_epochs"],
        max_time={"minutes": float(mm)} if mm else None,
        fast_dev_run=bool(trainer_cfg.get("fast_dev_run", False)),
        limit_train_batches=trainer_cfg.get("limit_train_batches") or 1.0,
        limit_val_batches=trainer_cfg.get("limit_val_batches") or 1.0,
        gradient_clip_val=trainer_cfg.get("gradient_clip_val"),
        enable_progress_bar=show_bar,
        log_every_n_steps=int(trainer_cfg.get("log_every_n_steps") or 50),
        callbacks=[ckpt_cb, *([] if show_bar else [EpochLine(name)])], logger=logger, num_sanity_val_steps=0, enable_model_summary=False,
        default_root_dir=str(work),
    )
    last = work / "ckpt" / "last.ckpt"
    resume = last if last.is_file() and not trainer_cfg.get("fast_dev_run") else None
    if resume:
        print(f"[train] resuming {name}-{id_} from {resume}")
    t_fit = time.perf_counter()
    trainer.fit(model, datamodule=dm, ckpt_path=str(resume) if resume else None)
    fit_s = time.perf_counter() - t_fit
    best_path = ckpt_cb.best_model_path
    if best_path and Path(best_path).is_file():
        state = torch.load(best_path, map_location="cpu", weights_only=False)["state_dict"]
        model.load_state_dict(state)
    model.eval()
    predictor = PerceptionMapPredictor(model, manifest={"dataset_id": ds.id, "scene": ds.manifest["scene"],
                                                        "render": ds.manifest["render"]})
    test_metrics, test_pred = evaluate(predictor, ds, levels, int(cfg.get("eval_seed", 123)), cfg.occlusions)
    metrics = {"dataset": f"{ds.name}-{ds.id}", "epochs": int(trainer.current_epoch),
               "fit_seconds": round(fit_s, 1),
               "train_images_per_s": round(trainer.global_step * trainer_cfg["batch_size"] / max(fit_s, 1e-9), 1),
               **test_metrics}
    meta = {"kind": "perception_map", "dataset_id": ds.id, "dataset_name": ds.name, "seed": seed,
            "model": hparams, "trainer": trainer_cfg, "eval_levels": levels,
            "scene": ds.manifest["scene"], "render": ds.manifest["render"],
            "image_shape": list(shape), "arena": [list(a) for a in arena],
            "code_version": tracking.code_version("train"), "metrics": metrics}
    with tracking.tracked_output(root, name, id_, meta) as out:
        torch.save({"hparams": {**hparams, "image_shape": list(shape), "arena": [list(a) for a in arena]},
                    "state_dict": model.state_dict()}, out / "model.pt")
        if best_path and Path(best_path).is_file():
            shutil.copy2(best_path, out / "best.ckpt")
        (out / "metrics.json").write_text(json.dumps(metrics, indent=2) + "\n")
        (out / "config.yaml").write_text(OmegaConf.to_yaml(cfg, resolve=False))
        curves = _curves(work / "logs" / "version_0" / "metrics.csv", out)
        _scatter(test_pred, ds.positions("test"), out / "scatter.png",
                 f"{name}-{id_} on {ds.name}-{ds.id} test: MAE {metrics['test_split']['mae_px']:.3f} px")
    shutil.rmtree(work, ignore_errors=True)
    line = ", ".join(f"{k} {v['mae_px']:.3f}" for k, v in metrics.items() if isinstance(v, dict))
    print(f"[train] {name}-{id_}: test MAE px ({line}); {metrics['epochs']} epochs in {fit_s:.0f} s "
          f"-> {final} ({time.perf_counter() - t_start:.0f} s total)")
    return {"id": id_, "name": name, "path": str(final), "skipped": False, "metrics": metrics,
            "epochs": len(curves)}

