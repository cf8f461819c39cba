"""`python -m pipeline.errormap [maps=<name>|[a,b]] [occlusion_levels=[none,heavy]] [grid.step=0.5] ...`

`model=<ref>` is accepted as an alias of `maps=<ref>` (conf/model/ is the train stage's config group, so
Hydra would otherwise read it as a group choice).
"""

import re
import sys

from omegaconf import DictConfig

from pipeline.cli import stage_main
from pipeline.errormap.stage import _occlusions, _plain, run, validate
from pipeline.errors import DatasetError, ModelError


def check(cfg: DictConfig) -> None:
    """Preflight: the settings, the cloud levels and every map (resolved by id, not loaded)."""
    from pipeline.lineage import resolve_map

    settings = validate(cfg)
    _occlusions(cfg, settings["occlusion_levels"])
    maps = _plain(cfg.get("maps"))
    for ref in maps if isinstance(maps, list) else [maps]:
        try:
            resolve_map(ref, cfg.paths.models_dir)
        except DatasetError as err:
            raise ModelError(str(err)) from None


@stage_main("errormap", check=check)
def main(cfg: DictConfig) -> None:
    run(cfg)


def _alias_model_override(argv: list[str]) -> list[str]:
    return [re.sub(r"^model=", "maps=", a) for a in argv]


if __name__ == "__main__":
    sys.argv = [sys.argv[0], *_alias_model_override(sys.argv[1:])]
    main()
