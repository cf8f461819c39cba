"""Stage `make learned` (`python -m pipeline.learned.evaluate`): the paper's architecture (perception map +
hybrid / smooth / CBF), the imitated end-to-end policy and the learned hybrid policy through one evaluation code
(:mod:`pipeline.learned.rollouts`), from random starts and from starts near `K`, on clean frames and near `K`
under the pixel attack at `κ` on each agent's own network; under the `clouds` level's clouds (random and near `K`:
the architecture with the occlusion-trained map `maps.occluded`, the learned policies imitated on clouded frames,
`policies.imitation_clouds`) and near `K` under the worst of `candidates` such clouds per frame on each agent's
own network; and the imitated policy's switching set over the arena.

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

AGENTS = ("hybrid", "smooth", "cbf", "imitated", "learned_hybrid", "ppo")
CLOUDED = ("hybrid", "smooth", "cbf", "imitated", "learned_hybrid")  # trained for clouds (not PPO: clear frames)
Agent = Literal["hybrid", "smooth", "cbf", "imitated", "learned_hybrid", "ppo"]
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
    agents_list: list[Agent] = field(default_factory=lambda: list(AGENTS))
    attack_list: list[Agent] = field(default_factory=lambda: list(AGENTS))
    grid: tuple[PositiveInt, PositiveInt] = (101, 61)
    clouds_list: list[Agent] = field(default_factory=lambda: list(CLOUDED))
    cloud_attack_list: list[Agent] = field(default_factory=lambda: ["hybrid", "imitated", "learned_hybrid"])
    candidates: PositiveInt = 4


@dataclass(frozen=True)
class Prepared:
    """What the check builds and the run uses: the environment's objects, the settings, the clouds' level, the
    feedback laws by agent name, the input folders (:func:`inputs`)."""

    obj: object
    settings: LearnedSettings
    clouds: object
    laws: dict
    folders: dict


def check(cfg: DictConfig) -> Prepared:
    """Preflight: every object built and every map and network found (nothing loaded, nothing run)."""
    obj = objects_from(cfg)
    if obj.plant.heading:
        raise ConfigError("vehicle", "the learned policies are evaluated on the single integrator")
    s = build(cfg.learned, "learned")
    laws = {"hybrid": obj.controller, **{n: build(cfg.controllers[n], f"controllers.{n}", scene=obj.scene)
                                         for n in ("smooth", "cbf")}}
    return Prepared(obj, s, build(cfg.clouds, "clouds"), laws, inputs(cfg, s))


def _policies(obj, laws, pm, model, names, ppo=None):
    from pipeline.envs.policies import ArchitecturePolicy
    from pipeline.learned.policies import ImitatedPolicy, LearnedHybridPolicy

    period = obj.camera_settings.period
    out = {}
    for name in names:
        if name in laws:
            out[name] = ArchitecturePolicy(pm, laws[name], obj.plant, obj.scene, period, name=f"map+{name}",
                                           scale=obj.scale)
        elif name == "imitated":
            out[name] = ImitatedPolicy(model, obj.scale)
        elif name == "ppo":
            out[name] = ppo
        else:
            out[name] = LearnedHybridPolicy(model, pm, obj.controller, obj.plant, obj.scene, period, scale=obj.scale)
    return out


def _attack_net(name, pm, model, ppo=None):
    from pipeline.learned.rollouts import HeadNet

    return HeadNet(model, 0) if name == "imitated" else ppo.net if name == "ppo" else pm.net


def _decision(name, pm, model, ppo=None):
    """What the worst cloud pushes along `d`: an end-to-end policy's velocity, or the map's estimate."""
    import torch

    if name == "imitated":
        return lambda images: model.act(torch.from_numpy(np.ascontiguousarray(images)), 0).double().numpy()
    return ppo.velocity if name == "ppo" else pm.predict


def _needs(s) -> dict[str, list[str]]:
    """The agents each input serves: the clean rows' and the clouded rows'."""
    return {"": list(s.agents_list), "_clouds": [*s.clouds_list, *s.cloud_attack_list]}


def inputs(cfg, s) -> dict[str, Path | None]:
    """The folders of the maps and networks the agents of `s` read (a map's training `.ckpt` file), resolved
    without loading them (a name means the one its current config makes): {"map", "model", "map_clouds",
    "model_clouds", "ppo"}, None where no agent reads it."""
    from pipeline.learned.imitate import policy_folder
    from pipeline.learned.ppo import ppo_folder
    from pipeline.lineage import resolve_map

    out = {}
    for key, agents in _needs(s).items():
        map_ref, field_ = (cfg.maps.clean, "maps.clean") if not key else (cfg.maps.occluded, "maps.occluded")
        policy_ref = cfg.policies.imitation if not key else cfg.policies.imitation_clouds
        needs_map = bool(set(agents) - {"imitated", "ppo"})
        ckpt = str(map_ref).endswith(".ckpt")
        out["map" + key] = None if not needs_map else Path(str(map_ref)) if ckpt else \
            resolve_map(map_ref, cfg.paths.models_dir, field=field_)
        out["model" + key] = policy_folder(policy_ref, cfg.paths.models_dir, field=f"policies.imitation{key}") \
            if set(agents) & {"imitated", "learned_hybrid"} else None
    every = {a for agents in _needs(s).values() for a in agents}
    out["ppo"] = ppo_folder(cfg.policies.ppo, cfg.paths.models_dir) if "ppo" in every else None
    return out


def learned_id(cfg, folders: dict) -> str:
    """The comparison's id: its settings, scene, laws, sim, clouds, the inputs (by folder name) and the code."""
    names = {k: None if v is None else v.name for k, v in folders.items()}
    return tracking.content_id(tracking.to_plain(cfg.learned), tracking.to_plain(cfg.scene),
                               tracking.to_plain(cfg.controllers), tracking.to_plain(cfg.sim),
                               tracking.to_plain(cfg.clouds), names, tracking.code_version(*CODE))


def _load(cfg, folders: dict, scale) -> dict:
    """The maps and networks of `folders`; PPO's acting in the env whose unit action is the velocity `scale`."""
    from pipeline.learned.imitate import load_policy_model
    from pipeline.learned.policies import load_map
    from pipeline.learned.ppo import PPOPolicy, load_ppo

    models = Path(cfg.paths.models_dir)
    out = {k: None if v is None else load_map(v, models) if k.startswith("map") else load_policy_model(v, models)
           for k, v in folders.items() if k != "ppo"}
    out["ppo"] = PPOPolicy(load_ppo(folders["ppo"], models), scale) if folders["ppo"] else None
    return out


def _measure(name: str, policy, conditions, seed: int) -> list[dict]:
    """One table row per condition `(label, environment objects, starts, attack or None)` of one agent."""
    from pipeline.learned.rollouts import run_policy

    out = []
    for cond, o, x0, attack in conditions:
        res = run_policy(o, policy, x0, seed=seed, attack=attack)
        out.append(rows(name, cond, res, attack.summary() if attack else (np.nan, np.nan)))
        print(f"learned: {name:15s} {cond:28s} reached {out[-1]['reached']:.0%} "
              f"stalled {out[-1]['stalled']:.0%} collided {out[-1]['collided']:.0%}", flush=True)
    return out


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
    from pipeline.learned.report import switching_figure, write_tables
    from pipeline.learned.rollouts import PolicyAttack
    from pipeline.perception.adversary import proposition1_direction
    from pipeline.preflight import prepared
    from pipeline.sim import starts as st

    ready = prepared(cfg, check)  # the preflight's, when it checked this job
    obj, s, folders = ready.obj, ready.settings, ready.folders
    id_ = learned_id(cfg, folders)
    root = Path(cfg.paths.outputs_dir) / "learned"
    if tracking.is_complete(root / f"learned-{id_}") and not cfg.force:
        print(f"learned: up to date -> {root / f'learned-{id_}'}")
        return {"path": root / f"learned-{id_}"}
    got = _load(cfg, folders, obj.scale)
    random = st.Random(n=s.agents, seed=s.seed, margin=2.0)(obj.scene)
    near = st.NearK(n=s.near_k, seed=s.seed, band=s.band, a_range=list(s.a_range))(obj.scene)
    direction = proposition1_direction(obj.scene)
    pm, model = got["map"], got["model"]
    table = []
    for name, policy in _policies(obj, ready.laws, pm, model, s.agents_list, got["ppo"]).items():
        conditions = [("random, clean", obj, random, None), ("near K, clean", obj, near, None)]
        if name in s.attack_list:
            conditions.append((f"near K, pixel attack κ={s.kappa:g}", obj, near, PolicyAttack(
                _attack_net(name, pm, model, got["ppo"]), direction, s.kappa, s.attack_steps)))
        table += _measure(name, policy, conditions, s.seed)
    table += _clouded(ready, got, random, near, direction)
    df = pd.DataFrame(table)
    names = {k: None if v is None else v.name for k, v in folders.items()}
    meta = {"kind": "learned", "config": tracking.to_plain(cfg), "map": names["map"], "policy": names["model"],
            "inputs": names}
    with tracking.tracked_output(root, "learned", id_, meta) as tmp:
        write_tables(df, tmp)
        if model is not None:
            switching_figure(obj, model, tmp / "fig_switching_set.png", s.grid)
    print(df[["agent", "condition", "reached", "reached_ci", "stalled", "collided", "induced_along"]]
          .to_string(index=False))
    return {"path": root / f"learned-{id_}", "table": df}


def _clouded(ready: Prepared, got, random, near, direction) -> list[dict]:
    """The rows under the `clouds` level: its random clouds (random starts and near K) for `clouds_list`, and
    near K the worst of `candidates` of its clouds per frame on each agent's own network for `cloud_attack_list`."""
    from dataclasses import replace

    from pipeline.learned.rollouts import PolicyWorstCloud

    obj, s, clouds = ready.obj, ready.settings, ready.clouds
    level = clouds.name or "clouds"
    cloudy = replace(obj, occlusion=clouds)
    pm, model = got["map_clouds"], got["model_clouds"]
    out = []
    agents = [*dict.fromkeys([*s.clouds_list, *s.cloud_attack_list])]
    for name, policy in _policies(obj, ready.laws, pm, model, agents, got["ppo"]).items():
        conditions = []
        if name in s.clouds_list:
            conditions += [(f"random, {level} clouds", cloudy, random, None), (f"near K, {level} clouds", cloudy, near, None)]
        if name in s.cloud_attack_list:
            conditions.append((f"near K, worst of {s.candidates} {level} clouds", obj, near,
                               PolicyWorstCloud(obj.camera, clouds, _decision(name, pm, model, got["ppo"]), direction,
                                                s.candidates, s.seed)))
        out += _measure(name, policy, conditions, s.seed)
    return out

main = stage_main("learned", run="pipeline.learned.evaluate:run", check="pipeline.learned.evaluate:check")

if __name__ == "__main__":
    main()
