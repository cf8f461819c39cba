"""The perception map `l(theta) ≈ p` (SPEC §2): the paper's CNN as a LightningModule.

Three Conv(3x3)-ReLU-MaxPool(2x2) blocks, flatten, Dropout(0.5), Linear -> 2 (the paper's block
structure). Filter counts, an optional BatchNorm, an optional hidden layer and the input/target
normalisation are config values (`conf/model/`). Inputs are uint8 images `(N, H, W, 3)` as stored in the
datasets; the module converts them to float channels_last tensors itself. Outputs are world coordinates:
the network predicts positions normalised to `[-1, 1]` over the arena and the module scales them back.
"""

from __future__ import annotations

from collections.abc import Sequence

import lightning as L
import torch
from torch import nn

from pipeline.errors import ConfigError, ModelError


def conv_blocks(in_ch: int, filters: Sequence[int], batch_norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for out_ch in filters:
        layers.append(nn.Conv2d(in_ch, out_ch, 3, padding=1, bias=not batch_norm))
        if batch_norm:
            layers.append(nn.BatchNorm2d(out_ch))
        layers += [nn.ReLU(inplace=True), nn.MaxPool2d(2)]
        in_ch = out_ch
    return nn.Sequential(*layers)


class PerceptionMap(L.LightningModule):
    """CNN perception map; `forward(uint8 or float images NHWC) -> (N, 2)` world coordinates."""

    def __init__(
        self,
        image_shape: Sequence[int] = (60, 100, 3),
        arena: Sequence[Sequence[float]] = ((-50.0, 50.0), (-30.0, 30.0)),
        filters: Sequence[int] = (32, 64, 128),
        batch_norm: bool = False,
        hidden: int = 0,
        dropout: float = 0.5,
        lr: float = 1e-3,
        weight_decay: float = 0.0,
        schedule: str = "constant",
        loss: str = "mse",
        coord_channels: bool = False,
        clamp: bool = True,
        name: str = "perception_map",
    ):
        super().__init__()
        self.save_hyperparameters()
        if len(image_shape) != 3 or image_shape[2] != 3:
            raise ConfigError("model.image_shape", f"must be [H, W, 3], got {list(image_shape)}")
        if not filters or any(int(f) <= 0 for f in filters):
            raise ConfigError("model.filters", f"must be a non-empty list of positive ints, got {list(filters)}")
        if not 0.0 <= dropout < 1.0:
            raise ConfigError("model.dropout", f"must be in [0, 1), got {dropout}")
        if schedule not in ("constant", "cosine", "onecycle"):
            raise ConfigError("model.schedule", f"must be constant, cosine or onecycle, got {schedule!r}")
        if loss not in ("mse", "l1", "smooth_l1"):
            raise ConfigError("model.loss", f"must be mse, l1 or smooth_l1, got {loss!r}")
        h, w, _ = (int(s) for s in image_shape)
        self.image_shape = (h, w, 3)
        (x0, x1), (y0, y1) = arena
        self.register_buffer("center", torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2], dtype=torch.float32))
        self.register_buffer("half_range", torch.tensor([(x1 - x0) / 2, (y1 - y0) / 2], dtype=torch.float32))
        # px per world unit (for metrics reported in pixels)
        self.px_per_unit = float(w / (x1 - x0))
        # CoordConv: two extra input channels holding the pixel's column/row in [-0.5, 0.5]
        self.coord_channels = bool(coord_channels)
        self.clamp = bool(clamp)
        if self.coord_channels:
            cols = torch.linspace(-0.5, 0.5, w).view(1, 1, 1, w).expand(1, 1, h, w)
            rows = torch.linspace(-0.5, 0.5, h).view(1, 1, h, 1).expand(1, 1, h, w)
            self.register_buffer("coords", torch.cat([cols, rows], 1).contiguous(), persistent=False)
        self.features = conv_blocks(3 + 2 * self.coord_channels, [int(f) for f in filters], batch_norm)
        fh, fw = h, w
        for _ in filters:
            fh, fw = fh // 2, fw // 2
        if fh < 1 or fw < 1:
            raise ConfigError("model.filters", f"{len(filters)} pooling blocks shrink a {h}x{w} image to nothing")
        flat = int(filters[-1]) * fh * fw
        head: list[nn.Module] = [nn.Flatten(), nn.Dropout(dropout)]
        if hidden:
            head += [nn.Linear(flat, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 2)]
        else:
            head += [nn.Linear(flat, 2)]
        self.head = nn.Sequential(*head)
        self._loss = {"mse": nn.functional.mse_loss, "l1": nn.functional.l1_loss,
                      "smooth_l1": nn.functional.smooth_l1_loss}[loss]
        self.to(memory_format=torch.channels_last)

    # --------------------------------------------------------------------------------- forward
    def prepare(self, images: torch.Tensor) -> torch.Tensor:
        """uint8/float NHWC -> float NCHW (channels_last memory), scaled to [-0.5, 0.5]."""
        if images.ndim != 4 or tuple(images.shape[1:]) != self.image_shape:
            raise ModelError(
                f"image shape {tuple(images.shape[1:])} does not match the model's {self.image_shape}"
            )
        x = images.permute(0, 3, 1, 2)  # a view: NCHW shape with channels_last strides
        x = x.to(torch.float32)
        if images.dtype == torch.uint8:
            x = x.mul_(1.0 / 255.0)
        x = x.sub_(0.5)
        if self.coord_channels:
            x = torch.cat([x, self.coords.expand(len(x), -1, -1, -1)], 1)
        return x.contiguous(memory_format=torch.channels_last)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        z = self.head(self.features(self.prepare(images)))
        if self.clamp and not self.training:
            z = z.clamp(-1.0, 1.0)  # a position estimate never leaves the arena the camera sees
        return z * self.half_range + self.center

    def normalised(self, images: torch.Tensor) -> torch.Tensor:
        return self.head(self.features(self.prepare(images)))

    # -------------------------------------------------------------------------------- training
    def _step(self, batch, stage: str):
        images, pos = batch
        target = (pos - self.center) / self.half_range
        pred_n = self.normalised(images)
        loss = self._loss(pred_n, target)
        err_px = (pred_n.detach() - target) * self.half_range * self.px_per_unit
        self.log(f"{stage}_loss", loss, prog_bar=stage != "train", on_epoch=True, on_step=stage == "train",
                 batch_size=len(pos))
        self.log(f"{stage}_mae", err_px.abs().mean(), prog_bar=True, on_epoch=True, on_step=False,
                 batch_size=len(pos))
        return loss

    def training_step(self, batch, batch_idx):
        return self._step(batch, "train")

    def validation_step(self, batch, batch_idx):
        return self._step(batch, "val")

    def configure_optimizers(self):
        hp = self.hparams
        opt = torch.optim.Adam(self.parameters(), lr=hp.lr, weight_decay=hp.weight_decay)
        if hp.schedule == "constant":
            return opt
        total = int(self.trainer.estimated_stepping_batches)
        if hp.schedule == "cosine":
            sched = torch.optim.lr_scheduler.CosineAnnealingLR(opt, T_max=max(1, total))
        else:
            sched = torch.optim.lr_scheduler.OneCycleLR(opt, max_lr=hp.lr, total_steps=max(2, total),
                                                        pct_start=0.15)
        return {"optimizer": opt, "lr_scheduler": {"scheduler": sched, "interval": "step"}}

    def flops_per_image(self) -> float:
        """Forward multiply-adds x2 of the conv and linear layers (for GFLOP/s figures)."""
        h, w, _ = self.image_shape
        flops = 0.0
        for m in self.features:
            if isinstance(m, nn.Conv2d):
                flops += 2 * h * w * m.in_channels * m.out_channels * 9
            elif isinstance(m, nn.MaxPool2d):
                h, w = h // 2, w // 2
        for m in self.head:
            if isinstance(m, nn.Linear):
                flops += 2 * m.in_features * m.out_features
        return flops
