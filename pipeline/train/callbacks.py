"""One progress line per epoch (logs, CI, a non-tty stderr): the train stage's (`callbacks.progress`,
conf/callbacks/default.yaml) and the imitation's. :func:`epoch_line` is a factory, so this module imports no
Lightning and a `callbacks.progress` node is imported and checked in the preflight like every other node."""

from __future__ import annotations

import functools
import time
from typing import Literal


def epoch_line(label: str | None = None, metric: Literal["val_mae", "train_loss"] = "val_mae"):
    """A Lightning callback printing one line per epoch while Lightning's progress bar is off: `val_mae` after each
    validation (the train stage, in px) or `train_loss` after each training epoch (the imitation). `label`: the
    run's name (default: the model's `name`)."""
    return _epoch_line()(label, metric)


@functools.cache
def _epoch_line():
    import lightning as L

    class EpochLine(L.Callback):
        def __init__(self, label: str | None, metric: str):
            self.label, self.metric, self.t0 = label, metric, time.perf_counter()

        def on_fit_start(self, trainer, pl_module):
            self.t0 = time.perf_counter()
            if self.label is None:
                self.label = str(getattr(pl_module, "hparams", {}).get("name", "train"))

        def on_validation_epoch_end(self, trainer, pl_module):
            if self.metric == "val_mae" and not trainer.sanity_checking:
                self._line(trainer, "[train]", "val MAE {:.3f} px")

        def on_train_epoch_end(self, trainer, pl_module):
            if self.metric == "train_loss":
                self._line(trainer, "[imitate]", "train loss {:.4f}")

        def _line(self, trainer, stage: str, words: str):
            if trainer.progress_bar_callback is not None or not trainer.is_global_zero:
                return
            value = trainer.callback_metrics.get(self.metric)
            value = float(value) if value is not None else float("nan")
            print(f"{stage} {self.label}: epoch {trainer.current_epoch + 1}/{trainer.max_epochs} "
                  f"{words.format(value)} ({time.perf_counter() - self.t0:.0f} s)", flush=True)

    return EpochLine
