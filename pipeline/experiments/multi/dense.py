"""Dense fields (issue 29; docs/dense.md): the hybrid controller's dense design against the smooth and CBF
baselines on the hybrid-RL benchmark's clutter, under its noise (`s (m, -m)`, world-fixed, flipping every frame),
the alternating noise of norm `eps` in the nearest obstacle's frame and SPEC §3.5's adversary near every disc.

The scenes: the bundle's `presets` (scene nodes composed by its defaults list: `case6`, `case6_variant`) and
`n_scenes` redraws of the composed `scene` (a `pipeline.control.dense.dense_scene` node, `scene=dense`, or the
benchmark's statistics with each field's own covering, `scene=benchmark`: the sweep of issue 45) with
seeds `scene_seed + j`; the starts: `n_agents` on the circle of `start_radius` about the goal (the benchmark's).
The vehicle is the composed one (`vehicle=unicycle` in the unicycle bundle); every controller on its steering
scene (SPEC §3.7).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import ClassVar

from pipeline import tracking
from pipeline.config import build
from pipeline.control import Scene
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.multi.fields import field_results
from pipeline.experiments.results import Results
from pipeline.experiments.scenario import Scenario, agent_rows
from pipeline.schema import NonNegative, NonNegativeInt, Positive, PositiveInt
from pipeline.sim import starts

DENSE_SCENE = "pipeline.control.dense.dense_scene"
BENCHMARK_SCENE = "pipeline.control.dense.benchmark_scene"  # the benchmark's statistics, each field's own covering


def dense_scenes(ctx: Context, presets: dict, n_scenes: int, seed: int) -> tuple[list[tuple[str, Scene]], list[str]]:
    """The preset scenes (`experiment.presets.<name>`), then `n_scenes` redraws of the composed dense scene (seeds
    `seed + j`); and the lines of the redraws no covering admits (`scene=benchmark`: each field gets its own, or is
    rejected with the pair of discs and the shortfall, and the others run)."""
    out = [(name, build(node, f"experiment.presets.{name}")) for name, node in presets.items()]
    node = tracking.to_plain(ctx.cfg.scene)
    if n_scenes and node.get("_target_") not in (DENSE_SCENE, BENCHMARK_SCENE):
        raise ConfigError("scene", f"this experiment redraws dense fields: needs scene=dense or scene=benchmark (a "
                                   f"{DENSE_SCENE} or {BENCHMARK_SCENE} node), got {node.get('_target_')}")
    rejected = []
    for j in range(n_scenes):
        name = f"{node.get('name', 'dense')}{j:02d}"
        try:
            out.append((name, build({**node, "seed": int(seed) + j, "name": name}, "scene")))
        except ConfigError as err:
            if node.get("_target_") != BENCHMARK_SCENE:
                raise
            rejected.append(f"{name} (seed {int(seed) + j}): {err}")
    return out, rejected


@dataclass(kw_only=True)
class DenseFields(Scenario):
    """Hybrid (the composed controller: `hybrid_dense`) vs smooth vs CBF on dense scenes from the benchmark's
    starts, under each noise level `m` of the benchmark, the alternating noise of norm `alternating_eps` and the
    adversary of `adversary_eps` (null: left out): success and collisions with Wilson intervals, stalls
    (traps), time, jumps and push-outs, pooled and per scene."""

    figures: ClassVar[str] = "pipeline.experiments.multi.dense_figures:draw_dense_fields"
    presets: dict = field(default_factory=dict)   # scene nodes by name (the bundle's defaults list)
    n_scenes: NonNegativeInt = 4
    scene_seed: NonNegativeInt = 0
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    benchmark_m: list[float] = field(default_factory=lambda: [0.05, 0.2])
    alternating_eps: NonNegative | None = 0.28
    adversary_eps: NonNegative | None = 0.28
    n_agents: PositiveInt = 100
    start_radius: Positive = 7.0
    n_drawn: PositiveInt = 100     # agents of the first scene recorded for the figure, per controller

    def validate(self) -> None:
        if not self.presets and not self.n_scenes:
            raise ConfigError("experiment.n_scenes", "must be >= 1 when there are no presets (no scene to run)")

    def uses(self):
        dist = ["world_alternating"] * bool(self.benchmark_m) + ["alternating"] * (self.alternating_eps is not None) \
            + ["adversarial"] * (self.adversary_eps is not None)
        return {"controllers": list(self.controllers), "disturbances": dist, "occlusions": []}

    def conditions(self, ctx: Context) -> list[tuple[str, object]]:
        out = [(f"benchmark m={m:g}", ctx.disturbance("world_alternating", m=m)) for m in self.benchmark_m]
        if self.alternating_eps is not None:
            out.append((f"alternating {self.alternating_eps:g}", ctx.disturbance("alternating", eps=self.alternating_eps)))
        if self.adversary_eps is not None:
            out.append((f"adversary {self.adversary_eps:g}", ctx.disturbance("adversarial", eps=self.adversary_eps)))
        return out

    def compute(self, ctx: Context) -> Results:
        n_scenes = ctx.n(self.n_scenes, minimum=0 if self.presets else 1) if self.n_scenes else 0
        scenes, rejected = dense_scenes(ctx, self.presets, n_scenes, self.scene_seed)
        for line in rejected:
            print(f"[experiments] {self.id}: no covering: {line}", flush=True)
        if not scenes:
            raise ConfigError("experiment.n_scenes", f"every field was rejected (no covering): {rejected[0]}")
        conds = self.conditions(ctx)
        ctx.expect(len(scenes) * len(conds) * len(self.controllers))
        n, frames, arrays = ctx.n(self.n_agents, minimum=4), [], {}
        for j, (label, scene) in enumerate(scenes):
            x0 = starts.Circle(n=n, radius=self.start_radius)(scene, "experiment.start_radius")
            for cond, dist in conds:
                for ctrl in self.controllers:
                    rec = j == 0 and cond == conds[-1][0]
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, disturbance=dist,
                                       record=rec)
                    if rec:
                        arrays[f"p_{ctrl}"] = res.p[:, : self.n_drawn]
                    frames.append(agent_rows(res, scene=label, condition=cond, obstacles=scene.n_obstacles))
            print(f"[experiments] {self.id}: {label} done ({j + 1}/{len(scenes)})", flush=True)
        return field_results(frames, arrays, scenes, ctx.seed, vehicle=ctx.vehicle.name, rejected=rejected)


__all__ = ["DenseFields", "dense_scenes"]
