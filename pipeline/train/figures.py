"""The train stage's figures: learning curves (`curves.csv/png`) and the test scatter (`scatter.png`)."""

from __future__ import annotations

from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402


def curves(log_csv: Path | None, out: Path) -> pd.DataFrame:
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


def scatter(pred: np.ndarray, true: np.ndarray, path: Path, title: str) -> None:
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
