"""Proposition 1 through the camera (issue 20; docs/attacks.md): starts near the set K behind the obstacle, the
camera and a learned perception map in the loop, and an adversary acting on the image (the camera attacks of
`pipeline.perception.adversary`, composed under `disturbances.`), its budget swept.

- :class:`CameraAttack` (`experiment=camera_attack`): the pixel attack (PGD, `|delta|_inf <= kappa` intensity
  levels) on the clean map, `kappa` swept;
- :class:`WorstCloudAttack` (`experiment=worst_cloud`): the worst of `candidates` cloud layouts of a level, on the
  occluded map, the level swept; with the animation of a smooth controller and the hybrid one under the worst
  cloud.

Per budget and controller: success, stall and collision rates with 95% Wilson intervals, the estimate error the
attack induced (along `-sign(b(p)) e_b` and in norm) near K, on the first frame (the starts: the static attack on
their images) and over the run; the uncertainty head's flag rate on the attacked frames (at the map's own
clean-image gate), and the gated loop (`camera.gate`: flagged frames held) under the same attack.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, ClassVar, Literal

import numpy as np
import pandas as pd

from pipeline.experiments.context import Context
from pipeline.experiments.results import Results
from pipeline.experiments.scenario import Scenario, agent_rows
from pipeline.render import load_occlusion
from pipeline.schema import Interval, NonEmpty, Option, Positive, PositiveInt, Range
from pipeline.sim import starts
from pipeline.sim.metrics import wilson

Controller = Annotated[str, Option("controller")]  # hybrid, smooth, cbf


def near_k(scene, p: np.ndarray, band: float) -> np.ndarray:
    """Rows of `p` near K: behind the obstacle's diamond (`a < -c`) within `band` of the line `b = 0`."""
    a, b = scene.to_frame(np.asarray(p, dtype=float).reshape(-1, 2))
    return (np.asarray(a) < -scene.c) & (np.abs(np.asarray(b)) < band)


def _rate(mask, n: int, key: str) -> dict:
    k = int(np.sum(mask))
    lo, hi = wilson(k, n)
    return {f"{key}_rate": k / n if n else np.nan, f"{key}_lo": float(lo), f"{key}_hi": float(hi)}


def _mean(x) -> float:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    return float(x.mean()) if len(x) else np.nan


@dataclass(kw_only=True)
class _AttackSweep(Scenario):
    """What both attack scenarios share: the starts, the sweep, the rows of the table."""

    map: str = "clean"
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    gated: list[Controller] = field(default_factory=lambda: ["hybrid"])  # also run with the gated loop
    gate: Positive | None = None   # world units; null: the map's own clean-image gate (docs/train.md)
    n_agents: PositiveInt = 100
    band: Positive = 0.5           # starts (and "near K" frames) within this distance of the line behind the obstacle
    a_range: Interval = field(default_factory=lambda: [-35.0, -15.0])
    horizon: Positive | None = None  # seconds; null: sim.horizon
    record: bool = False           # record the runs at the last budget (trajectories, chosen clouds): the animation

    budget_key: ClassVar[str] = "kappa"

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return (self.map,)

    def budgets(self) -> list:  # pragma: no cover - interface
        raise NotImplementedError

    def scene_clouds(self) -> str | None:
        """The cloud level of the scene itself under the attack (None: clean images)."""
        return None

    def uses(self):
        levels = [self.scene_clouds()] if self.scene_clouds() else []
        if self.budget_key == "level":
            levels += list(self.budgets())
        return {"controllers": sorted(set(self.controllers) | set(self.gated)), "disturbances": [self.attack],
                "occlusions": sorted(set(levels))}

    def check(self, ctx: Context) -> None:
        if self.budget_key == "level":
            for level in self.budgets():
                load_occlusion(level, ctx.cfg.occlusions, field="experiment.levels")
        super().check(ctx)
        for b in self.budgets():
            ctx.attack(self.attack, **{self.budget_key: b})

    def starts(self, ctx: Context) -> np.ndarray:
        return starts.NearK(n=ctx.n(self.n_agents), seed=ctx.seed, band=self.band, a_range=list(self.a_range))(ctx.scene)

    def row(self, ctx: Context, res, frames: pd.DataFrame, **labels) -> dict:
        m, n = res.metrics, len(res.metrics["success"])
        near = near_k(ctx.scene, frames[["x", "y"]].to_numpy(), self.band) if len(frames) else np.zeros(0, bool)
        first = frames["frame"].to_numpy() == 0
        row = {**labels, "n": n, **_rate(m["success"], n, "success"), **_rate(m["outcome"] == "stalled", n, "stalled"),
               **_rate(m["collision"], n, "collision"), "timed_out": float(np.mean(m["outcome"] == "timed_out")),
               "induced_along_near_K": _mean(frames["along"][near]), "induced_norm_near_K": _mean(frames["norm"][near]),
               "induced_along_start": _mean(frames["along"][first]), "induced_norm_start": _mean(frames["norm"][first]),
               "induced_norm_run": _mean(frames["norm"]), "frames_near_K": int(near.sum()),
               "attacked_images": len(frames)}
        if "stopped_frames" in m:  # dead reckoning (camera.predict): agents its fallback stopped at least once
            row["stopped_by_drift"] = int(np.sum(m["stopped_frames"] > 0))
        if "rejected_frames" in m:  # camera.innovation: agents with a frame rejected against their own motion
            row["rejected"] = int(np.sum(m["rejected_frames"] > 0))
        if frames["predicted_error"].notna().any():
            row |= {"flag_rate": float(frames["flagged"].mean()), "flag_rate_near_K": _mean(frames["flagged"][near]),
                    "gated_share": float(frames["gated"].mean())}
        return row

    def compute(self, ctx: Context) -> Results:
        x0 = self.starts(ctx)
        gate = self.gate if self.gate is not None else ctx.map_gate(self.map)
        notes = []
        runs = [(c, False) for c in self.controllers]
        if self.gated and gate is None:
            notes.append(f"map {self.map} has no uncertainty head (or a perfect map): no gated runs")
        elif self.gated:
            runs += [(c, True) for c in self.gated]
        every = max(1, round((ctx.frame_period or ctx.dt) / ctx.dt))
        rows, agents, arrays = [], [], {"x0": x0}
        budgets = self.budgets()
        ctx.expect(len(budgets) * len(runs))
        for budget in budgets:
            att = ctx.attack(self.attack, **{self.budget_key: budget})
            rec = self.record and budget == budgets[-1]
            for ctrl, gated in runs:
                ctx.label = f"{att.label()} {ctrl}{' gated' if gated else ''}"
                measure = ctx.camera_measure(self.map, self.scene_clouds(), attack=att, gate=gate if gated else None,
                                             flag_gate=gate, keep_clouds=rec)
                res = ctx.simulate(ctx.controller(ctrl), x0, measure=measure, record=rec, record_every=every,
                                   horizon=self.horizon, innovation=gated)
                frames = measure.table()
                label = {"budget": budget, "attack": att.label(), "controller": ctrl, "gated": gated}
                rows.append(self.row(ctx, res, frames, **label))
                agents.append(agent_rows(res, **label))
                if rec and not gated:
                    arrays |= {f"rec_{ctrl}_p": res.p, f"rec_{ctrl}_m": res.m, f"rec_{ctrl}_t": res.t,
                               f"rec_{ctrl}_rows": frames[["frame", "agent"]].to_numpy(),
                               f"rec_{ctrl}_clouds": (np.concatenate(measure.clouds) if measure.clouds
                                                      else np.zeros((0, 4), np.int64))}
        info = {"gate": gate, "notes": notes, "budget_key": self.budget_key,
                "record": budgets[-1] if self.record else None,
                "horizon": self.horizon or ctx.horizon, "map": self.map, "attack": self.attack}
        return Results({"summary": pd.DataFrame(rows), "metrics": pd.concat(agents, ignore_index=True)}, arrays, info)


@dataclass(kw_only=True)
class CameraAttack(_AttackSweep):
    """The pixel attack (`disturbances.pixel_attack`) on the clean map, its budget `kappa` (intensity levels) swept."""

    figures: ClassVar[str] = "pipeline.experiments.attacks.figures:draw_camera_attack"
    attack: Literal["pixel_attack"] = "pixel_attack"  # the camera attack of `disturbances` whose kappa is swept
    occlusion: str | None = None   # the scene's clouds under the attack (null: clean images)
    kappas: Annotated[list[float], Range(ge=0, le=255), NonEmpty()] = field(default_factory=lambda: [0.0, 2.0, 4.0, 8.0])

    def budgets(self) -> list:
        return list(self.kappas)

    def scene_clouds(self) -> str | None:
        return self.occlusion


@dataclass(kw_only=True)
class WorstCloudAttack(_AttackSweep):
    """The worst cloud (`disturbances.worst_cloud`) on the occluded map, its budget (the cloud level) swept; with
    `record`, the runs at the last level are kept for the animation (a smooth controller stalled beside the hybrid
    passing). The worst cloud draws its own clouds: the scene has none besides."""

    figures: ClassVar[str] = "pipeline.experiments.attacks.figures:draw_worst_cloud"
    budget_key: ClassVar[str] = "level"
    attack: Literal["worst_cloud"] = "worst_cloud"
    map: str = "occluded"
    levels: Annotated[list[str], NonEmpty(distinct=True)] = field(default_factory=lambda: ["light", "medium", "heavy"])
    record: bool = True

    def budgets(self) -> list:
        return list(self.levels)
