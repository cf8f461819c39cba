"""Stage `make learned` (`python -m pipeline.learned.evaluate`): the paper's architecture (perception map +
hybrid / smooth / CBF), the imitated end-to-end policy and the learned hybrid policy through one evaluation code
(:mod:`pipeline.learned.rollouts`), from random starts and from starts near `K`, on clean frames and near `K`
under the pixel attack at `κ` on each agent's own network; and the imitated policy's switching set over the arena.

Writes `outputs/learned/learned-<id>/`: `tab_learned.csv`/`.md` (success, collision, stall, left-view rates with
95% Wilson intervals, median time to target, the attack's mean induced output change), `fig_switching_set.png`,
and the manifest (config, the map's and the policy's ids).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import pandas as pd
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.envs.navigate import objects_from
from pipeline.errors import ConfigError
from pipeline.schema import Interval, Kappa, NonNegativeInt, Positive, PositiveInt, checked

AGENTS = ("hybrid", "smooth", "cbf", "imitated", "learned_hybrid")
CODE = ("envs", "learned", "control", "render", "plants", "sim", "hybrid", "perception")


@checked("learned")
@dataclass(frozen=True)
class LearnedSettings:
    agents: PositiveInt = 100
    near_k: PositiveInt = 100
    band: Positive = 0.5
    a_range: Interval = (-45.0, -15.0)
    kappa: Kappa = 1.0
    attack_steps: NonNegativeInt = 2
    seed: NonNegativeInt = 7
    agents_list: list[Literal["hybrid", "smooth", "cbf", "imitated", "learned_hybrid"]] = \
        field(default_factory=lambda: list(AGENTS))
    attack_list: list[Literal["hybrid", "smooth", "cbf", "imitated", "learned_hybrid"]] = \
        field(default_factory=lambda: list(AGENTS))
    grid: tuple[PositiveInt, PositiveInt] = (101, 61)


def check(cfg: DictConfig) -> None:
    objects_from(cfg)
    build(cfg.learned, "learned")
    for name in ("smooth", "cbf"):
        build(cfg.controllers[name], f"controllers.{name}", scene=build(cfg.scene, "scene"))
    if cfg.vehicle._target_.endswith("Unicycle"):
        raise ConfigError("vehicle", "the learned policies are evaluated on the single integrator")


def _policies(cfg, obj, pm, model, names):
    from pipeline.envs.policies import ArchitecturePolicy
    from pipeline.learned.policies import ImitatedPolicy, LearnedHybridPolicy

    period = obj.camera_settings.period
    out = {}
    for name in names:
        if name in ("hybrid", "smooth", "cbf"):
            law = obj.controller if name == "hybrid" else build(cfg.controllers[name], f"controllers.{name}",
                                                               scene=obj.scene)
            out[name] = ArchitecturePolicy(pm, law, obj.plant, obj.scene, period, name=f"map+{name}")
        elif name == "imitated":
            out[name] = ImitatedPolicy(model)
        else:
            out[name] = LearnedHybridPolicy(model, pm, obj.controller, obj.plant, obj.scene, period)
    return out


def _attack_net(name, pm, model):
    from pipeline.learned.rollouts import HeadNet

    return HeadNet(model, 0) if name == "imitated" else pm.net


def rows(agent: str, condition: str, res: dict, induced=(np.nan, np.nan)) -> dict:
    from pipeline.sim.metrics import wilson

    n = len(res["outcome"])
    row = {"agent": agent, "condition": condition, "n": n}
    for cls in ("reached", "collided", "stalled", "left_view", "timed_out"):
        k = int((res["outcome"] == cls).sum())
        lo, hi = wilson(k, n)
        row[cls] = k / n
        row[f"{cls}_ci"] = f"[{float(lo):.2f}, {float(hi):.2f}]"
    t = res["time"][np.isfinite(res["time"])]
    row["median_time_s"] = float(np.median(t)) if len(t) else np.nan
    row["induced_along"], row["induced_norm"] = induced
    return row


def run(cfg: DictConfig) -> dict:
    from pipeline.learned.imitate import load_policy_model
    from pipeline.learned.policies import load_map
    from pipeline.learned.report import switching_figure, write_tables
    from pipeline.learned.rollouts import PolicyAttack, run_policy
    from pipeline.perception.adversary import proposition1_direction
    from pipeline.sim import starts as st

    check(cfg)
    obj, s = objects_from(cfg), build(cfg.learned, "learned")
    needs_map = set(s.agents_list) - {"imitated"}
    pm = load_map(cfg.maps.clean, cfg.paths.models_dir) if needs_map else None
    map_name = f"{pm.name}-{pm.id}" if pm is not None else None
    learned = set(s.agents_list) & {"imitated", "learned_hybrid"}
    model = load_policy_model(cfg.policies.imitation, cfg.paths.models_dir) if learned else None
    policy_name = model.tracked_name if model is not None else None
    id_ = tracking.content_id(tracking.to_plain(cfg.learned), tracking.to_plain(cfg.scene),
                              tracking.to_plain(cfg.controllers), tracking.to_plain(cfg.sim), map_name,
                              policy_name, tracking.code_version(*CODE))
    root = Path(cfg.paths.outputs_dir) / "learned"
    if (root / f"learned-{id_}").is_dir() and not cfg.force:
        print(f"learned: up to date -> {root / f'learned-{id_}'}")
        return {"path": root / f"learned-{id_}"}
    random = st.Random(n=s.agents, seed=s.seed, margin=2.0)(obj.scene)
    near = st.NearK(n=s.near_k, seed=s.seed, band=s.band, a_range=list(s.a_range))(obj.scene)
    direction = proposition1_direction(obj.scene)
    table = []
    for name, policy in _policies(cfg, obj, pm, model, s.agents_list).items():
        conditions = [("random, clean", random, None), ("near K, clean", near, None)]
        if name in s.attack_list:
            conditions.append((f"near K, pixel attack κ={s.kappa:g}", near,
                               PolicyAttack(_attack_net(name, pm, model), direction, s.kappa, s.attack_steps)))
        for cond, x0, attack in conditions:
            res = run_policy(obj, policy, x0, seed=s.seed, attack=attack)
            table.append(rows(name, cond, res, attack.summary() if attack else (np.nan, np.nan)))
            print(f"learned: {name:15s} {cond:28s} reached {table[-1]['reached']:.0%} "
                  f"stalled {table[-1]['stalled']:.0%} collided {table[-1]['collided']:.0%}")
    df = pd.DataFrame(table)
    meta = {"kind": "learned", "config": tracking.to_plain(cfg), "map": map_name,
            "policy": policy_name}
    with tracking.tracked_output(root, "learned", id_, meta) as tmp:
        write_tables(df, tmp)
        if model is not None:
            switching_figure(obj, model, tmp / "fig_switching_set.png", s.grid)
    print(df[["agent", "condition", "reached", "reached_ci", "stalled", "collided", "induced_along"]]
          .to_string(index=False))
    return {"path": root / f"learned-{id_}", "table": df}


main = stage_main("learned", run="pipeline.learned.evaluate:run", check="pipeline.learned.evaluate:check")

if __name__ == "__main__":
    main()
