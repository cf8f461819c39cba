"""A pose map's heading (SPEC §2, §3.7): `(cos θ, sin θ)` read from the convolutional features, `θ = atan2`.

Where the vehicle is changes from image to image, its marker does not: the heading is a property of a small
oriented triangle wherever it lies. `heading_head: pooled` (the default) reads it with the same weights at every
place: the last block's feature map is max-pooled over the image (each channel's strongest response, the marker's
where the channel detects a marker feature) and a small MLP maps the pooled channels to `(cos θ, sin θ)`.
`heading_head: attention` (with `position_head: keypoint`) reads the last block's features before its pooling,
averaged with the keypoint's attention weights: the features at the marker, wherever it lies.
`heading_head: flat` appends the two outputs to the position's linear head on the flattened features, which must
then learn the heading at every one of the feature map's cells separately (with 12 000 images and 3 epochs it
learned nothing: 88° mean error, the error of a guess).

The loss on `(cos θ, sin θ)` is the model's loss (MSE by default) on the unit vector: smooth, with no
wrap-around at ±π, and `heading_weight` times the position's (whose targets are normalised to [-1, 1]).
"""

from __future__ import annotations

import torch
from torch import nn


class HeadingHead(nn.Module):
    """`(N, C, h, w)` features -> `(N, 2)` = `(cos θ, sin θ)` (unnormalised): global max pool, then an MLP."""

    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 2))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        return self.mlp(f.amax(dim=(2, 3)))


class AttentionHeadingHead(nn.Module):
    """`(N, C, h, w)` features and attention weights `(N, 1, h, w)` (summing to 1 over the grid) -> `(N, 2)` =
    `(cos θ, sin θ)` (unnormalised): the attention-weighted mean feature, then an MLP."""

    def __init__(self, channels: int, hidden: int):
        super().__init__()
        self.mlp = nn.Sequential(nn.Linear(channels, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, 2))

    def forward(self, g: torch.Tensor, attention: torch.Tensor) -> torch.Tensor:
        return self.mlp((g * attention).sum(dim=(2, 3)))


def heading_deg(pred: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean wrapped angle (degrees) between predicted and target `(cos, sin)` pairs `(N, 2)`."""
    cross = pred[:, 1] * target[:, 0] - pred[:, 0] * target[:, 1]
    dot = (pred * target).sum(1)
    return torch.rad2deg(torch.atan2(cross, dot).abs()).mean()
