"""`python -m pipeline.data [data=<recipe>] [overrides]` (multirun: `-m data=clean,occluded`)."""

from __future__ import annotations

import sys

from omegaconf import DictConfig

from pipeline.cli import stage_main


def check(cfg: DictConfig) -> None:
    """Preflight: validate the recipe and compute the dataset id (no rendering)."""
    from pipeline.data.stage import plan

    plan(cfg)


@stage_main("data", check=check)
def main(cfg: DictConfig) -> None:
    from pipeline.data.stage import run

    run(cfg)


if __name__ == "__main__":
    sys.exit(main())
