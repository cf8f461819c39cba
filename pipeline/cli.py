"""The thin Hydra shell of every stage: preflight, one-line errors, Ctrl-C, and the stage's work by name.

Each stage's `__main__` is::

    main = stage_main("train", run="pipeline.train.stage:run", check="pipeline.train.checks:check")

Before Hydra runs any job, :func:`pipeline.preflight.preflight` composes every job of the command line (each sweep
value) and checks it (Hydra's composition errors, unknown keys and wrong values with or without `+`, output
paths, the stage's own `check`), importing nothing heavy: a user error is one line on stderr and exit code 2 in
about a second, before any work and before torch or Lightning is imported. The stage's `run(cfg) -> dict` (what
tests call with a composed config) is imported only then. Ctrl-C is one line and exit code 130; stages write
through temporary folders, so nothing is left half-written.
"""

from __future__ import annotations

import contextlib
import functools
import os
import signal
import sys
import threading

from omegaconf import DictConfig

from pipeline.config import compose, resolve
from pipeline.errors import PipelineError
from pipeline.preflight import preflight
from pipeline.repo import CONF_DIR, REPO_ROOT

__all__ = ["CONF_DIR", "REPO_ROOT", "compose", "report_error", "stage_main"]


def report_error(err: BaseException) -> None:
    """Print one clear line for a user error."""
    print(f"error: {err}", file=sys.stderr)


_SIGINT = {"seen": False}


def _interrupted() -> None:
    print("interrupted (Ctrl-C): nothing half-written was kept", file=sys.stderr)
    sys.exit(130)


def _on_sigint(signum, frame):
    """Ctrl-C as Python's own handler, remembered: Lightning turns it into `sys.exit(1)` (its graceful
    shutdown), which the stage then reports as an interruption (exit 130) all the same."""
    _SIGINT["seen"] = True
    raise KeyboardInterrupt


@contextlib.contextmanager
def _watching_sigint():
    _SIGINT["seen"] = False
    watch = threading.current_thread() is threading.main_thread() and \
        signal.getsignal(signal.SIGINT) is signal.default_int_handler  # not where Ctrl-C is ignored
    if watch:
        signal.signal(signal.SIGINT, _on_sigint)
    try:
        yield
    finally:
        if watch:
            signal.signal(signal.SIGINT, signal.default_int_handler)


def stage_main(config_name: str, run: str, check: str | None = None):
    """The entry point of a stage: preflight with `check` (a cheap `check(cfg)`: no data, no training, no torch),
    then Hydra runs `run(cfg)` for each job (both `"module:function"` paths). User errors are one line and exit 2."""

    def guarded(cfg: DictConfig):
        try:
            return resolve(run)(cfg)
        except PipelineError as err:
            report_error(err)
            sys.exit(2)
        except KeyboardInterrupt:
            _interrupted()
        except SystemExit as done:
            if _SIGINT["seen"] and done.code != 130:  # 130: reported already (here, or by a stage of make paper)
                _interrupted()
            raise

    import hydra

    main = hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(guarded)

    @functools.wraps(guarded)
    def entry():
        os.environ.setdefault("HYDRA_FULL_ERROR", "0")
        try:
            with _watching_sigint():
                preflight(config_name, sys.argv[1:], resolve(check) if check else None)
                return main()
        except PipelineError as err:
            report_error(err)
            sys.exit(2)
        except KeyboardInterrupt:
            _interrupted()
        except SystemExit as done:
            if _SIGINT["seen"] and done.code != 130:
                _interrupted()
            raise

    return entry
