"""The typed spec of a perception map (`conf/model/`): what :class:`pipeline.perception.network.PerceptionNet` is
built from. No torch here, so a config's `model` node is imported, checked and built in the preflight like every
other node; the network takes the built spec (`PerceptionNet(spec)`, or `PerceptionNet.of(**fields)` from Python;
the training's `pipeline.train.module.PerceptionMap` alike).

The defaults are conf/model/default.yaml's (the project's map); conf/model/paper.yaml is the paper's. Four variants
share it: the flat or the keypoint position head, a position or a pose map (with its heading head), and the
Gaussian uncertainty head or none; the cross-field rules between them are :meth:`MapSpec.__post_init__`'s.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from pipeline.errors import ConfigError
from pipeline.schema import (
    Interval,
    Name,
    NonEmpty,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    Range,
    checked,
)


@checked("model")
@dataclass(frozen=True)
class MapSpec:
    """A perception map: image and arena (set by the train stage from the dataset), the trunk (`filters`,
    `batch_norm`, `coord_channels`), the position head (`position_head`; `hidden`, `dropout` for the flat one), the
    fit (`lr`, `weight_decay`, `schedule`, `loss`), the uncertainty head (`uncertainty_*`) and a pose map's heading
    head (`outputs: pose`, `heading_*`). conf/model/default.yaml documents each key."""

    image_shape: tuple[PositiveInt, PositiveInt, Literal[3]] = (60, 100, 3)
    arena: tuple[Interval, Interval] = ((-50.0, 50.0), (-30.0, 30.0))
    filters: Annotated[Sequence[int], Range(ge=1), NonEmpty()] = (16, 32, 64)
    batch_norm: bool = True
    hidden: NonNegativeInt = 0
    dropout: Annotated[float, Range(ge=0, lt=1)] = 0.1
    lr: Positive = 2e-3
    weight_decay: NonNegative = 0.0
    schedule: Literal["constant", "cosine", "onecycle"] = "onecycle"
    loss: Literal["mse", "l1", "smooth_l1"] = "mse"
    coord_channels: bool = True
    clamp: bool = True
    name: Name = "default"
    uncertainty: Literal["none", "gaussian"] = "gaussian"
    uncertainty_epochs: PositiveInt = 10
    uncertainty_lr: Positive = 2e-3
    uncertainty_batch_size: PositiveInt = 128
    uncertainty_thumbnail: PositiveInt = 4
    outputs: Literal["position", "pose"] = "position"
    position_head: Literal["flat", "keypoint"] = "flat"
    heading_head: Literal["pooled", "flat", "attention"] = "pooled"
    heading_hidden: PositiveInt = 64
    heading_weight: Positive = 1.0

    def __post_init__(self):
        """The variant's cross-field rules: a thumbnail cell that fits the image, blocks that do not pool the image
        away, the attention heading head with the keypoint position head (pooled or flat with flat)."""
        h, w = (int(s) for s in self.image_shape[:2])
        if self.uncertainty_thumbnail > min(h, w):
            raise ConfigError("model.uncertainty_thumbnail", f"must be <= {min(h, w)} (pixels per side of a "
                                                             f"thumbnail cell), got {self.uncertainty_thumbnail!r}")
        if h >> len(self.filters) < 1 or w >> len(self.filters) < 1:
            raise ConfigError("model.filters", f"{len(self.filters)} pooling blocks shrink a {h}x{w} image to "
                                               "nothing")
        if self.outputs == "pose" and (self.heading_head == "attention") != (self.position_head == "keypoint"):
            raise ConfigError("model.heading_head", f"{self.heading_head!r} with position_head="
                                                    f"{self.position_head!r}: the attention head reads the "
                                                    "keypoint's weights (attention with keypoint; pooled or flat "
                                                    "with flat)")
