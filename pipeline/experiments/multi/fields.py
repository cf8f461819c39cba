"""Several obstacles (SPEC §3.6, issue 19): the locally active obstacle's cells, Proposition 1 behind every
obstacle, a Monte Carlo over random valid fields, and the camera in the loop on a field.

The fields are the composed `scene` (a `pipeline.control.fields.random_scene` node, `scene=field`) redrawn with
other seeds and disc counts (:func:`field_scenes`): every one passes V1–V3 for the controller's cell hysteresis,
speed limit and the camera's frame period. The hybrid controller runs with its sampled-data guard (SPEC §3.3)
as the bundles set it (`controller.guard: true`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline import tracking
from pipeline.config import build
from pipeline.control import Scene
from pipeline.control.fields import analyse_field
from pipeline.control.potentials import potential
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.results import Results, mean_ci, summarise
from pipeline.experiments.scenario import Scenario, agent_rows
from pipeline.schema import Positive
from pipeline.sim import starts
from pipeline.sim.metrics import wilson

RANDOM_SCENE = "pipeline.control.fields.random_scene"
COUNTERS = ("cell_jumps", "mode_jumps", "pushouts", "guard_frames")


def field_scenes(ctx: Context, n_scenes: int, obstacles: list[int], seed: int) -> list[tuple[str, Scene]]:
    """`n_scenes` random valid fields: the composed `scene` node (a `random_scene`) with seed `seed + j` and
    `obstacles[j % len(obstacles)]` discs."""
    node = tracking.to_plain(ctx.cfg.scene)
    if node.get("_target_") != RANDOM_SCENE:
        raise ConfigError("scene", f"this experiment draws random fields: needs scene=field (a {RANDOM_SCENE} node), "
                                   f"got {node.get('_target_')}")
    out = []
    for j in range(n_scenes):
        m, s = int(obstacles[j % len(obstacles)]), int(seed) + j
        out.append((f"field{j:02d}-M{m}", build({**node, "n_obstacles": m, "seed": s, "name": f"field{j:02d}"},
                                                 "scene")))
    return out


def check_map_scene(ctx: Context, kind: str) -> None:
    """The scene map `kind` was trained on (its manifest) must be the composed one: the camera draws the obstacles
    the vehicle avoids (a perfect map passes)."""
    map_scene = ctx.map_scene(kind)
    if map_scene is not None and map_scene.config() != ctx.scene.config():
        raise ConfigError(f"maps.{kind}", f"the map was trained on scene {map_scene.name!r}, not the composed one "
                                          f"({ctx.scene.name!r}): its camera would draw other obstacles than those "
                                          "simulated")


def summarise_field(metrics: pd.DataFrame, by: list[str], seed: int, delta_practical: float | None = None) -> pd.DataFrame:
    """The Monte Carlo table (:func:`pipeline.experiments.context.summarise`) plus the mean of each counter per
    agent (cell jumps, mode jumps, push-outs, guard-active frames) with its 95% interval."""
    table = summarise(metrics, by, seed=seed, delta_practical=delta_practical)
    extra = []
    for _, g in metrics.groupby(by, sort=False):
        row = {}
        for k in COUNTERS:
            m, lo, hi = mean_ci(g[k].to_numpy(float))
            row |= {f"mean_{k}": m, f"mean_{k}_lo": lo, f"mean_{k}_hi": hi}
        row["total_pushouts"] = int(g["pushouts"].sum())
        extra.append(row)
    return pd.concat([table, pd.DataFrame(extra)], axis=1)


def field_results(frames: list[pd.DataFrame], arrays: dict, scenes: list, seed: int, **info) -> Results:
    """The per-agent rows of a run over several fields, summarised pooled and per scene (`scenes`: (label,
    scene) pairs; `info`: further facts for the figures)."""
    metrics = pd.concat(frames, ignore_index=True)
    table = summarise_field(metrics, ["condition", "controller"], seed)
    per_scene = summarise_field(metrics, ["scene", "condition", "controller"], seed)
    return Results({"metrics": metrics, "summary": table, "per_scene": per_scene}, arrays,
                   {"scenes": [s for s, _ in scenes], "first": scenes[0][1].config(), **info})


# ------------------------------------------------------------------------------------------ the cells
@dataclass(kw_only=True)
class MultiCells(Scenario):
    """The cells of the locally active obstacle on the composed field: which obstacle is active where
    (`argmin_j dist_j`), the hysteresis band (`dist_i <= min_j dist_j + h` for two obstacles at once), each
    obstacle's diamond and disc `D_i`, the active potential's level sets, a few true-state trajectories with
    their cell and mode, and the field's validity margins (V1–V3)."""

    figures: ClassVar[str] = "pipeline.experiments.multi.figures:draw_multi_cells"
    grid_step: float = 0.25
    initial_conditions: list[list[float]] = field(default_factory=lambda: [[-40.0, 0.0], [-12.0, 2.0],
                                                                            [-37.0, -17.0]])

    def compute(self, ctx: Context) -> Results:
        scene, ctrl = ctx.scene, ctx.controller("hybrid")
        step = self.grid_step / min(1.0, ctx.scale) ** 0.5
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        dist = ctrl.cell_distance(pts)
        cell = dist.argmin(axis=1)
        second = np.sort(dist, axis=1)[:, 1] if scene.n_obstacles > 1 else np.full(len(pts), np.inf)
        band = second - dist.min(axis=1) < ctrl.h
        V = np.full(len(pts), np.nan)
        for i in range(scene.n_obstacles):
            rows = cell == i
            cov = scene.covering(i)
            V[rows] = np.fmin(potential(cov, 1, pts[rows]), potential(cov, 2, pts[rows]))
        res = ctx.simulate(ctrl, np.asarray(self.initial_conditions, float), record_every=2)
        arr = scene.arrays
        fa = analyse_field(arr["center"], arr["radius"], scene.p_T, starts=self.initial_conditions,
                           arena=scene.bounds, h=ctrl.h, u_max=ctrl.u_max, T_s=ctx.frame_period)
        obstacles = pd.DataFrame({"obstacle": np.arange(scene.n_obstacles), "x": arr["center"][:, 0],
                                  "y": arr["center"][:, 1], "r": arr["radius"], "apex_c": arr["c"],
                                  "reach_rho": arr["reach"], "R": arr["R"],
                                  "V1_slack": np.hypot(*(scene.p_T - arr["center"]).T) - arr["R"],
                                  "share_of_arena": np.bincount(cell, minlength=scene.n_obstacles) / len(pts)})
        info = {"h": ctrl.h, "band_share": float(band.mean()), "kappa_max": fa.kappa_max,
                "kappa": float(np.max(arr["R"] / arr["radius"])), "binding": list(fa.kappa_binding),
                "summary": fa.summary()}
        arrays = {"x": xs, "y": ys, "cell": cell.reshape(X.shape).astype(np.int16), "band": band.reshape(X.shape),
                  "V": V.reshape(X.shape), "p": res.p, "i": res.i, "q": res.q}
        return Results({"obstacles": obstacles, "metrics": agent_rows(res)}, arrays, info)


# ------------------------------------------------------------------------ Proposition 1, every obstacle
@dataclass(kw_only=True)
class MultiAdversarial(Scenario):
    """Success versus ε under SPEC §3.5's adversary (in the frame of the obstacle nearest the vehicle) from starts
    near every obstacle's set K (`pipeline.sim.starts.BehindObstacles`), on `n_scenes` random valid fields:
    hybrid against the smooth and CBF baselines, with Wilson intervals."""

    figures: ClassVar[str] = "pipeline.experiments.multi.figures:draw_multi_adversarial"
    eps: list[float] = field(default_factory=lambda: [0.0, 0.25, 0.5, 1.0])
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_scenes: int = 5
    obstacles: list[int] = field(default_factory=lambda: [3, 4, 5])
    scene_seed: int = 100
    n_agents: int = 200      # per scene, dealt out over the obstacles with room behind them
    min_band: float = 0.1    # |b| < max(eps, min_band)
    depth: float = 10.0      # starts from 1 to 1 + depth behind each diamond's back vertex

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": ["adversarial"], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        n, frames = ctx.n(self.n_agents, minimum=4), []
        scenes = field_scenes(ctx, ctx.n(self.n_scenes, minimum=1), self.obstacles, self.scene_seed)
        for label, scene in scenes:
            for eps in self.eps:
                x0 = starts.BehindObstacles(n=n, seed=ctx.seed, band=max(eps, self.min_band), depth=self.depth)(scene)
                d = ctx.disturbance("adversarial", eps=eps) if eps > 0 else None
                for ctrl in self.controllers:
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, disturbance=d, record=False)
                    frames.append(agent_rows(res, scene=label, eps=eps))
            print(f"[experiments] {self.id}: {label} done", flush=True)
        metrics = pd.concat(frames, ignore_index=True)
        table = summarise_field(metrics, ["eps", "controller"], ctx.seed)
        return Results({"metrics": metrics, "summary": table}, {}, {"scenes": [s for s, _ in scenes]})


# ------------------------------------------------------------------------------------- Monte Carlo
@dataclass(kw_only=True)
class MultiMonteCarlo(Scenario):
    """Random valid fields x random starts x disturbances x controllers on the true state: success, collision,
    stall, time, clearance, jumps by kind, push-outs and guard frames, with intervals (per condition and
    controller, and per field)."""

    figures: ClassVar[str] = "pipeline.experiments.multi.figures:draw_multi_monte_carlo"
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_scenes: int = 20
    obstacles: list[int] = field(default_factory=lambda: [3, 4, 5])
    scene_seed: int = 0
    n_agents: int = 200
    sigma: float = 0.5        # the gaussian condition
    eps: float = 0.5          # the alternating condition
    conditions: list[str] = field(default_factory=lambda: ["none", "gaussian", "alternating"])
    margin: float = 2.0       # starts at least this far inside the arena
    n_drawn: int = 8          # agents of the first field recorded for the figure

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": [c for c in self.conditions if c != "none"],
                "occlusions": []}

    def _disturbance(self, ctx: Context, cond: str):
        if cond == "none":
            return None
        return ctx.disturbance(cond, **({"sigma": self.sigma} if cond == "gaussian" else {"eps": self.eps}))

    def compute(self, ctx: Context) -> Results:
        n, frames, arrays = ctx.n(self.n_agents, minimum=4), [], {}
        scenes = field_scenes(ctx, ctx.n(self.n_scenes, minimum=1), self.obstacles, self.scene_seed)
        for j, (label, scene) in enumerate(scenes):
            x0 = starts.Random(n=n, seed=ctx.seed + j, margin=self.margin)(scene)
            for cond in self.conditions:
                for ctrl in self.controllers:
                    rec = j == 0 and cond == "none"
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0[: self.n_drawn] if rec else x0,
                                       scene=scene, disturbance=self._disturbance(ctx, cond), record=rec)
                    if rec:
                        arrays[f"p_{ctrl}"] = res.p
                        res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, record=False)
                    frames.append(agent_rows(res, scene=label, condition=cond, obstacles=scene.n_obstacles))
            print(f"[experiments] {self.id}: {label} done ({j + 1}/{len(scenes)})", flush=True)
        return field_results(frames, arrays, scenes, ctx.seed)


# -------------------------------------------------------------------------------- camera in the loop
@dataclass(kw_only=True)
class MultiCamera(Scenario):
    """The camera in the loop on the composed field with the map trained on it (`maps.field_heavy`: the field
    under heavy clouds) at cloud level `occlusion`: hybrid, smooth and CBF from `n_agents` random starts, and the
    trajectories of a few of them. The map's own scene (from its dataset's manifest) must be the composed one:
    the camera draws the obstacles the vehicle avoids. `start_radius` (null: random starts `margin` inside the arena):
    `n_agents` starts on the circle of that radius about the goal instead (the hybrid-RL benchmark's, bundle
    dense_camera). `benchmark_m`, `adversary_eps`: further conditions with the benchmark's noise `s (m, -m)` or
    §3.5's adversary added to the camera's estimate (the figure draws the last condition)."""

    figures: ClassVar[str] = "pipeline.experiments.multi.figures:draw_multi_camera"
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    occlusion: str = "heavy"
    map_kind: str = "field_heavy"
    n_agents: int = 100
    margin: float = 2.0
    n_drawn: int = 6
    delta_practical: Positive | None = 3.0
    start_radius: Positive | None = None
    benchmark_m: list[float] = field(default_factory=list)
    adversary_eps: Positive | None = None

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return (self.map_kind,)

    def uses(self):
        dist = ["world_alternating"] * bool(self.benchmark_m) + ["adversarial"] * (self.adversary_eps is not None)
        return {"controllers": list(self.controllers), "disturbances": dist, "occlusions": [self.occlusion]}

    def conditions(self, ctx: Context) -> list[tuple[str, object]]:
        """`(label, disturbance added to the camera's estimate)`: the camera alone, then each noise level."""
        clouds = f"{self.occlusion} clouds" if self.occlusion != "none" else "clean images"
        base = f"{clouds}, {self.map_kind} map"
        out = [(base, None)]
        out += [(f"{base} + benchmark m={m:g}", ctx.disturbance("world_alternating", m=m)) for m in self.benchmark_m]
        if self.adversary_eps is not None:
            out.append((f"{base} + adversary {self.adversary_eps:g}", ctx.disturbance("adversarial",
                                                                                     eps=self.adversary_eps)))
        return out

    def check(self, ctx: Context) -> None:
        super().check(ctx)
        ctx.occlusion(self.occlusion)
        check_map_scene(ctx, self.map_kind)

    def compute(self, ctx: Context) -> Results:
        self.check(ctx)
        n = ctx.n(self.n_agents, minimum=4)
        if self.start_radius is None:
            x0 = starts.Random(n=n, seed=ctx.seed, margin=self.margin)(ctx.scene)
        else:
            x0 = starts.Circle(n=n, radius=self.start_radius)(ctx.scene, "experiment.start_radius")
        measure = ctx.camera_measure(self.map_kind, self.occlusion)
        frames, arrays, conds = [], {}, self.conditions(ctx)
        ctx.expect(len(conds) * len(self.controllers))
        for cond, dist in conds:
            for ctrl in self.controllers:
                res = ctx.simulate(ctx.controller(ctrl), x0, measure=measure, disturbance=dist, record=True)
                frames.append(agent_rows(res, condition=cond))
                arrays[f"p_{ctrl}"], arrays[f"m_{ctrl}"] = res.p[:, : self.n_drawn], res.m[:, : self.n_drawn]
                err = np.hypot(*(res.m - res.p).transpose(2, 0, 1))
                frames[-1]["perception_error_mean"] = np.nanmean(err, axis=0)
                print(f"[experiments] {self.id}: {cond}: {ctrl} done", flush=True)
        metrics = pd.concat(frames, ignore_index=True)
        table = summarise_field(metrics, ["condition", "controller"], ctx.seed, self.delta_practical)
        table["perception_error_mean"] = metrics.groupby(["condition", "controller"], sort=False)[
            "perception_error_mean"].mean().to_numpy()
        return Results({"metrics": metrics, "summary": table}, arrays,
                       {"occlusion": self.occlusion, "drawn": conds[-1][0]})


__all__ = ["MultiAdversarial", "MultiCamera", "MultiCells", "MultiMonteCarlo", "check_map_scene", "field_results", "field_scenes", "summarise_field",
           "wilson"]
