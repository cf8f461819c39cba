"""The experiments stage's own settings (the root keys of conf/experiments.yaml), typed."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from pipeline.schema import Device, Positive, checked


@checked("")
@dataclass(frozen=True)
class ExperimentSettings:
    """`perception`: the camera and a learned map in the loop (`cnn`) or a perfect map (`oracle`); `maps` and
    `errormaps`: the inputs by reference (names, ids); `device` where maps run; `scale` multiplies every agent count
    (and coarsens grids below 1); `force` recomputes cached results; `publish` where figures go (false: the side
    folder | true: the paper folder | auto; docs/experiments.md)."""

    perception: Literal["cnn", "oracle"] = "cnn"
    maps: dict[str, str] = field(default_factory=lambda: {"clean": "clean_keypoint", "occluded": "occluded_keypoint",
                                                          "authors": "authors", "clean_paper": "clean_paper",
                                                          "field_heavy": "field_heavy_keypoint",
                                                          "unicycle_pose": "unicycle_pose",
                                                          "unicycle_field_pose": "unicycle_field_pose",
                                                          "dense_case6": "dense_case6_keypoint"})
    errormaps: dict[str, str | None] = field(default_factory=lambda: {"clean": None, "unicycle_pose": None,
                                                                      "unicycle_field_pose": None})
    device: Device = "auto"
    scale: Positive = 1.0
    force: bool = False
    publish: Literal["auto"] | bool = False
