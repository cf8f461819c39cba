"""The smallest complete stage: what a newcomer copies to add one (docs/stages.md). One module and one conf file
(conf/example_stage.yaml); `python -m pipeline.example_stage example.power=3`.

It raises each of `example.values` to `example.power` and writes `result.json` and `table.md` into
`${paths.outputs_dir}/example/powers-<id>/`. What every stage of the project does, in order:

- **settings**: a frozen dataclass checked with `@checked` (types and ranges from `Annotated`), built from its config
  node with `build` (`_target_` names it): a wrong key or value is one line naming it, exit 2, before any work;
- **check**: `check(cfg)` builds what the run needs, cheaply (no data, no torch); the preflight calls it for every job
  of the command line before Hydra starts one, and `run` takes what it built with `prepared` (built once);
- **id**: the output folder is named by the hash of what determines its bytes (the settings and the code), so a run
  with the same config finds its output and does nothing, and a changed value gets a folder of its own;
- **atomic write**: `tracked_output` yields a temporary folder and renames it on success (a manifest of the files
  inside); an error or Ctrl-C leaves nothing under the final name.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Annotated

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.preflight import prepared
from pipeline.schema import NonEmpty, Range, checked


@checked("example")
@dataclass(frozen=True)
class PowerSettings:
    """`values` raised to `power` (conf/example_stage.yaml documents each key)."""

    values: Annotated[list[float], NonEmpty()]
    power: Annotated[int, Range(ge=1, le=8)] = 2

    def __post_init__(self):  # a rule across fields (or one the annotations cannot say): one line, the key named
        if self.power > 1 and any(v < 0 for v in self.values):
            raise ConfigError("example.values", "must be >= 0 when example.power > 1 (this stage's own rule)")


def check(cfg: DictConfig) -> PowerSettings:
    """Preflight: the settings, built and checked (no work)."""
    return build(cfg.example, "example")


def powers_id(s: PowerSettings) -> str:
    """What determines the output's bytes: the settings and this module's code."""
    return tracking.content_id(asdict(s), tracking.sha256_file(Path(__file__)))


def run(cfg: DictConfig) -> dict:
    s = prepared(cfg, check)
    id_ = powers_id(s)
    folder = Path(cfg.paths.outputs_dir) / "example" / f"powers-{id_}"
    if tracking.is_complete(folder) and not cfg.force:
        print(f"example: up to date: {folder}")
        return {"folder": folder, "computed": False}
    out = [v ** s.power for v in s.values]
    with tracking.tracked_output(folder.parent, "powers", id_, {"kind": "example", "recipe": asdict(s)}) as tmp:
        (tmp / "result.json").write_text(json.dumps({"values": list(s.values), "powers": out}) + "\n")
        rows = "\n".join(f"| {v:g} | {p:g} |" for v, p in zip(s.values, out))
        (tmp / "table.md").write_text(f"| value | value^{s.power} |\n|---|---|\n{rows}\n")
    print(f"example: -> {folder}")
    return {"folder": folder, "computed": True}


main = stage_main("example_stage", run="pipeline.example_stage:run", check="pipeline.example_stage:check")

if __name__ == "__main__":
    sys.exit(main())
