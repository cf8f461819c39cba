"""The experiments stage's preflight: the scenario, every object it uses and its inputs by id (no map loaded, no
torch imported)."""

from __future__ import annotations

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
