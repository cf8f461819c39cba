"""The thin Hydra shell of every stage: preflight, one-line errors, Ctrl-C, and the stage's work by name.

Each stage's `__main__` is::

    main = stage_main("train", run="pipeline.train.stage:run", check="pipeline.train.checks:check")

Before Hydra runs any job, :func:`pipeline.preflight.preflight` composes every job of the command line (each sweep
value) and checks it (Hydra's composition errors, unknown keys and wrong values with or without `+`, output
paths, the stage's own `check`), importing nothing heavy: a user error is one line on stderr and exit code 2 in
about a second, before any work and before torch or Lightning is imported; so is a sweep without `-m` and an
override of an input that no job reads (:func:`before_hydra`). The stage's `run(cfg) -> dict` (what
tests call with a composed config) is imported only then. Ctrl-C is one line and exit code 130; stages write
through temporary folders, so nothing is left half-written.
"""

from __future__ import annotations

import contextlib
import functools
import os
import re
import signal
import sys
import threading
from collections.abc import Callable

from omegaconf import DictConfig

from pipeline.allocator import keep_freed_memory
from pipeline.config import compose, resolve
from pipeline.errors import ConfigError, PipelineError
from pipeline.preflight import preflight
from pipeline.repo import CONF_DIR, REPO_ROOT

__all__ = ["CONF_DIR", "REPO_ROOT", "before_hydra", "compose", "report_error", "stage_main"]


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


@contextlib.contextmanager
def _one_line():
    """A user error: one line, exit 2; Ctrl-C (or Lightning's exit after it): exit 130, said once (130: reported
    already, here or by a stage of make paper)."""
    try:
        yield
    except PipelineError as err:
        report_error(err)
        sys.exit(2)
    except KeyboardInterrupt:
        _interrupted()
    except SystemExit as done:
        if _SIGINT["seen"] and done.code != 130:
            _interrupted()
        raise


# ------------------------------------------------------------------------------------------ the command line
def _overrides(argv: list[str]):
    """The command line as Hydra reads it, and its overrides with each one's sweep flag (None: Hydra's parser
    rejects it, which the preflight reports)."""
    from hydra._internal.utils import get_args_parser
    from hydra.core.override_parser.overrides_parser import OverridesParser

    args, parser, out = get_args_parser().parse_args(argv), OverridesParser.create(), []
    for raw in args.overrides:
        try:
            out.append((raw, parser.parse_overrides([raw])[0].is_sweep_override()))
        except Exception:  # noqa: BLE001 - Hydra's parse errors
            out.append((raw, None))
    return args, out


def _multirun_config(config_name: str, overrides: list[str]) -> bool:
    """Whether the composed config sets `hydra.mode: MULTIRUN` itself (a sweeper's config, `hydra.mode=MULTIRUN`):
    then Hydra sweeps without `-m`. True where it does not compose here: the preflight says why."""
    from hydra import compose as hydra_compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra
    from hydra.types import RunMode

    try:
        with contextlib.nullcontext() if GlobalHydra.instance().is_initialized() else \
                initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
            cfg = hydra_compose(config_name=config_name, overrides=overrides, return_hydra_config=True)
        return cfg.hydra.mode == RunMode.MULTIRUN
    except Exception:  # noqa: BLE001 - a composition error: the preflight's to report
        return True


def _sweep_without_multirun(config_name: str, args, overrides: list[tuple[str, bool | None]]) -> None:
    """A sweep (`key=a,b`) without `-m`: one line naming the key (Hydra's own answer is five lines and exit 1)."""
    sweeps = [raw for raw, sweep in overrides if sweep]
    if not sweeps or args.multirun or args.cfg or args.help or args.hydra_help or args.info or args.shell_completion:
        return
    if _multirun_config(config_name, [raw for raw, sweep in overrides if sweep is False]):
        return
    key, _, value = sweeps[0].partition("=")
    key = key.lstrip("+~")
    listed = "," in value and "(" not in value and not (CONF_DIR / key.split("@")[0]).is_dir()  # a group: no list
    raise ConfigError(key, f"'{value}' is a sweep (one job per value): add -m (--multirun) to run it" +
                      (f", or write a list as {key}=[{value}]" if listed else ""))


def _unread(overrides: list[tuple[str, bool | None]], reads: list[tuple[str, dict[str, set[str]]]]) -> None:
    """An override of a named input (`maps.clean`, `controllers.cbf.alpha`) that no job of the command line reads (each
    job's `reads`: who, and the names it reads of each group): one line naming the key and who ignores it. Only where
    the preflight checked every job (at most one sweep: with more, it checks each value once, not each combination)."""
    if not reads or sum(bool(sweep) for _, sweep in overrides) > 1:
        return
    for raw, _ in overrides:
        key = raw.lstrip("+~").split("=", 1)[0]
        group, _, rest = key.partition(".")
        name = re.split(r"[.\[@]", rest)[0]
        if not name or not all(group in r for _, r in reads) or any(name in r[group] for _, r in reads):
            continue
        who = list(dict.fromkeys(w for w, _ in reads))
        names = ", ".join(sorted(set().union(*(r[group] for _, r in reads)))) or "none"
        raise ConfigError(key, f"{who[0]} never reads it (the {group} it reads: {names}); drop the override" if
                          len(who) == 1 else f"no job reads it ({', '.join(who)}; the {group} they read: {names}); "
                                             "drop the override")


def before_hydra(config_name: str, argv: list[str], check: Callable | None = None, reads: Callable | None = None):
    """Everything a stage checks before Hydra starts a job: a sweep without `-m`, the preflight (every job composed
    and checked with `check`) and, with `reads(cfg) -> (who, {group: names read})` (the `inputs_read` beside a
    stage's check), an override that no job reads."""
    args, overrides = _overrides(argv)
    _sweep_without_multirun(args.config_name or config_name, args, overrides)
    seen: list = []

    def checking(cfg):
        out = check(cfg)
        seen.append(reads(cfg))
        return out

    preflight(config_name, argv, checking if check is not None and reads is not None else check)
    _unread(overrides, seen)


def stage_main(config_name: str, run: str, check: str | None = None):
    """The entry point of a stage: preflight with `check` (a cheap `check(cfg)`: no data, no training, no torch),
    then Hydra runs `run(cfg)` for each job (both `"module:function"` paths). Where the check's module also defines
    `inputs_read(cfg)` (the inputs a job reads), an override that no job reads is an error (:func:`before_hydra`). User
    errors are one line and exit 2."""

    def guarded(cfg: DictConfig):
        with _one_line():
            return resolve(run)(cfg)

    import hydra

    main = hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name=config_name)(guarded)

    @functools.wraps(guarded)
    def entry():
        os.environ.setdefault("HYDRA_FULL_ERROR", "0")
        keep_freed_memory()  # the same bytes, fewer page faults (pipeline.allocator)
        with _one_line(), _watching_sigint():
            checking = resolve(check) if check else None
            reads = getattr(sys.modules[checking.__module__], "inputs_read", None) if checking else None
            before_hydra(config_name, sys.argv[1:], checking, reads)
            return main()

    return entry
