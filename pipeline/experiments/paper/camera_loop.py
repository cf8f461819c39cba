"""The camera-in-the-loop scenarios (SPEC §4): noise and failures, occlusion, the leader-follower level sets,
perception closeness, and the Monte Carlo table."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline.control import potential
from pipeline.experiments.context import Context
from pipeline.experiments.results import Results, summarise
from pipeline.experiments.scenario import Points, Scenario, agent_rows, frame_index
from pipeline.schema import NonNegative, Positive, PositiveInt
from pipeline.sim import starts
from pipeline.sim.settings import FailureRate


# ------------------------------------------------------------------------------ noise + failure
@dataclass(kw_only=True)
class NoiseFailure(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_noise_failure"
    sigma: NonNegative = 0.5
    p_fail: FailureRate = 0.5
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": ["gaussian"], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        ics = np.asarray(self.initial_conditions, float)
        noise = ctx.disturbance("gaussian", sigma=self.sigma)
        single = ctx.simulate(ctx.controller("hybrid"), ics, disturbance=noise, p_fail=self.p_fail,
                              measure=ctx.camera_measure("clean"))
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[1:2], kind="clean", sigma=self.sigma, p_fail=self.p_fail)
        rows = pd.concat([agent_rows(single, role="vehicle"), agent_rows(lead, role="leader"),
                          agent_rows(foll, role="follower")], ignore_index=True)
        arrays = {"single_p": single.p, "single_m": single.m, "lead_p": lead.p, "foll_p": foll.p,
                  "foll_target": foll.target, "lead_t": lead.t, "foll_t": foll.t}
        return Results({"metrics": rows}, arrays, {"sigma": self.sigma, "p_fail": self.p_fail})


# --------------------------------------------------------------------------------------- occlusion
@dataclass(kw_only=True)
class OccludedFollowers(Scenario):
    """The paper's occlusion figure: followers of a leader under `occlusion` clouds, with the clean and the
    occluded map (not the renderer's clouds, `pipeline.render.Occlusion`)."""

    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_occlusion"
    occlusion: str = "heavy"
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    n_agents: PositiveInt = 100   # followers from random initial conditions for the table
    delta_practical: NonNegative = 3.0  # success also within this distance of the target
    maps: ClassVar[tuple[str, ...]] = ("clean", "occluded")

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": [self.occlusion]}

    def starts(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Leaders (all at the first initial condition) and followers (random, the first at the last one)."""
        ics = np.asarray(self.initial_conditions, float)
        n_mc = ctx.n(self.n_agents)
        leaders = np.repeat(ics[:1], n_mc, 0)
        followers = starts.Random(n=n_mc, seed=ctx.seed, margin=3.0)(ctx.scene)
        followers[0] = ics[-1]
        return leaders, followers

    def follow(self, ctx: Context, kind: str, level: str | None, leaders, followers):
        """The followers with map `kind` on `level` clouds: per-agent rows (with the mean tracking error of the
        perceived leader), the leader and follower runs and the tracking errors (T, N)."""
        lead, foll, track = ctx.leader_follower(leaders, followers, kind=kind, level=level)
        err = np.hypot(*(foll.target - track.position(foll.t)).transpose(2, 0, 1))
        df = agent_rows(foll, map=kind, occlusion=level)
        df["tracking_error_mean"] = np.nanmean(err, axis=0)
        return df, lead, foll, err

    @staticmethod
    def summary(metrics: pd.DataFrame, by: list[str], seed: int, delta_practical: float) -> pd.DataFrame:
        table = summarise(metrics, by, seed=seed, delta_practical=delta_practical)
        g = metrics.groupby(by, sort=False)
        table["tracking_error_mean"] = g["tracking_error_mean"].mean().to_numpy()
        # the follower stops next to a leader it only sees through clouds: how close it gets matters more
        # than the strict |p - p_T| <= delta success
        table["final_error_median"] = g["final_error"].median().to_numpy()
        table["within_3_units"] = g["final_error"].apply(lambda e: float((e <= 3.0).mean())).to_numpy()
        return table

    def compute(self, ctx: Context) -> Results:
        level = self.occlusion
        leaders, followers = self.starts(ctx)
        rows, arrays = [], {}
        for kind in ("clean", "occluded"):
            df, lead, foll, err = self.follow(ctx, kind, level, leaders, followers)
            rows.append(df)
            arrays[f"{kind}_foll_p"] = foll.p[:, 0]
            arrays[f"{kind}_foll_target"] = foll.target[:, 0]
            arrays[f"{kind}_lead_p"] = lead.p[:, 0]
            arrays[f"{kind}_err"] = err[:, 0]
        metrics = pd.concat(rows, ignore_index=True)
        table = self.summary(metrics, ["map", "occlusion"], ctx.seed, self.delta_practical)
        return Results({"metrics": metrics, "summary": table}, arrays, {"level": level})


# --------------------------------------------------------------------------------- leader-follower
@dataclass(kw_only=True)
class LeaderFollower(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_leader_follower"
    instants: list[int] = field(default_factory=lambda: [1, 90, 180])   # camera frames
    sigma: NonNegative = 0.0
    grid_step: Positive = 0.5
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": ["gaussian"] if self.sigma > 0 else [], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        ics = np.asarray(self.initial_conditions, float)
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[-1:], kind="clean", sigma=self.sigma)
        frames = list(self.instants)
        period = ctx.frame_period or ctx.dt
        idx = frame_index(foll.t, [f * period for f in frames])
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0, x1 + 1e-9, self.grid_step), np.arange(y0, y1 + 1e-9, self.grid_step)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        arrays = {"x": xs, "y": ys, "lead_p": lead.p[:, 0], "foll_p": foll.p[:, 0], "foll_t": foll.t,
                  "foll_q": foll.q[:, 0], "foll_target": foll.target[:, 0], "idx": np.asarray(idx)}
        rows = []
        for f, k in zip(frames, idx):
            q = int(foll.q[k, 0])
            arrays[f"V_{f}"] = potential(ctx.scene, q, pts, foll.target[k, 0]).reshape(X.shape)
            rows.append({"frame": f, "t": float(foll.t[k]), "mode_q": q, "target_x": float(foll.target[k, 0, 0]),
                         "target_y": float(foll.target[k, 0, 1]), "follower_x": float(foll.p[k, 0, 0]),
                         "follower_y": float(foll.p[k, 0, 1])})
        return Results({"instants": pd.DataFrame(rows),
                        "metrics": pd.concat([agent_rows(lead, role="leader"), agent_rows(foll, role="follower")])},
                       arrays, {"frames": frames})


# ---------------------------------------------------------------------------- perception closeness
@dataclass(kw_only=True)
class PerceptionCloseness(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_perception_closeness"
    initial_conditions: Points = field(default_factory=lambda: [[-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)
    errormaps: ClassVar[tuple[str, ...]] = ("clean",)

    def compute(self, ctx: Context) -> Results:
        x0 = np.asarray(self.initial_conditions, float)
        res = ctx.simulate(ctx.controller("hybrid"), x0, measure=ctx.camera_measure("clean"))
        err = np.hypot(*(res.m - res.p).transpose(2, 0, 1))
        eps, source = ctx.eps_perception("clean", "none")
        table = pd.DataFrame([{"eps": eps, "eps_source": source, "max_error_on_run": float(err.max()),
                               "mean_error_on_run": float(err.mean()), "inside_tube": float((err <= eps).mean()),
                               "success": bool(res.metrics["success"][0])}])
        return Results({"closeness": table}, {"p": res.p[:, 0], "m": res.m[:, 0]}, {"eps": eps})


# ------------------------------------------------------------------------------------ Monte Carlo
@dataclass(kw_only=True)
class MonteCarlo(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_monte_carlo"
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    sigma: NonNegative = 0.5
    p_fail: FailureRate = 0.5
    occlusion: str = "heavy"
    camera: bool = True          # include the camera-in-the-loop occlusion conditions (one per map)
    n_agents: PositiveInt = 300          # random initial conditions, true-state conditions
    n_agents_camera: PositiveInt = 100   # random initial conditions, camera conditions (each frame renders + infers them all)
    delta_practical: NonNegative = 3.0  # success also within this distance (about the perception error near the target)

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return ("clean", "occluded") if self.camera else ()

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": ["gaussian"],
                "occlusions": [self.occlusion] if self.camera else []}

    def conditions(self, ctx: Context, camera: bool):
        noise = ctx.disturbance("gaussian", sigma=self.sigma)
        conds = [("none", {}), (f"gaussian σ={self.sigma}", {"disturbance": noise}),
                 (f"gaussian σ={self.sigma} + {self.p_fail:.0%} failure", {"disturbance": noise, "p_fail": self.p_fail})]
        if camera:
            for kind in ("clean", "occluded"):
                conds.append((f"{self.occlusion} occlusion, {kind} map", {"camera": (kind, self.occlusion)}))
        return conds

    def metrics(self, ctx: Context, scene, label: str, camera: bool) -> pd.DataFrame:
        n = ctx.n(self.n_agents)
        n_cam = ctx.n(self.n_agents_camera)
        x0_all = starts.Random(n=max(n, n_cam), seed=ctx.seed, margin=2.0)(scene)
        frames = []
        for cond, kw in self.conditions(ctx, camera):
            ctx.label = f"{label} {cond}"
            kw = dict(kw)
            measure, x0 = None, x0_all[:n]
            if "camera" in kw:
                kind, level = kw.pop("camera")
                measure, x0 = ctx.camera_measure(kind, level), x0_all[:n_cam]
            for ctrl in self.controllers:
                res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, measure=measure, record=False, **kw)
                frames.append(agent_rows(res, scene=label, condition=cond))
        return pd.concat(frames, ignore_index=True)

    def compute(self, ctx: Context) -> Results:
        ctx.expect(len(self.conditions(ctx, self.camera)) * len(self.controllers))
        metrics = self.metrics(ctx, ctx.scene, "default", camera=self.camera)
        table = summarise(metrics, ["condition", "controller"], seed=ctx.seed, delta_practical=self.delta_practical)
        return Results({"metrics": metrics, "summary": table}, {}, {})


