"""Small Lightning callbacks of the train stage (built from `conf/callbacks/`)."""

from __future__ import annotations

import time

import lightning as L


class EpochLine(L.Callback):
    """One progress line per epoch when Lightning's progress bar is off (logs, CI, a non-tty stderr)."""

    def __init__(self, label: str | None = None):
        self.label, self.t0 = label, time.perf_counter()

    def on_fit_start(self, trainer, pl_module):
        self.t0 = time.perf_counter()
        if self.label is None:
            self.label = str(getattr(pl_module, "hparams", {}).get("name", "train"))

    def on_validation_epoch_end(self, trainer, pl_module):
        if trainer.sanity_checking or trainer.progress_bar_callback is not None or not trainer.is_global_zero:
            return
        mae = trainer.callback_metrics.get("val_mae")
        print(f"[train] {self.label}: epoch {trainer.current_epoch + 1}/{trainer.max_epochs} "
              f"val MAE {float(mae) if mae is not None else float('nan'):.3f} px "
              f"({time.perf_counter() - self.t0:.0f} s)", flush=True)
