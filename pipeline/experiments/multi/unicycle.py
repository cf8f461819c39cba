"""The unicycle (SPEC §3.7, the paper's Remark 1; issue 19): the hybrid controller steering the look-ahead point
around every disc inflated by `d`, on the composed scene (`unicycle`: the default scene; `unicycle_field`: the
field drawn valid for the inflated discs, conf/scene/field_unicycle.yaml).

Conditions, on the same starts (the paper's two and `n_agents` random starts with random headings, every look-ahead
point clear of every inflated diamond): the true state; the camera with the pose map trained on the scene, its
heading read from the image (`camera`); the same map's position with the heading from an onboard sensor, the true
heading plus noise (`imu`, the ablation); and the single integrator from the same starts (true state), the time
reference. Success and collision are judged on the axle point; `|ω|` saturation and the heading error are counted
per agent.
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import warnings
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np
import pandas as pd

from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.multi.fields import check_map_scene, summarise_field
from pipeline.experiments.results import Results, mean_ci
from pipeline.experiments.scenario import Points, Scenario, agent_rows
from pipeline.plants import SingleIntegrator
from pipeline.schema import NonNegative, PositiveInt
from pipeline.sim import starts

Condition = Literal["true_state", "camera", "imu"]
PAPER_STARTS = [[-12.0, 2.0], [-37.0, -17.0]]


@contextlib.contextmanager
def swapped(ctx: Context, **attrs):
    """The context with some attributes replaced inside the block (`vehicle=SingleIntegrator()`: the time
    reference; `camera_settings=...`: a heading source)."""
    saved = {k: getattr(ctx, k) for k in attrs}
    for k, v in attrs.items():
        setattr(ctx, k, v)
    try:
        yield ctx
    finally:
        for k, v in saved.items():
            setattr(ctx, k, v)


def unicycle_starts(ctx: Context, paper: list, n: int, seed: int, margin: float) -> np.ndarray:
    """The paper's starts and `n` random ones, outside every disc inflated by `2 d` (so the look-ahead point, `d`
    from the axle, starts outside every diamond of the steering scene)."""
    clear = ctx.scene.inflated(2.0 * ctx.vehicle.lookahead)
    pts = starts.Points(points=paper)(ctx.scene, "experiment.initial_conditions")
    return np.concatenate([pts, starts.Random(n=n, seed=seed, margin=margin)(clear, "experiment")])


def heading_error_deg(res) -> np.ndarray:
    """Per agent, the mean wrapped error of the measured heading along the recorded run (degrees): of the estimate
    the controller holds, the last frame's, so it includes the turn since that frame (about 1 degree on the true
    state at 20 Hz); the map's own error on clean images is its error map's (`info.errormap_heading_clean`)."""
    d = np.degrees(np.abs(np.angle(np.exp(1j * (res.heading_measured - res.heading)))))
    with warnings.catch_warnings():  # an agent without a finite frame: NaN
        warnings.simplefilter("ignore", RuntimeWarning)
        return np.nanmean(d, axis=0)


@dataclass(kw_only=True)
class UnicycleRuns(Scenario):
    """The unicycle on the composed scene under each condition of `conditions`, beside the single integrator;
    a GIF of one camera run beside its camera view (`gif: true`)."""

    figures: ClassVar[str] = "pipeline.experiments.multi.unicycle_figures:draw_unicycle"
    map_kind: str = "unicycle_pose"
    conditions: list[Condition] = field(default_factory=lambda: ["true_state", "camera", "imu"])
    initial_conditions: Points = field(default_factory=lambda: [list(p) for p in PAPER_STARTS])
    n_agents: PositiveInt = 200   # random starts and headings (vehicle.heading0, vehicle.heading_seed)
    margin: NonNegative = 2.0
    imu_noise: NonNegative = 0.05  # radians: the onboard sensor's heading noise (condition imu)
    n_drawn: PositiveInt = 8       # agents recorded for the figure (the paper's starts first)
    gif: bool = True
    gif_agent: int = 0             # which start the GIF follows (0: the paper's first)
    record_every: PositiveInt = 5
    DRAW_ONLY: ClassVar[tuple[str, ...]] = (*Scenario.DRAW_ONLY, "gif", "gif_agent")  # the GIF is drawn, not computed

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return (self.map_kind,) if {"camera", "imu"} & set(self.conditions) else ()

    @property
    def errormaps(self) -> tuple[str, ...]:
        """The pose map's error map: its heading error on clean images (checked before any work, in the key)."""
        return self.maps

    def check(self, ctx: Context) -> None:
        super().check(ctx)
        if not ctx.vehicle.heading:
            raise ConfigError("vehicle", f"this experiment runs the unicycle (vehicle=unicycle), got {ctx.vehicle.name}")
        ctx.controller("hybrid").check_loop(ctx.frame_period)  # V3 on the inflated discs, before any run
        if self.maps:
            check_map_scene(ctx, self.map_kind)
        if "camera" in self.conditions:  # whatever camera.heading says: this condition reads it from the map
            with swapped(ctx, camera_settings=dataclasses.replace(ctx.camera_settings, heading="camera")):
                ctx.check_heading(self.map_kind)

    def _measure(self, ctx: Context, cond: str):
        if cond == "true_state":
            return None
        measure = ctx.camera_measure(self.map_kind)
        if not dataclasses.is_dataclass(measure):  # a perfect map: the true state
            return measure
        heading = "camera" if cond == "camera" else "imu"
        return dataclasses.replace(measure, heading=heading, heading_noise=self.imu_noise if cond == "imu" else 0.0)

    def _rows(self, ctx: Context, res, cond: str, vehicle: str) -> pd.DataFrame:
        df = agent_rows(res, condition=cond, vehicle=vehicle, start=np.arange(len(res.x0)))
        period = ctx.frame_period or ctx.dt
        t_end = np.where(df["success"], df["time_to_target"], ctx.horizon)
        frames = np.maximum(np.ceil(t_end / period), 1.0)
        df["omega_saturation"] = df["saturated_frames"] / frames
        df["heading_error_deg"] = heading_error_deg(res) if res.heading is not None else np.nan
        return df

    def compute(self, ctx: Context) -> Results:
        self.check(ctx)
        x0 = unicycle_starts(ctx, self.initial_conditions, ctx.n(self.n_agents, minimum=4), ctx.seed, self.margin)
        ctrl = ctx.controller("hybrid")
        frames, arrays = [], {"x0": x0}
        for cond in self.conditions:
            res = ctx.simulate(ctrl, x0, measure=self._measure(ctx, cond), record_every=self.record_every)
            frames.append(self._rows(ctx, res, cond, "unicycle"))
            k = self.n_drawn
            arrays |= {f"t_{cond}": res.t, f"p_{cond}": res.p[:, :k], f"m_{cond}": res.m[:, :k],
                       f"th_{cond}": res.heading[:, :k], f"thm_{cond}": res.heading_measured[:, :k]}
            print(f"[experiments] {self.id}: {cond} done", flush=True)
        with swapped(ctx, vehicle=SingleIntegrator()):
            res = ctx.simulate(ctx.controller("hybrid"), x0, record_every=self.record_every)
        frames.append(self._rows(ctx, res, "true_state", "integrator"))
        arrays |= {"t_integrator": res.t, "p_integrator": res.p[:, : self.n_drawn]}
        metrics = pd.concat(frames, ignore_index=True)
        return Results({"metrics": metrics, "summary": self.summary(ctx, metrics)}, arrays, self.info(ctx))

    def summary(self, ctx: Context, metrics: pd.DataFrame) -> pd.DataFrame:
        """Per condition and vehicle: the Monte Carlo table, the `|ω|` saturation share, the heading error along
        the runs, and the time against the single integrator on the same starts (median of per-start ratios)."""
        by = ["condition", "vehicle"]
        table = summarise_field(metrics, by, ctx.seed)
        ref = metrics[metrics["vehicle"] == "integrator"].set_index("start")["time_to_target"]
        extra = []
        for _, g in metrics.groupby(by, sort=False):
            row = {}
            for k in ("omega_saturation", "heading_error_deg"):
                m, lo, hi = mean_ci(g[k].to_numpy(float))
                row |= {f"mean_{k}": m, f"mean_{k}_lo": lo, f"mean_{k}_hi": hi}
            ratio = (g.set_index("start")["time_to_target"] / ref).to_numpy(float)
            ratio = ratio[np.isfinite(ratio)]
            row["median_time_ratio"] = float(np.median(ratio)) if len(ratio) else math.nan
            paper = g[g["start"] < len(self.initial_conditions)]
            row["paper_starts_time"] = "; ".join(f"{t:.2f}" for t in paper["time_to_target"])
            extra.append(row)
        return pd.concat([table, pd.DataFrame(extra)], axis=1)

    def info(self, ctx: Context) -> dict:
        out = {"scene": ctx.scene.name, "lookahead": ctx.vehicle.lookahead, "omega_max": ctx.vehicle.omega_max,
               "n_paper_starts": len(self.initial_conditions), "imu_noise_deg": math.degrees(self.imu_noise)}
        if self.maps:
            s = ctx.error_map(self.map_kind)
            if s is not None:  # the map's heading error on clean images, over the arena and the heading grid
                out["errormap"] = s["path"].name
                out["errormap_heading_clean"] = s["levels"]["none"].get("heading")
                out["errormap_position_clean"] = {k: s["levels"]["none"][k] for k in ("mean", "p95", "max")}
        return out


__all__ = ["UnicycleRuns", "heading_error_deg", "swapped", "unicycle_starts"]
