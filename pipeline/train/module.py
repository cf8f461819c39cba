"""The perception map's training (SPEC §2): :class:`pipeline.perception.network.PerceptionNet` with Lightning's
steps, logging and optimiser. The network, its parameters and their initial values are the net's own (a trained
map is saved as the net's `state_dict` and hyperparameters, and loaded without Lightning:
`pipeline.perception.maps.load_perception_map`)."""

from __future__ import annotations

import dataclasses

import lightning as L
import torch
from torch import nn

from pipeline.perception.heading import heading_deg
from pipeline.perception.network import PerceptionNet
from pipeline.perception.spec import MapSpec


class PerceptionMap(PerceptionNet, L.LightningModule):
    """The net trained by Lightning; `hparams` are the spec's fields. `certified_term`: a bound-based term the train
    stage attaches (`pipeline.train.certified`); None: off."""

    def __init__(self, spec: MapSpec):
        super().__init__(spec)
        self.save_hyperparameters(dataclasses.asdict(spec))
        self.heading_weight = float(spec.heading_weight)
        self.certified_term = None
        self._loss = {"mse": nn.functional.mse_loss, "l1": nn.functional.l1_loss,
                      "smooth_l1": nn.functional.smooth_l1_loss}[spec.loss]

    def _step(self, batch, stage: str):
        images, labels = batch
        target = self.targets(labels)
        pred_n = self.head_outputs(*self.encode(self.prepare(images)))  # the variance head is fitted afterwards
        if self.pose:  # position and heading, the heading's loss weighted (pipeline.perception.heading)
            loss = self._loss(pred_n[:, :2], target[:, :2]) + self.heading_weight * self._loss(pred_n[:, 2:4],
                                                                                               target[:, 2:])
            self.log(f"{stage}_heading_deg", heading_deg(pred_n.detach()[:, 2:4], target[:, 2:]), prog_bar=True,
                     on_epoch=True, on_step=False, batch_size=len(labels), sync_dist=stage != "train")
        else:
            loss = self._loss(pred_n, target)
        err_px = (pred_n.detach()[:, :2] - target[:, :2]) * self.half_range * self.px_per_unit
        sync = stage != "train"  # epoch metrics over every rank's share of the split (a no-op on one device)
        self.log(f"{stage}_loss", loss, prog_bar=stage != "train", on_epoch=True, on_step=stage == "train",
                 batch_size=len(labels), sync_dist=sync)
        self.log(f"{stage}_mae", err_px.abs().mean(), prog_bar=True, on_epoch=True, on_step=False,
                 batch_size=len(labels), sync_dist=sync)
        return loss

    def training_step(self, batch, batch_idx):
        loss = self._step(batch, "train")
        return loss if self.certified_term is None else self.certified_term.add_to(self, loss, batch, batch_idx)

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
