"""Issue 11, item 4: how each perception map generalises across cloud levels, in pixels and in the closed loop.

:class:`PerceptionGeneralisation` evaluates every map of `maps` (keys of the composed `maps` node: `clean`,
`authors`, `occluded` = heavy clouds, `clean_paper` = the paper's network) on freshly rendered images at every
cloud level of `levels`:

- `n_positions` positions drawn as a dataset's test split is (`pipeline.data.sampling.plan_split`: uniform over
  the arena, a share `follower_probability` of the images with the follower as a distractor), from `seed`: the
  same positions at every level, each level with its own clouds; and `n_near_target` positions uniform within
  `near_radius` of the target (where the closed loop lives), leader only, with the level's clouds;
- one batched render per level, one batched inference per map and level; `perception_metrics` gives the MAE,
  p95, the visible / hidden split (`hidden_alpha` of cloud opacity over the leader) and, on the near-target
  set, the near-target errors;
- the follower of the occlusion scenario (:meth:`OccludedFollowers.starts`, :meth:`OccludedFollowers.follow`,
  :meth:`OccludedFollowers.summary`) with each map under each level: success (|p - p_T| <= sim.delta), practical
  success (within `delta_practical`), collisions.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Annotated, ClassVar

import numpy as np
import pandas as pd

from pipeline import tracking
from pipeline.data.recipe import Follower, Recipe, Sampling, Splits
from pipeline.data.sampling import plan_split
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.paper.camera_loop import OccludedFollowers
from pipeline.experiments.results import Results
from pipeline.experiments.scenario import Points, Scenario
from pipeline.perception.measure import OracleMap
from pipeline.perception.metrics import perception_metrics
from pipeline.render import load_occlusion
from pipeline.schema import NonEmpty, NonNegative, NonNegativeInt, Positive, PositiveInt, Range, Share

Names = Annotated[list[str], NonEmpty(distinct=True)]

# columns of the follower summary carried into the table (renamed `follower_<column>`)
FOLLOWER_COLUMNS = ("n", "success_rate", "success_lo", "success_hi", "success_practical", "collision_rate",
                    "stalled", "final_error_median", "tracking_error_mean")


@dataclass(kw_only=True)
class PerceptionGeneralisation(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_perception_generalisation"
    maps: Names = field(default_factory=lambda: ["clean", "authors", "occluded", "clean_paper"])
    levels: Names = field(default_factory=lambda: ["none", "light", "authors", "heavy"])
    n_positions: PositiveInt = 4000  # test positions per level (uniform over the arena), the same at every level
    n_near_target: NonNegativeInt = 1000  # positions uniform within near_radius of the target
    near_radius: Positive = 5.0      # world units (r_T of the near-target metrics)
    hidden_alpha: Annotated[float, Range(gt=0, le=1)] = 0.8  # cloud opacity over the leader: the frame is hidden
    follower_probability: Share = 0.5  # share of the uniform images that show the follower as a distractor
    seed: NonNegativeInt = 11        # positions and clouds (not a dataset's seed: fresh test positions)
    n_agents: PositiveInt = 100      # followers of the occlusion scenario per map and level
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    delta_practical: NonNegative = 3.0  # follower success also within this distance of the target

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": list(self.levels)}

    def check(self, ctx: Context) -> None:
        known = list(tracking.to_plain(ctx.cfg.maps) or {})
        for name in self.maps:
            if name not in known:
                raise ConfigError("experiment.maps", f"{name!r} is not in the composed `maps` node (known: "
                                                     f"{', '.join(known)}; add maps.{name}=<name or id>)")
        for level in self.levels:
            load_occlusion(level, ctx.cfg.occlusions, field="experiment.levels")
        super().check(ctx)
        specs = {name: _camera_spec(ctx.map_folder(name)) for name in self.maps}  # resolved by id, not loaded
        first = self.maps[0]
        for name, spec in specs.items():
            if spec is not None and specs[first] is not None and spec != specs[first]:
                raise ConfigError("experiment.maps", f"{name} was trained on images of another camera than {first} "
                                                     "(render/scene differ): its numbers would not be comparable")

    # ---------------------------------------------------------------------------------- perception
    def camera(self, ctx: Context):
        """One camera renders every level's images for every map (the first map's; `check` makes sure the
        others were trained on the same one)."""
        return ctx.camera(self.maps[0])

    def images(self, ctx: Context, camera, level: str):
        """(uniform render result, uniform positions, near-target images, near-target positions) at `level`."""
        occ = load_occlusion(level, ctx.cfg.occlusions, field="experiment.levels")
        recipe = Recipe(name=self.id, occlusion=level, seed=self.seed,
                        splits=Splits(train=1, val=1, test=ctx.n(self.n_positions, minimum=1)),
                        sampling=Sampling(mode="uniform"), follower=Follower(probability=self.follower_probability))
        plan = plan_split(recipe, "test", camera, occ)  # leaders and followers: the same at every level
        uniform = camera.render(plan.leader, plan.follower, occlusion=occ, clouds=plan.clouds, return_info=True)
        m = ctx.n(self.n_near_target, minimum=0)
        rng = np.random.default_rng([self.seed, 1])  # the same near-target positions at every level
        r = self.near_radius * np.sqrt(rng.uniform(size=m))
        ang = rng.uniform(0.0, 2 * np.pi, m)
        near = np.asarray(ctx.scene.p_T, float) + np.stack([r * np.cos(ang), r * np.sin(ang)], axis=1)
        (x0, x1), (y0, y1) = camera.arena
        half = camera.robot_size / 2 / camera.scale
        near = np.clip(near, [x0 + half, y0 + half], [x1 - half, y1 - half])
        clouds = occ.sample(m, np.random.default_rng([self.seed, 2]), camera.shape) if occ.active else None
        near_images = camera.render(near, None, occlusion=occ, clouds=clouds)
        return uniform, plan.leader.astype(np.float64), near_images, near

    def perception(self, ctx: Context) -> pd.DataFrame:
        camera = self.camera(ctx)
        rows = []
        for level in self.levels:
            uniform, pos, near_images, near = self.images(ctx, camera, level)
            for name in self.maps:
                pm = ctx.perception_map(name)
                ppu = camera.scale if isinstance(pm, OracleMap) else pm.px_per_unit
                m = perception_metrics(_predict(pm, uniform.images, pos), pos, ppu, target=ctx.scene.p_T,
                                       leader_alpha=uniform.leader_alpha, near_radius=self.near_radius,
                                       hidden_alpha=self.hidden_alpha)
                nt = perception_metrics(_predict(pm, near_images, near), near, ppu)
                rows.append({"map": name, "level": level, "n": m["n"], "mae_px": m["mae_px"],
                             "p95_px": m["p95_dist_px"], "max_px": m["max_dist_px"],
                             "near_target_n": nt["n"], "near_target_mean_px": nt["mean_dist_px"],
                             "near_target_p95_px": nt["p95_dist_px"], "near_target_max_px": nt["max_dist_px"],
                             "visible_mae_px": m["visible"]["mae_px"], "hidden_mae_px": m["hidden"]["mae_px"],
                             "hidden_share": m["hidden"]["share"]})
        df = pd.DataFrame(rows).astype({c: float for c in ("mae_px", "p95_px", "max_px", "near_target_mean_px",
                                                             "near_target_p95_px", "near_target_max_px",
                                                             "visible_mae_px", "hidden_mae_px")})
        order = {name: i for i, name in enumerate(self.maps)}
        return df.sort_values("map", key=lambda s: s.map(order), kind="stable").reset_index(drop=True)

    # ------------------------------------------------------------------------------------ follower
    def followers(self, ctx: Context) -> tuple[pd.DataFrame, pd.DataFrame]:
        """Per-agent rows and their summary per (map, level): the occlusion scenario's follower."""
        occ = OccludedFollowers(id=self.id, title=self.title, initial_conditions=self.initial_conditions,
                        n_agents=self.n_agents, delta_practical=self.delta_practical)
        leaders, followers = occ.starts(ctx)
        rows = [occ.follow(ctx, name, level, leaders, followers)[0] for name in self.maps for level in self.levels]
        metrics = pd.concat(rows, ignore_index=True).rename(columns={"occlusion": "level"})
        return metrics, OccludedFollowers.summary(metrics, ["map", "level"], ctx.seed, self.delta_practical)

    def compute(self, ctx: Context) -> Results:
        perception = self.perception(ctx)
        metrics, follow = self.followers(ctx)
        follow = follow[["map", "level", *FOLLOWER_COLUMNS]].rename(columns={c: f"follower_{c}"
                                                                             for c in FOLLOWER_COLUMNS})
        summary = perception.merge(follow, on=["map", "level"], how="left", validate="one_to_one")
        info = {"maps": {name: ctx.perception_map(name).id for name in self.maps}, "levels": list(self.levels),
                "delta": ctx.delta, "delta_practical": self.delta_practical}
        return Results({"perception": perception, "metrics": metrics, "summary": summary}, {}, info)


def _predict(pm, images, positions) -> np.ndarray:
    """The map's estimates; a perfect map (`perception=oracle`) answers the true positions."""
    if isinstance(pm, OracleMap):
        return np.asarray(positions, np.float64)
    return pm.predict(images)


def _camera_spec(folder) -> str | None:
    """The render and scene settings the map in `folder` was trained with (None: a perfect map, or not recorded)."""
    manifest = {} if folder is None else tracking.read_manifest(folder)
    if "render" not in manifest:
        return None
    return tracking.canonical_json([manifest.get("render"), manifest.get("scene")])
