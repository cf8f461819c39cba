"""Maps trained to be certifiable (SPEC §5.2, "Certifiable maps"): a bound-based term on sampled cells added to the
regression loss in `PerceptionMap.training_step`.

Each training step draws `cells_per_step` cells of side `s(t)` centred on the batch's own positions (the training
distribution), bounds the perception error over them with :func:`pipeline.certify.certified_error_bound` (from the
position through the camera and the network as deployed, differentiable in the weights) and adds

    weight(t) * mean(relu(eps_bar(P) - target))          (eps_bar in world units)

to the loss. The schedule (`t` in epochs, fractional within an epoch; the warm-up certified training needs):

- `t < warmup_epochs`: regression only (the term is not computed);
- then over `ramp_epochs` the weight ramps linearly from 0 to `weight` and the cell side from `cell_start` to
  `cell`; both stay there afterwards;
- the bound is `ibp` (cheap, loose) until `warmup_epochs + ibp_epochs`, then `mode` (`crown`: the tight one).

Off by default (`certified: null` in conf/train.yaml): the loss and the weights are those of a map without it.
`certified=on` (conf/certified/on.yaml) turns it on; its keys are part of the map's id.
"""

from __future__ import annotations

import torch

from pipeline.certify import certified_error_bound, prepare
from pipeline.train.settings import CertifiedTraining


class CertifiedTerm:
    """The term for one run: the settings and the camera the bound renders with (the dataset's)."""

    def __init__(self, settings: CertifiedTraining, camera):
        self.settings = settings
        self.camera = camera
        self.last: dict = {}

    def __call__(self, model, labels: torch.Tensor, epoch: float) -> torch.Tensor | None:
        """The term at fractional epoch `epoch` on cells around the first `cells_per_step` positions of `labels`;
        None during the warm-up (nothing computed)."""
        w, side, mode = self.settings.schedule(epoch)
        if w == 0:
            self.last = {"weight": 0.0, "cell": side, "mode": mode}
            return None
        c = labels[: self.settings.cells_per_step, :2].detach().to(torch.float32)
        h = side / 2
        cells = torch.stack([c[:, 0] - h, c[:, 0] + h, c[:, 1] - h, c[:, 1] + h], 1)
        prep = prepare(model, self.camera, self.settings.kappa)  # rebuilt every step: the weights moved
        eps = certified_error_bound(prep, cells, mode).eps
        term = torch.relu(eps - self.settings.target).mean()
        self.last = {"weight": w, "cell": side, "mode": mode, "eps_mean": float(eps.detach().mean())}
        return w * term

    def add_to(self, model, loss: torch.Tensor, batch, batch_idx: int) -> torch.Tensor:
        """`loss` plus the term at the step's fractional epoch, logged on the model (the warm-up: `loss` alone)."""
        n = model.trainer.num_training_batches
        epoch = model.current_epoch + (batch_idx / n if n and n != float("inf") else 0.0)
        term = self(model, batch[1], epoch)
        if term is None:
            return loss
        model.log("train_cert_term", term.detach(), on_epoch=True, on_step=False, batch_size=len(batch[1]))
        model.log("train_cert_eps", self.last["eps_mean"], on_epoch=True, on_step=False, batch_size=len(batch[1]))
        return loss + term
