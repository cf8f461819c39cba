"""The scenarios' base (SPEC §4): a scenario is a dataclass with typed keyword arguments built from its experiment
bundle (`conf/experiment/<id>.yaml`, `_target_` + parameters; the signature is the schema: types, choices and
ranges, checked with the config and when the scenario is built, :func:`pipeline.schema.check_fields`). It computes (`compute(ctx) -> Results`, cached) and names its drawing function (`figures`); `maps` names
the perception maps its results depend on and `uses()` the composed controllers, disturbances and cloud levels:
with the scenario's own parameters they make its cache key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, ClassVar

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.results import Results
from pipeline.schema import NonEmpty, Pair, check_fields
from pipeline.sim import starts

Points = Annotated[list[Pair], NonEmpty()]  # initial conditions [[x, y], ...]


def agent_rows(res, **cols) -> pd.DataFrame:
    df = res.metrics_frame()
    for k, v in cols.items():
        df[k] = v
    return df


def practical_success(res, delta: float, eps: float) -> np.ndarray:
    """Per agent: reached the target up to the disturbance (strict success, or |p - p_T| <= delta + ε at the
    end) without a collision. Under a disturbance of size ε the closed loop is only practically stable: its
    equilibrium moves by up to ε, so `delta` alone would count a vehicle resting at p_T + ε as a failure."""
    m = res.metrics
    return (m["success"] | (m["final_error"] <= delta + eps + 1e-9)) & ~m["collision"]


def frame_index(t: np.ndarray, times) -> list[int]:
    return [int(min(np.searchsorted(t, s - 1e-9), len(t) - 1)) for s in times]


@dataclass(kw_only=True)
class Scenario:
    """Base: `id`, `title` and `paper` (what it reproduces) label the outputs; the rest is the computation."""

    id: str
    title: str
    paper: str = "–"
    maps: ClassVar[tuple[str, ...]] = ()
    DRAW_ONLY: ClassVar[tuple[str, ...]] = ("title", "paper")
    figures: ClassVar[str] = ""  # its drawing function, "module:function" (drawing code is no part of the cache key)

    def __post_init__(self):
        check_fields(self, "experiment")  # types, choices and ranges of the fields (also when built from Python)
        self.validate()

    def validate(self) -> None:
        """The cross-field rules of a scenario's parameters (ConfigError naming `experiment.<key>`)."""

    def uses(self) -> dict[str, list[str]]:
        """Names of the composed controllers, disturbances and cloud levels the computation reads."""
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": []}

    def time_models(self, ctx: Context) -> set[str]:
        """The time models the computation's runs use (`sim.model`, and a scenario's own `time_model`)."""
        return {ctx.sim.model, getattr(self, "time_model", ctx.sim.model)}

    def check(self, ctx: Context) -> None:
        """Preflight: build what the computation will use (no simulation)."""
        p_fail = ctx.camera_settings.p_fail
        if p_fail > 0 and "continuous" in self.time_models(ctx):
            raise ConfigError("camera.p_fail", f"does not apply to {self.id}: its continuous-time runs take no camera "
                                               f"failures, got {p_fail} (camera.p_fail=0, or a sampled time model)")
        for name in self.uses()["controllers"]:
            ctx.controller(name)
        for name in self.uses()["disturbances"]:
            ctx.disturbance(name)
        for level in self.uses()["occlusions"]:
            ctx.occlusion(level)
        ics = getattr(self, "initial_conditions", None)
        if ics is not None:
            starts.Points(points=ics)(ctx.scene, "experiment.initial_conditions")

    def compute(self, ctx: Context) -> Results:  # pragma: no cover - interface
        raise NotImplementedError
