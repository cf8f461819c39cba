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

This module is the stage's entry, settings and preflight (:func:`check`, the inputs by id: no map or network
loaded, no torch imported); the run is :mod:`pipeline.learned.comparison`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.envs.navigate import objects_from
from pipeline.errors import ConfigError
from pipeline.learned.imitate import policy_folder
from pipeline.lineage import ppo_folder, resolve_map
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
    kappas: list[Kappa] = field(default_factory=lambda: [1.0])  # the pixel attack's budgets near K (a κ curve)
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


def _needs(s) -> dict[str, list[str]]:
    """The agents each input serves: the clean rows' and the clouded rows'."""
    return {"": list(s.agents_list), "_clouds": [*s.clouds_list, *s.cloud_attack_list]}


def inputs(cfg, s) -> dict[str, Path | None]:
    """The folders of the maps and networks the agents of `s` read (a map's training `.ckpt` file), resolved
    without loading them (a name means the one its current config makes): {"map", "model", "map_clouds",
    "model_clouds", "ppo"}, None where no agent reads it."""
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


main = stage_main("learned", run="pipeline.learned.comparison:run", check="pipeline.learned.evaluate:check")

if __name__ == "__main__":
    main()
