"""The scenarios' base (SPEC §4): a scenario is a dataclass with typed keyword arguments built from its experiment
bundle (`conf/experiment/<id>.yaml`, `_target_` + parameters; the signature is the schema, checked with the
config). It computes (`compute(ctx) -> Results`, cached) and names its drawing function (`figures`); `maps` names
the perception maps its results depend on and `uses()` the composed controllers, disturbances and cloud levels:
with the scenario's own parameters they make its cache key.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.experiments.context import Context, Results
from pipeline.sim import starts

Points = list[list[float]]


def _agent_rows(res, **cols) -> pd.DataFrame:
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


def _frame_index(t: np.ndarray, times) -> list[int]:
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
        self.validate()

    def validate(self) -> None:
        """Ranges of the scenario's parameters (ConfigError naming `experiment.<key>`)."""
        for name in ("n_agents", "n_agents_camera"):
            v = getattr(self, name, None)
            if v is not None and v < 1:
                raise ConfigError(f"experiment.{name}", f"must be >= 1, got {v}")
        for name in ("sigma", "p_fail", "eps", "min_band"):
            v = getattr(self, name, None)
            vals = v if isinstance(v, list) else [v]
            if v is not None and any(x < 0 for x in vals):
                raise ConfigError(f"experiment.{name}", f"must be >= 0, got {v}")
        if getattr(self, "p_fail", 0.0) >= 1:
            raise ConfigError("experiment.p_fail", f"must be in [0, 1), got {self.p_fail}")
        for name in ("grid_step", "grid_step_y"):
            v = getattr(self, name, None)
            if v is not None and not v > 0:
                raise ConfigError(f"experiment.{name}", f"must be > 0, got {v}")
        a_range = getattr(self, "a_range", None)
        if a_range is not None and not (len(a_range) == 2 and a_range[0] < a_range[1]):
            raise ConfigError("experiment.a_range", f"must be [min, max] with min < max, got {a_range}")
        tm = getattr(self, "time_model", "sampled")
        if tm not in ("sampled", "continuous"):
            raise ConfigError("experiment.time_model", f"must be sampled or continuous, got {tm!r}")
        ics = getattr(self, "initial_conditions", None)
        if ics is not None and not (ics and all(len(p) == 2 for p in ics)):
            raise ConfigError("experiment.initial_conditions", f"must be a non-empty list of [x, y], got {ics}")

    def uses(self) -> dict[str, list[str]]:
        """Names of the composed controllers, disturbances and cloud levels the computation reads."""
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": []}

    def check(self, ctx: Context) -> None:
        """Preflight: build what the computation will use (no simulation)."""
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
