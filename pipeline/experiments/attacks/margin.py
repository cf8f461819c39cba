"""Theorem 1's robustness margin over the geometry (issue 20; docs/attacks.md, "What sets the margin"): the
largest disturbance size ε the hybrid controller tolerates from starts near K, per cell of the covering's apex
`c / r` and the barrier's `ρ_b` and `ℓ_B`, with (χ, λ) at the paper's values. The bisection on ε is
`HysteresisMargin`'s (imported: same starts, same success criterion, same bracket); only the scene changes from
cell to cell. A cell whose scene or controller is not valid (V1: the target outside the wedges by more than the
barrier's reach; the starts outside the diamond) is skipped with a note naming the reason.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, ClassVar

import numpy as np
import pandas as pd

from pipeline.config import build
from pipeline.control import in_diamond
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.paper.theory import HysteresisMargin
from pipeline.experiments.results import Results
from pipeline.schema import NonEmpty, Range

SQRT2 = 1.4142135623730951


def cell_scene(scene_cfg: dict, *, apex_ratio: float, rho: float, scale: float):
    """The composed scene with obstacle 0's apex `c = apex_ratio * r`, the barrier's `rho` and obstacle 0's
    barrier scale `ℓ_B = scale` (the rest as composed); raises the scene's ConfigError when not valid."""
    node = {**scene_cfg, "barrier": {**scene_cfg["barrier"], "rho": float(rho)}}
    obstacles = [dict(o) for o in scene_cfg["obstacles"]]
    obstacles[0] |= {"apex": float(apex_ratio) * float(obstacles[0]["radius"]), "barrier_scale": float(scale)}
    node["obstacles"] = obstacles
    return build(node, "scene")


@dataclass(kw_only=True)
class GeometryMargin(HysteresisMargin):
    """The margin map of `HysteresisMargin` over (c / r, ρ_b, ℓ_B) at `chi` x `lam` (default: the paper's cell)."""

    figures: ClassVar[str] = "pipeline.experiments.attacks.figures:draw_geometry_margin"

    chi: list[float] = field(default_factory=lambda: [1.1])
    lam: list[float] = field(default_factory=lambda: [0.09])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial"])
    # c / r (paper: 2 sqrt 2); the diamond must contain the disc: c / r > sqrt 2
    apex_ratio: Annotated[list[float], Range(gt=SQRT2), NonEmpty()] = field(default_factory=lambda: [2.0, 2.5, 2.83, 3.5])
    rho: Annotated[list[float], Range(gt=0, le=1), NonEmpty()] = field(default_factory=lambda: [0.1, 0.5, 1.0])  # ρ_b
    barrier_scale: Annotated[list[float], Range(gt=0), NonEmpty()] = field(default_factory=lambda: [2.0, 4.0, 8.0])  # ℓ_B
    a_range: list[float] = field(default_factory=lambda: [-45.0, -20.0])
    time_model: str = "sampled"

    def geometry(self) -> list[tuple[float, float, float]]:
        return [(c, r, s) for c in self.apex_ratio for r in self.rho for s in self.barrier_scale]

    def cell(self, ctx: Context, x0, apex_ratio: float, rho: float, scale: float):
        """(scene, its hybrid controller, None) or (None, None, the reason the cell is skipped)."""
        try:
            scene = cell_scene(ctx.scene_cfg, apex_ratio=apex_ratio, rho=rho, scale=scale)
            hybrid = ctx.controller("hybrid", scene=scene)
            for chi, lam in self.cells():
                hybrid.with_hysteresis(chi, lam)
        except ConfigError as err:
            return None, None, str(err)
        inside = int(in_diamond(scene, x0).sum())
        if inside:
            return None, None, f"{inside} starts inside the diamond (c = {scene.c:.3g}): a_range must end below -c"
        return scene, hybrid, None

    def compute(self, ctx: Context) -> Results:
        x0 = self.starts(ctx)
        rows = []
        ctx.expect(len(self.geometry()) * len(self.disturbances) * len(self.cells()) * self.steps())
        for apex_ratio, rho, scale in self.geometry():
            scene, hybrid, note = self.cell(ctx, x0, apex_ratio, rho, scale)
            base = {"apex_ratio": apex_ratio, "rho": rho, "barrier_scale": scale, "valid": scene is not None,
                    "note": note or ""}
            if scene is not None:
                cov = scene.covering(0)
                base |= {"c": cov.c, "barrier_reach": cov.barrier_reach, "influence_radius": cov.influence_radius}
            for dist in self.disturbances:
                ctx.label = f"c/r={apex_ratio:g} rho_b={rho:g} l_B={scale:g}"
                found = self.margins(ctx, x0, hybrid, dist, self.cells(), scene) if scene is not None else None
                for k, (chi, lam) in enumerate(self.cells()):
                    row = {"disturbance": dist, "chi": chi, "lam": lam, **base}
                    if found is None:
                        rows.append(row | {"eps_margin": np.nan, "eps_fails": np.nan, "simulations": 0})
                        ctx.advance(self.steps())
                        continue
                    lo, hi, sims = found[k]
                    ctx.advance(self.steps() - sims)  # a bisection that stopped early
                    rows.append(row | {"eps_margin": lo, "eps_fails": hi, "n_starts": len(x0), "simulations": sims})
        default = ctx.scene.covering(0)
        info = {"default": {"apex_ratio": default.c / default.obstacle_radius, "rho": default.barrier_rho,
                            "barrier_scale": default.ell}, "radius": default.obstacle_radius,
                "skipped": [r["note"] for r in rows if r["note"]]}
        return Results({"margin": pd.DataFrame(rows)}, {"x0": x0}, info)
