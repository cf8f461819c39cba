"""The imitation network (SPEC §6): the perception map's trunk with a velocity head.

The trunk is the map's (:func:`pipeline.perception.network.conv_blocks`: Conv(3x3)[-BN]-ReLU-MaxPool blocks on
the frame scaled to [-0.5, 0.5], with the two CoordConv channels), optionally initialised from a trained map's
weights (`imitation.trunk_from`; `freeze_trunk`: kept as the map learned it). `reads: features` (default): the
head (Flatten, Dropout, Linear-ReLU, Linear) reads the pooled features; `reads: keypoint`: the map's keypoint
head (:class:`pipeline.perception.keypoint.KeypointHead`, copied and frozen with the trunk) reads the last block
before its pooling, and the head (Linear-ReLU, Linear-ReLU, Linear) reads the soft-argmax position it gives
(on clouded frames the flat readout of a frozen trunk does not fit: docs/learned.md). Either way the policy is a
network continuous in the image. The head predicts `3` velocities, each `(N, 2)`
in units of `u_max`: head 0 the expert's action (the end-to-end policy), heads 1 and 2 the hybrid controller's
flow in mode 1 and mode 2 (the two policies of the learned hybrid policy). The loss is the MSE of each head on the
frames where its label is defined (the mode's flow set), weights equal.
"""

from __future__ import annotations

import dataclasses

import lightning as L
import numpy as np
import torch
from torch import nn

from pipeline.errors import ConfigError
from pipeline.learned.spec import PolicySpec
from pipeline.perception.keypoint import KeypointHead
from pipeline.perception.network import conv_blocks

HEADS = 3  # expert action, mode-1 flow, mode-2 flow


class VelocityPolicy(L.LightningModule):
    """`forward(uint8 NHWC frames) -> (N, HEADS, 2)` velocities in world units per second."""

    @classmethod
    def of(cls, **fields) -> VelocityPolicy:
        """The network of `PolicySpec(**fields)` (Python callers, a saved policy's hyperparameters)."""
        return cls(PolicySpec(**fields))

    def __init__(self, spec: PolicySpec):
        super().__init__()
        self.save_hyperparameters(dataclasses.asdict(spec))
        image_shape, filters, hidden, reads = spec.image_shape, spec.filters, spec.hidden, spec.reads
        h, w, _ = image_shape
        self.image_shape, self.u_max, self.lr = tuple(image_shape), float(spec.u_max), float(spec.lr)
        self.coord_channels, self.freeze_trunk = bool(spec.coord_channels), bool(spec.freeze_trunk)
        cols = torch.linspace(-0.5, 0.5, w).view(1, 1, 1, w).expand(1, 1, h, w)
        rows = torch.linspace(-0.5, 0.5, h).view(1, 1, h, 1).expand(1, 1, h, w)
        self.register_buffer("coords", torch.cat([cols, rows], 1).contiguous(), persistent=False)
        self.features = conv_blocks(3 + 2 * self.coord_channels, [int(f) for f in filters], spec.batch_norm)
        fh, fw = h, w
        for _ in filters[:-1]:
            fh, fw = fh // 2, fw // 2
        self.reads = reads
        self.readings: tuple[int, torch.Tensor] | None = None  # a fit's (batch, frozen keypoint readings)
        self.keypoint = KeypointHead(int(filters[-1]), (fh, fw)) if reads == "keypoint" else None
        fh, fw = fh // 2, fw // 2
        self.head = nn.Sequential(nn.Linear(2, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden),
                                  nn.ReLU(inplace=True), nn.Linear(hidden, 2 * HEADS)) if reads == "keypoint" else \
            nn.Sequential(nn.Flatten(), nn.Dropout(spec.dropout), nn.Linear(int(filters[-1]) * fh * fw, hidden),
                          nn.ReLU(inplace=True), nn.Linear(hidden, 2 * HEADS))

    def prepare(self, images: torch.Tensor) -> torch.Tensor:
        x = images.permute(0, 3, 1, 2).to(torch.float32)
        x = x * (1.0 / 255.0) - 0.5 if images.dtype == torch.uint8 else x - 0.5
        if self.coord_channels:
            x = torch.cat([x, self.coords.expand(len(x), -1, -1, -1)], 1)
        return x

    def normalised(self, images: torch.Tensor) -> torch.Tensor:
        """Velocities in units of `u_max` `(N, HEADS, 2)` (images: uint8 in [0, 255] or float in [0, 1])."""
        if self.keypoint is not None:
            return self.head(self.keypoint_of(images)).view(-1, HEADS, 2)
        return self.head(self.features(self.prepare(images))).view(-1, HEADS, 2)

    def keypoint_of(self, images: torch.Tensor) -> torch.Tensor:
        """`reads: keypoint`: the position the keypoint head reads in each image `(N, 2)` (what the head gets)."""
        return self.keypoint(self.features[:-1](self.prepare(images)))[0]

    def frozen_readings(self, images: np.ndarray, batch: int) -> torch.Tensor | None:
        """With `reads: keypoint` and `freeze_trunk`, the keypoint positions of `images` `(N, H, W, 3)` read once for
        a fit instead of every epoch `(N, 2)`, every image read in a batch of `batch` (the trunk in eval mode, as
        each epoch puts it). A convolution's result for one image depends on its batch's size (oneDNN picks its
        kernel by it), not on the other images in it: a training batch of `batch` frames gets from these the bits it
        would compute itself, and a smaller one (an epoch's last) reads its frames again (:meth:`loss`). None for a
        trunk that learns (`freeze_trunk` false, or no map's trunk loaded: :meth:`load_trunk` freezes it)."""
        if self.keypoint is None or any(p.requires_grad for p in [*self.features.parameters(),
                                                                   *self.keypoint.parameters()]):
            return None
        n, size = len(images), min(batch, len(images))
        read = torch.empty(n, 2)
        self.features.eval()
        with torch.no_grad():
            for s in [*range(0, n - size + 1, size), *([n - size] if n % size else [])]:
                read[s:s + size] = self.keypoint_of(torch.from_numpy(images[s:s + size]))
        return read

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.normalised(images) * self.u_max

    def load_trunk(self, perception_model) -> None:
        """Initialise the trunk from a trained perception map's (same blocks and input channels); with
        `freeze_trunk` it stays as the map learned it (no gradient, BatchNorm in eval mode). `reads: keypoint`
        copies the map's keypoint head too (a map with one)."""
        self.features.load_state_dict(perception_model.features.state_dict())
        self.features.requires_grad_(not self.freeze_trunk)
        if self.keypoint is not None:
            if not getattr(perception_model, "keypoint", False):
                raise ConfigError("model.reads", "keypoint needs a trunk map with a keypoint head "
                                                 "(imitation.trunk_from: a *_keypoint map)")
            self.keypoint.load_state_dict(perception_model.head.state_dict())
            self.keypoint.requires_grad_(not self.freeze_trunk)

    def on_train_epoch_start(self) -> None:
        if self.freeze_trunk:
            self.features.eval()

    def loss(self, batch) -> torch.Tensor:
        """`batch`: (B, H, W, 3) uint8 frames, [with `readings` set (a fit's, :meth:`frozen_readings`) their indices
        `(B,)`,] (B, HEADS, 2) labels in world units, (B, HEADS) bool masks."""
        images, *index, labels, mask = batch
        if index and len(images) == self.readings[0]:  # a full batch: the frozen trunk's readings
            out = self.head(self.readings[1][index[0]]).view(-1, HEADS, 2)
        else:
            out = self.normalised(images)
        err = (out - labels / self.u_max).pow(2).sum(-1)
        m = mask.to(err.dtype)
        return ((err * m).sum(0) / m.sum(0).clamp_min(1.0)).sum()

    def training_step(self, batch, batch_idx):
        loss = self.loss(batch)
        self.log("train_loss", loss, prog_bar=True)
        return loss

    def validation_step(self, batch, batch_idx):
        self.log("val_loss", self.loss(batch), prog_bar=True)

    def configure_optimizers(self):
        return torch.optim.Adam([p for p in self.parameters() if p.requires_grad], lr=self.lr)

    @torch.no_grad()
    def act(self, images, head: int | torch.Tensor = 0) -> torch.Tensor:
        """World velocities `(N, 2)` of head `head` (an int, or a per-row tensor of heads), in eval mode."""
        was = self.training
        self.eval()
        x = torch.as_tensor(images)
        out = self(x)
        self.train(was)
        if isinstance(head, int):
            return out[:, head]
        return out[torch.arange(len(out)), head]
