"""`python -m pipeline.errormap [maps=<name>|[a,b]] [occlusion_levels=[none,heavy]] [grid.step=0.5] ...`

`model=<ref>` is accepted as an alias of `maps=<ref>` (conf/model/ is the train stage's config group, so Hydra
would otherwise read it as a group choice).
"""

import re
import sys

from pipeline.cli import stage_main

main = stage_main("errormap", run="pipeline.errormap.stage:run", check="pipeline.errormap.checks:check")


def _alias_model_override(argv: list[str]) -> list[str]:
    return [re.sub(r"^model=", "maps=", a) for a in argv]


if __name__ == "__main__":
    sys.argv = [sys.argv[0], *_alias_model_override(sys.argv[1:])]
    main()
