"""The perception map as deployed, in the form the bounds read (SPEC §5.2).

:func:`deployed` rewrites a position map (`PerceptionNet`, eval-mode semantics) with the folding of the inference
network `pipeline.perception.network.FoldedPerceptionNet`, :func:`pipeline.perception.network.fold` (BatchNorm folded
into the convolutions with its running statistics, the input scaling `x / 255 - 0.5` and the CoordConv channels
folded into the first convolution's weights and a per-pixel bias map, dropout dropped), but **without detaching**:
every tensor is a differentiable function of the model's parameters, so a training loss can backpropagate through a
bound.

:func:`static_pass` is the nominal forward pass on the camera's static image (background, obstacle, target: no
robot), optionally as intervals under a pixel budget `kappa` (every pixel `±kappa` levels, clipped to
`[0, 255]`): every activation outside the robot's cone equals (lies within) these maps.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import nn
from torch.nn import functional as F

from pipeline.errors import ConfigError
from pipeline.perception.heading import AttentionHeadingHead
from pipeline.perception.network import fold


@dataclass
class Deployed:
    """The deployed position map: conv blocks, the linear head and `_to_world`'s scaling.

    - `weights[k]`, `biases[k]`: block `k`'s folded 3x3 convolution (padding 1); `biases[0]` is the first
      block's per-pixel bias map `(C, H, W)` (input scaling and CoordConv folded in), the others `(C,)`;
      `weights[0]` reads images in `[0, 255]`;
    - `head_w (2, C, h, w)`, `head_b (2,)`: the flat head on the last block's pooled features;
    - world position `= clamp(z, -1, 1) * half_range + center` (`clamp` as the model's eval mode).
    """

    weights: list[torch.Tensor]
    biases: list[torch.Tensor]
    head_w: torch.Tensor
    head_b: torch.Tensor
    center: torch.Tensor
    half_range: torch.Tensor
    clamp: bool
    grids: list[tuple[int, int]]  # each block's input grid (H_k, W_k); grids[-1]: the pooled features' grid
    # the keypoint head (`position_head: keypoint`) instead of the flat one: its 1x1 convolution's weight `(3, C)`
    # and bias `(3,)` (score, dx, dy), the cells' centres `cx (w,)`, `cy (h,)` and size `(sx, -sy)`, normalised
    keypoint: tuple[torch.Tensor, ...] | None = None
    # a pose map's attention heading head (`heading_head: attention`): its MLP `(W1, b1, W2, b2)` on the
    # attention-weighted mean of the same ReLU map, giving `(cos θ, sin θ)`
    heading: tuple[torch.Tensor, ...] | None = None

    @property
    def levels(self) -> int:
        return len(self.weights)


def deployed(model, dtype: torch.dtype = torch.float32) -> Deployed:
    """The map `model` (a `PerceptionNet`: a flat head without a hidden layer, or the keypoint head; a pose map
    with the attention heading head) as :class:`Deployed`.

    Differentiable in the model's parameters; BatchNorm uses its running statistics (eval mode) whatever
    `model.training` is. Raises `ConfigError` for the parts the bounds do not cover (another heading head, a
    hidden layer)."""
    keypoint = bool(getattr(model, "keypoint", False))
    heading = None
    if getattr(model, "pose", False):
        if not keypoint or not isinstance(model.heading_head, AttentionHeadingHead):
            raise ConfigError("certify.maps", "the certified bound covers pose maps with the keypoint head and the "
                                              "attention heading head (model=pose)")
        lin = [m for m in model.heading_head.mlp if isinstance(m, nn.Linear)]
        heading = tuple(t.to(dtype) for t in (lin[0].weight, lin[0].bias, lin[1].weight, lin[1].bias))
    lin = [] if keypoint else [m for m in model.head if isinstance(m, nn.Linear)]
    if not keypoint and len(lin) != 1:
        raise ConfigError("certify.maps", "the certified bound covers a flat head without a hidden layer "
                                          "(model.hidden=0)")
    weights, biases = fold(model, dtype, grad=True)
    h, w, _ = model.image_shape
    grids = [(h, w)]
    for _ in weights:
        grids.append((grids[-1][0] // 2, grids[-1][1] // 2))
    c_last = weights[-1].shape[0]
    cast = lambda t: t.to(dtype)  # noqa: E731
    kp = None
    if keypoint:
        head = model.head
        if tuple(head.grid) != grids[-2]:
            raise ConfigError("certify.maps", f"the keypoint head's grid {tuple(head.grid)} is not the last block's "
                                              f"{grids[-2]}")
        head_w, head_b = head.score.weight[:, :, 0, 0], head.score.bias
        kp = (cast(head_w), cast(head_b), cast(head.cx.flatten()), cast(head.cy.flatten()), cast(head.cell.flatten()))
    else:
        head_w, head_b = lin[0].weight.reshape(lin[0].out_features, c_last, *grids[-1]), lin[0].bias
    return Deployed(weights, biases, cast(head_w), cast(head_b), cast(model.center), cast(model.half_range),
                    bool(model.clamp), grids, kp, heading)


def _conv_interval(lo, hi, w, b, level0: bool):
    mid, rad = (lo + hi) / 2, (hi - lo) / 2
    c = F.conv2d(mid, w, padding=1)
    r = F.conv2d(rad, w.abs(), padding=1)
    bias = b[None] if level0 else b.view(1, -1, 1, 1)
    return c - r + bias, c + r + bias


@dataclass
class Static:
    """The static image's activations (intervals under `kappa`; `lo is hi` when `kappa == 0`).

    `inputs[k]`: block `k`'s input `(C, H_k, W_k)` (the image in `[0, 255]` for `k = 0`, else the previous
    block's pooled output); `post[k]`: block `k`'s ReLU output before its pooling; `features`: the last pooled map.
    """

    inputs_lo: list[torch.Tensor]
    inputs_hi: list[torch.Tensor]
    post_lo: list[torch.Tensor]
    post_hi: list[torch.Tensor]


def static_pass(net: Deployed, background: torch.Tensor, kappa: float = 0.0) -> Static:
    """The nominal pass on `background` (`(H, W, 3)` uint8 or float in `[0, 255]`); with `kappa > 0` an
    interval pass over every image within `kappa` levels of it (clipped to `[0, 255]`)."""
    x = background.to(net.head_w.dtype).permute(2, 0, 1)[None]
    lo, hi = (x - kappa).clamp(0, 255), (x + kappa).clamp(0, 255)
    in_lo, in_hi, post_lo, post_hi = [], [], [], []
    for k, (w, b) in enumerate(zip(net.weights, net.biases)):
        in_lo.append(lo[0])
        in_hi.append(hi[0])
        if kappa == 0:
            y = F.conv2d(lo, w, padding=1) + (b[None] if k == 0 else b.view(1, -1, 1, 1))
            lo = hi = F.relu(y)
        else:
            lo, hi = (F.relu(t) for t in _conv_interval(lo, hi, w, b, k == 0))
        post_lo.append(lo[0])
        post_hi.append(hi[0])
        lo = F.max_pool2d(lo, 2)
        hi = lo if kappa == 0 else F.max_pool2d(hi, 2)
    in_lo.append(lo[0])
    in_hi.append(hi[0])
    return Static(in_lo, in_hi, post_lo, post_hi)
