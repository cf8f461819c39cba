"""The typed specs of the learned policies' torch code: the imitation network (`model` of conf/imitate.yaml), which
:class:`pipeline.learned.network.VelocityPolicy` takes (`VelocityPolicy(spec)`, or `VelocityPolicy.of(**fields)` from
Python), and PPO's settings (`ppo` of conf/ppo.yaml, :mod:`pipeline.learned.ppo`). No torch here, so the nodes are
imported, checked and built in the preflight like every other."""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated, Literal

from pipeline.schema import NonEmpty, NonNegativeInt, Positive, PositiveInt, Range, checked


@checked("model")
@dataclass(frozen=True)
class PolicySpec:
    """The map's trunk (`filters`, `batch_norm`, `coord_channels`; `freeze_trunk`: kept as the map learned it), what
    the velocity head reads (`reads`: the pooled features or the keypoint's position), its `hidden` units and
    `dropout`, the fit's `lr`, and `u_max` (the velocities' unit). `image_shape` is set by the stage."""

    image_shape: tuple[int, int, int] = (60, 100, 3)
    filters: Annotated[Sequence[int], Range(ge=1), NonEmpty()] = (16, 32, 64)
    batch_norm: bool = True
    coord_channels: bool = True
    hidden: PositiveInt = 128
    dropout: Annotated[float, Range(ge=0, lt=1)] = 0.1
    lr: Positive = 2e-3
    u_max: Positive = 10.0
    freeze_trunk: bool = False
    reads: Literal["features", "keypoint"] = "features"


@checked("ppo")
@dataclass(frozen=True)
class PPOSettings:
    """`ppo`: `num_envs` agents of the vector environment, `total_timesteps` agent-steps in all (the budget),
    PPO's `n_steps` per agent per rollout, `batch_size`, `n_epochs`, `learning_rate`, `seed`, torch `threads`."""

    num_envs: PositiveInt = 64
    total_timesteps: PositiveInt = 200_000
    n_steps: PositiveInt = 64
    batch_size: PositiveInt = 256
    n_epochs: PositiveInt = 4
    learning_rate: Positive = 3e-4
    seed: NonNegativeInt = 0
    threads: PositiveInt | None = None
