"""The run of stage `make learned` (`python -m pipeline.learned.evaluate`; its entry, settings and preflight are
:mod:`pipeline.learned.evaluate`, which imports no torch): every agent built from its map and network, run through
the one evaluation code (:func:`pipeline.learned.rollouts.run_policy`) under each condition of the stage (clean,
pixel attack, the clouds' level, the worst cloud), the table with Wilson intervals and the switching-set figure.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pandas as pd
import torch
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.envs.policies import ArchitecturePolicy
from pipeline.learned.evaluate import Prepared, check, learned_id
from pipeline.learned.imitate import policy_folder
from pipeline.learned.network import VelocityPolicy
from pipeline.learned.policies import ImitatedPolicy, LearnedHybridPolicy, load_map
from pipeline.learned.ppo import PPOPolicy, load_ppo
from pipeline.learned.report import switching_figure, write_tables
from pipeline.learned.rollouts import HeadNet, PolicyAttack, PolicyWorstCloud, run_policy
from pipeline.perception.adversary import proposition1_direction
from pipeline.preflight import prepared
from pipeline.sim import starts as st
from pipeline.sim.metrics import wilson


def load_policy_model(ref, models_dir, field: str = "policies.imitation"):
    """The trained imitation network :func:`pipeline.learned.imitate.policy_folder` finds, in eval mode."""
    folder = policy_folder(ref, models_dir, field)
    m = tracking.read_manifest(folder)
    hp = dict(m["hparams"])
    hp["image_shape"] = tuple(hp["image_shape"])
    model = VelocityPolicy.of(**hp)
    model.load_state_dict(torch.load(folder / "model.pt", map_location="cpu"))
    model.eval()
    model.tracked_name = folder.name
    return model


def _policies(obj, laws, pm, model, names, ppo=None):
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
    return HeadNet(model, 0) if name == "imitated" else ppo.net if name == "ppo" else pm.net


def _decision(name, pm, model, ppo=None):
    """What the worst cloud pushes along `d`: an end-to-end policy's velocity, or the map's estimate."""
    if name == "imitated":
        return lambda images: model.act(torch.from_numpy(np.ascontiguousarray(images)), 0).double().numpy()
    return ppo.velocity if name == "ppo" else pm.predict


def _load(cfg, folders: dict, scale) -> dict:
    """The maps and networks of `folders`; PPO's acting in the env whose unit action is the velocity `scale`."""
    models = Path(cfg.paths.models_dir)
    out = {k: None if v is None else load_map(v, models) if k.startswith("map") else load_policy_model(v, models)
           for k, v in folders.items() if k != "ppo"}
    out["ppo"] = PPOPolicy(load_ppo(folders["ppo"], models), scale) if folders["ppo"] else None
    return out


def _measure(name: str, policy, conditions, seed: int) -> list[dict]:
    """One table row per condition `(label, environment objects, starts, attack or None)` of one agent."""
    out = []
    for cond, o, x0, attack in conditions:
        res = run_policy(o, policy, x0, seed=seed, attack=attack)
        out.append(rows(name, cond, res, attack.summary() if attack else (np.nan, np.nan)))
        print(f"learned: {name:15s} {cond:28s} reached {out[-1]['reached']:.0%} "
              f"stalled {out[-1]['stalled']:.0%} collided {out[-1]['collided']:.0%}", flush=True)
    return out


def rows(agent: str, condition: str, res: dict, induced=(np.nan, np.nan)) -> dict:
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
            conditions += [(f"near K, pixel attack κ={kappa:g}", obj, near, PolicyAttack(
                _attack_net(name, pm, model, got["ppo"]), direction, kappa, s.attack_steps)) for kappa in s.kappas]
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
