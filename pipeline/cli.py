"""Thin Hydra shell shared by every stage: config location, resolvers, preflight, one-line errors.

Each stage module does::

    @stage_main("simulate", check=check)
    def main(cfg): return run(cfg)

`run(cfg) -> dict` holds the work and is what tests call with a composed config. Before Hydra runs any
job, :func:`pipeline.config.preflight` composes every job of the command line (each sweep value) and checks
it (Hydra's composition errors, unknown keys with or without `+`, output paths, the stage's `check`): a user
error is one line on stderr and exit code 2, before any work.
"""

from __future__ import annotations

import functools
import os
import sys
from pathlib import Path

import hydra
from omegaconf import DictConfig, OmegaConf

from pipeline.errors import PipelineError

REPO_ROOT = Path(__file__).resolve().parents[1]
CONF_DIR = REPO_ROOT / "conf"


def _register_resolvers() -> None:
    if not OmegaConf.has_resolver("repo_root"):
        OmegaConf.register_new_resolver("repo_root", lambda: str(REPO_ROOT))


_register_resolvers()


def report_error(err: BaseException) -> None:
    """Print one clear line for a user error."""
    print(f"error: {err}", file=sys.stderr)


def stage_main(config_name: str, check=None):
    """Decorator: Hydra entry point with a preflight; user errors become one line on stderr and exit 2.

    `check(cfg)` validates a composed config cheaply (no data, no training): it runs for every job of the
    command line before the first one starts, and again inside each job.
    """

    def wrap(task):
        @functools.wraps(task)
        def guarded(cfg: DictConfig):
            try:
                return task(cfg)
            except PipelineError as err:
                report_error(err)
                sys.exit(2)

        main = hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(guarded)

        @functools.wraps(task)
        def entry():
            os.environ.setdefault("HYDRA_FULL_ERROR", "0")
            from pipeline.config import preflight

            try:
                preflight(config_name, sys.argv[1:], check)
            except PipelineError as err:
                report_error(err)
                sys.exit(2)
            return main()

        return entry

    return wrap


def compose(config_name: str, overrides: list[str] | None = None) -> DictConfig:
    """Compose a stage config outside of `@hydra.main` (tests, notebooks, the paper DAG).

    `hydra:` interpolations are not available here, so `paths.output_dir` must be overridden
    (or the caller sets it) before use.
    """
    from pipeline.config import compose as _compose

    return _compose(config_name, overrides)
