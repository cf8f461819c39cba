"""The keypoint position head (`model.position_head: keypoint`): where the vehicle is, read as a soft-argmax.

The paper's head flattens the last block's feature map and regresses the position with one linear layer: every
cell of the 7 x 12 feature grid has its own weights, so the map must learn "the vehicle is here, a fraction of a
pixel to the left" separately at each of the 84 cells, from the images that happen to put the vehicle there.

The keypoint head reads the last block's feature map *before* its pooling (15 x 25 cells of 4 px for the default
60 x 100 image) with one 1x1 convolution giving, per cell, a score and a sub-cell offset `(dx, dy)` (in cells).
A softmax over the grid turns the scores into attention weights `a` (summing to 1) and the position is the
attention-weighted mean of the cells' centres plus their offsets:

    p = sum_cells a_c (centre_c + offset_c),

in the arena's normalised coordinates (x right, y up, each in [-1, 1] over the image). The same weights read every
cell (translation-equivariant), so each image teaches the offset wherever the vehicle lies. Measured on this
2-core CPU with the same trunk and optimiser (docs/train.md): the `unicycle` pose map 0.17 px after 8000 images x
10 epochs (the flat head: 1.4 px after 6; the `clean` map's flat head needs 24k images x 10 epochs for 0.28 px);
`field_heavy` (heavy clouds on 90% of the images) 0.34 px after 12k x 10 (flat: 4.8 px after 6, 1.27 px with 48k).

The attention weights are returned too: a pose map's `heading_head: attention` averages the same feature map with
them (the features at the marker).
"""

from __future__ import annotations

import torch
from torch import nn


class KeypointHead(nn.Module):
    """`(N, C, h, w)` features -> (normalised position `(N, 2)`, attention `(N, 1, h, w)`).

    `grid` is the feature map's `(h, w)`; its cells tile the image (a cell spans the trunk's pooling factor in
    pixels; where the image size is not a multiple of it the cells are a fraction of a pixel larger, which the
    learned offsets absorb)."""

    def __init__(self, channels: int, grid: tuple[int, int]):
        super().__init__()
        h, w = (int(v) for v in grid)
        self.grid = (h, w)
        self.score = nn.Conv2d(channels, 3, 1)  # score, dx, dy (cells)
        # a cell's size in normalised units (the image spans 2 in each direction) and its centre; y points up
        sx, sy = 2.0 / w, 2.0 / h
        cx = (torch.arange(w, dtype=torch.float32) + 0.5) * sx - 1.0
        cy = 1.0 - (torch.arange(h, dtype=torch.float32) + 0.5) * sy
        self.register_buffer("cx", cx.view(1, 1, 1, w), persistent=False)
        self.register_buffer("cy", cy.view(1, 1, h, 1), persistent=False)
        self.register_buffer("cell", torch.tensor([sx, -sy]).view(1, 2, 1, 1), persistent=False)

    def forward(self, g: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        k = self.score(g)
        n, _, h, w = k.shape
        a = torch.softmax(k[:, 0].reshape(n, h * w), 1).view(n, 1, h, w)
        off = k[:, 1:3] * self.cell
        x = (a * (self.cx + off[:, :1])).sum(dim=(1, 2, 3))
        y = (a * (self.cy + off[:, 1:])).sum(dim=(1, 2, 3))
        return torch.stack([x, y], 1), a

    def flops(self) -> float:
        """Multiply-adds x2 per image of the 1x1 convolution and the weighted sums."""
        h, w = self.grid
        return 2.0 * h * w * (self.score.in_channels * 3 + 4)
