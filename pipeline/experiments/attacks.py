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
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.experiments.context import Context, Results, wilson
from pipeline.experiments.scenario import Scenario, _agent_rows
from pipeline.render import load_occlusion
from pipeline.sim import starts


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

    attack: str = "pixel_attack"
    map: str = "clean"
    occlusion: str | None = None   # the scene's clouds under a pixel attack (null: clean images)
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    gated: list[str] = field(default_factory=lambda: ["hybrid"])  # also run with the gated loop
    gate: float | None = None      # world units; null: the map's own clean-image gate (docs/train.md)
    n_agents: int = 100
    band: float = 0.5              # starts (and "near K" frames) within this distance of the line behind the obstacle
    a_range: list[float] = field(default_factory=lambda: [-35.0, -15.0])
    horizon: float | None = None   # seconds; null: sim.horizon
    record: str | None = None      # the budget whose runs are recorded (trajectories, chosen clouds): the animation

    budget_key: ClassVar[str] = "kappa"

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return (self.map,)

    def budgets(self) -> list:  # pragma: no cover - interface
        raise NotImplementedError

    def validate(self) -> None:
        super().validate()
        if not self.band > 0:
            raise ConfigError("experiment.band", f"must be > 0, got {self.band}")
        if self.horizon is not None and not self.horizon > 0:
            raise ConfigError("experiment.horizon", f"must be > 0 (or null: sim.horizon), got {self.horizon}")
        if self.gate is not None and not self.gate > 0:
            raise ConfigError("experiment.gate", f"must be > 0 (world units) or null, got {self.gate}")
        if not self.budgets():
            raise ConfigError(f"experiment.{self.budget_key}s", "needs at least one budget")
        unknown = sorted(set(self.gated) - set(self.controllers))
        if unknown:
            raise ConfigError("experiment.gated", f"{unknown} are not among the controllers {self.controllers}")

    def uses(self):
        levels = [self.occlusion] if self.occlusion else []
        if self.budget_key == "level":
            levels += list(self.budgets())
        return {"controllers": list(self.controllers), "disturbances": [self.attack],
                "occlusions": sorted(set(levels))}

    def check(self, ctx: Context) -> None:
        if self.budget_key == "level":
            for level in self.budgets():
                load_occlusion(level, ctx.cfg.occlusions, field="experiment.levels")
        super().check(ctx)
        for b in self.budgets():
            att = ctx.attack(self.attack, **{self.budget_key: b})
            if att.budget_key != self.budget_key:
                raise ConfigError("experiment.attack", f"{self.attack!r} is swept by {att.budget_key}, this "
                                                       f"experiment sweeps {self.budget_key}")

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
        for budget in self.budgets():
            att = ctx.attack(self.attack, **{self.budget_key: budget})
            rec = self.record is not None and str(budget) == str(self.record)
            for ctrl, gated in runs:
                measure = ctx.camera_measure(self.map, self.occlusion, attack=att, gate=gate if gated else None,
                                             flag_gate=gate, keep_clouds=rec)
                res = ctx.simulate(ctx.controller(ctrl), x0, measure=measure, record=rec, record_every=every,
                                   horizon=self.horizon)
                frames = measure.table()
                label = {"budget": budget, "attack": att.label(), "controller": ctrl, "gated": gated}
                rows.append(self.row(ctx, res, frames, **label))
                agents.append(_agent_rows(res, **label))
                if rec and not gated:
                    arrays |= {f"rec_{ctrl}_p": res.p, f"rec_{ctrl}_m": res.m, f"rec_{ctrl}_t": res.t,
                               f"rec_{ctrl}_rows": frames[["frame", "agent"]].to_numpy(),
                               f"rec_{ctrl}_clouds": (np.concatenate(measure.clouds) if measure.clouds
                                                      else np.zeros((0, 4), np.int64))}
        info = {"gate": gate, "notes": notes, "budget_key": self.budget_key, "record": self.record,
                "horizon": self.horizon or ctx.horizon, "map": self.map, "attack": self.attack}
        return Results({"summary": pd.DataFrame(rows), "metrics": pd.concat(agents, ignore_index=True)}, arrays, info)


@dataclass(kw_only=True)
class CameraAttack(_AttackSweep):
    """The pixel attack (`disturbances.pixel_attack`) on the clean map, its budget `kappa` (intensity levels) swept."""

    figures: ClassVar[str] = "pipeline.experiments.attack_figures:draw_camera_attack"
    kappas: list[float] = field(default_factory=lambda: [0.0, 2.0, 4.0, 8.0])

    def budgets(self) -> list:
        return list(self.kappas)

    def validate(self) -> None:
        if any(not 0 <= k <= 255 for k in self.kappas):
            raise ConfigError("experiment.kappas", f"must be intensity levels in [0, 255], got {self.kappas}")
        super().validate()


@dataclass(kw_only=True)
class WorstCloudAttack(_AttackSweep):
    """The worst cloud (`disturbances.worst_cloud`) on the occluded map, its budget (the cloud level) swept; the
    runs at `record` are kept for the animation (a smooth controller stalled beside the hybrid passing)."""

    figures: ClassVar[str] = "pipeline.experiments.attack_figures:draw_worst_cloud"
    budget_key: ClassVar[str] = "level"
    attack: str = "worst_cloud"
    map: str = "occluded"
    levels: list[str] = field(default_factory=lambda: ["light", "medium", "heavy"])
    record: str | None = "heavy"

    def budgets(self) -> list:
        return list(self.levels)

    def validate(self) -> None:
        super().validate()
        if self.record is not None and self.record not in self.levels:
            raise ConfigError("experiment.record", f"must be one of the levels {self.levels} (or null), got {self.record!r}")
        if self.occlusion is not None:
            raise ConfigError("experiment.occlusion", "the worst cloud draws its own clouds: leave it null")
