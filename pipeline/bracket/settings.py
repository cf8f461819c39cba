"""`bracket`: the settings of the bracket stage (conf/bracket.yaml), typed and checked with the config."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, Literal

from pipeline.errors import ConfigError
from pipeline.schema import (
    Device,
    NonEmpty,
    NonNegative,
    NonNegativeInt,
    Positive,
    PositiveInt,
    Range,
    checked,
)

Law = Literal["hybrid", "smooth", "cbf"]
CameraAdversary = Literal["fixed", "mode_aware"]


@checked("bracket")
@dataclass(frozen=True)
class BracketSettings:
    """What the bracket computes (docs/bracket.md): the certificate at each uniform `eps` (and at the certified
    error map's `ε̄` when `error_map` names its cell table, or several of one perception map: the smallest bound
    per cell; a certify output's table at the pixel budget `error_map_kappa`; a clouds output's `eps_bar_delta`, or
    with `error_map_gated` its gated column, the flagged frames dropped: :mod:`pipeline.bracket.clouds`) on cells of
    side `cell` in a frame rotated by `angle` with edges over `frames` camera frames, and the falsifier from the centre of every start cell of side `start_cell`, bisecting `ε_hi` on
    `[0, eps_max]` in `n_bisect` steps (its adversaries: :mod:`pipeline.bracket.falsifier`; the ``trap`` one aimed at the
    back vertex with `trap_dirs` directions within `trap_reach` of it, aiming `trap_offset` outside it; with
    `error_map` also within the map's own `ε̄`, the failing scale of that bound bisected in `map_bisect` steps); success is
    reaching `B(p_T, goal_radius)` within `sim.horizon` seconds.
    With `camera_map` (a perception map: path, name-id, id or name), the falsifier through the camera too: `κ_hi`
    bisected on the integer levels `[0, kappa_max]`, `pgd_steps` PGD steps per frame towards the directions of
    `camera_adversaries`, on `camera_device` (:mod:`pipeline.bracket.camera_falsifier`). `lost_frames`: the most
    consecutive camera frames the proof lets be lost (`camera.p_fail`, `camera.gate`; held or, with
    `camera.predict`, dead-reckoned: :mod:`pipeline.bracket.lost`); 0: every frame arrives (the loop must lose none).
    `funnel_split`: sub-squares per side of a start cell the abstraction does not certify, each followed by a funnel
    through free space (:mod:`pipeline.bracket.funnel`); 0: the abstraction alone. `refine`: the half-width of a window
    around the back vertex where the abstraction runs on cells `refine_factor` times finer, edges over one frame
    (:mod:`pipeline.bracket.refine`); 0: off. `directional`: the window's arrival bounds also through sets of nodes
    along which a direction decreases (:func:`pipeline.bracket.winning.directional_frames`). `polytope_split`: a
    start sub-square's funnel that ends without a hand-off goes on as a polytope, its perceived sets cut into
    `polytope_split²` sub-boxes (:mod:`pipeline.bracket.polytope`); 0: off. `mode_split`: a start sub-square's
    initial modes decided on `mode_split²` sub-boxes of its perceived box (1: the whole box). `axis_start`: the
    uniform falsifier also from each start cell's point nearest `K` where that point is within this distance of `K`
    and nearer to it than the centre (the smaller `ε_hi` kept, its start in `hi_x, hi_y`); 0: off."""

    controllers: Annotated[list[Law], NonEmpty()] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    eps: Annotated[list[NonNegative], NonEmpty()] = field(default_factory=lambda: [0.1, 0.25, 0.5])
    error_map: str | Annotated[list[str], NonEmpty(distinct=True)] | None = None
    error_map_kappa: NonNegative = 0.0
    error_map_gated: bool = False
    cell: Positive = 0.75
    angle: float = 45.0
    n_split: PositiveInt = 4
    window: PositiveInt = 12
    frames: PositiveInt = 4
    goal_radius: Positive = 5.0
    start_cell: Positive = 5.0
    eps_max: Positive = 4.0
    n_bisect: NonNegativeInt = 4
    n_dirs: PositiveInt = 16
    lookahead: PositiveInt = 8
    commit: PositiveInt = 8
    tail: NonNegativeInt = 40
    n_random: NonNegativeInt = 4
    seed: NonNegativeInt = 0
    trap_dirs: PositiveInt = 64
    trap_reach: Positive = 3.0
    trap_offset: NonNegative = 0.2
    map_bisect: NonNegativeInt = 2
    formats: Annotated[list[str], NonEmpty()] = field(default_factory=lambda: ["png"])
    camera_map: str | None = None
    kappa_max: Annotated[int, Range(ge=1, le=255)] = 16
    pgd_steps: PositiveInt = 3
    camera_adversaries: Annotated[list[CameraAdversary], NonEmpty()] = field(
        default_factory=lambda: ["fixed", "mode_aware"])
    camera_device: Device = "cpu"
    lost_frames: NonNegativeInt = 0
    funnel_split: NonNegativeInt = 10
    refine: NonNegative = 10.0
    refine_factor: Annotated[int, Range(ge=2, le=64)] = 8
    directional: bool = True
    polytope_split: NonNegativeInt = 16
    mode_split: PositiveInt = 8
    axis_start: NonNegative = 0.0

    def __post_init__(self):
        if self.commit > self.lookahead:
            raise ConfigError("bracket.commit", f"must be <= bracket.lookahead = {self.lookahead}, got {self.commit}")
        if sorted(self.eps) != list(self.eps) or len(set(self.eps)) != len(self.eps):
            raise ConfigError("bracket.eps", f"must be increasing, got {list(self.eps)}")
        if len(set(self.controllers)) != len(self.controllers):
            raise ConfigError("bracket.controllers", f"names a controller twice: {list(self.controllers)}")
        if len(set(self.camera_adversaries)) != len(self.camera_adversaries):
            raise ConfigError("bracket.camera_adversaries", f"names an adversary twice: {list(self.camera_adversaries)}")
