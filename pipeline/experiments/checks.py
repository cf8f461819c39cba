"""The experiments stage's preflight: the scenario, every object it uses and its inputs by id (no map loaded, no
torch imported)."""

from __future__ import annotations

import re

from omegaconf import OmegaConf

from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.scenario import Scenario


def build_scenario(cfg) -> Scenario:
    node = cfg.get("experiment")
    if node is None or "_target_" not in node:
        raise ConfigError("experiment", "pick a bundle: experiment=<id> (conf/experiment/)")
    scen = build(node, "experiment")
    if not isinstance(scen, Scenario):
        raise ConfigError("experiment._target_", f"{node['_target_']} is not a scenario")
    return scen


def check(cfg) -> tuple[Scenario, Context]:
    """Preflight: the scenario, every object it uses and its inputs (maps and error maps, by id); returns the
    scenario and its context (no map loaded), which the run uses (:func:`pipeline.preflight.prepared`)."""
    scen = build_scenario(cfg)
    ctx = Context(cfg)
    scen.check(ctx)
    ctx.map_ids(scen.maps)
    for kind in scen.maps:  # a unicycle reading its heading from the camera needs pose maps
        ctx.check_heading(kind)
    for kind in getattr(scen, "errormaps", ()):
        ctx.error_map(kind)
    return scen, ctx


INPUTS = ("maps", "errormaps", "controllers", "disturbances", "occlusions")  # the named inputs a bundle picks from


def inputs_read(cfg) -> tuple[str, dict[str, set[str]]]:
    """The named inputs the bundle reads (:func:`pipeline.cli.before_hydra` rejects an override that no job reads):
    its maps, error maps and the controllers, disturbances and cloud levels of its `uses()` (what its cache key
    holds), every node these interpolate (`occlusions.heavy_mix` reads `heavy`'s keys) and every one an
    interpolation elsewhere in the config names."""
    scen = build_scenario(cfg)
    used = {"maps": scen.maps, "errormaps": getattr(scen, "errormaps", ()), **scen.uses()}
    todo = [(g, str(n)) for g in INPUTS for n in used.get(g, ())]
    todo += _refs(OmegaConf.masked_copy(cfg, [k for k in cfg if k not in INPUTS]), "")
    read: dict[str, set[str]] = {g: set() for g in INPUTS}
    while todo:
        group, name = todo.pop()
        nodes = cfg.get(group) if group in INPUTS else None
        if nodes is not None and name in nodes and name not in read[group]:
            read[group].add(name)
            todo += _refs(OmegaConf.masked_copy(nodes, [name]), group)
    return f"experiment {scen.id}", read


def _refs(node, group: str) -> list[tuple[str, str]]:
    """(group, name) of each interpolation in `node` of `group` (unresolved): `${occlusions.heavy.x}`, and a
    sibling's `${..heavy.x}`."""
    found = re.findall(r"\$\{(\.\.+|\w+\.)(\w+)", OmegaConf.to_yaml(node))
    return [(group if prefix.startswith(".") else prefix[:-1], name) for prefix, name in found]
