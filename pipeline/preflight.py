"""Preflight: every job of a command line (each value of a sweep) composed and checked before any job runs: Hydra's
composition, the schema (:func:`pipeline.config.check_schema`), the output paths and the stage's own cheap check, so
that a bad input is one line and exit code 2 before any work. What the stage's check built, its run uses (:func:`prepared`)."""

from __future__ import annotations

import os
from collections.abc import Callable

from omegaconf import DictConfig, OmegaConf

from pipeline.config import check_schema, compose, plain_value
from pipeline.errors import ConfigError
from pipeline.repo import CONF_DIR, check_folder


def preflight(config_name: str, argv: list[str], check: Callable[[DictConfig], object] | None = None) -> int:
    """Compose and check every job of a command line (read by Hydra's own parser); returns the number checked."""
    from hydra._internal.utils import get_args_parser

    args = get_args_parser().parse_args(argv)
    if args.help or args.hydra_help or args.cfg or args.info or args.shell_completion:
        return 0
    dirs = [f"file://{os.path.abspath(args.config_dir)}"] if args.config_dir else []  # a user's config folders
    for key, _, value in (o.lstrip("+").partition("=") for o in args.overrides):
        if key == "hydra.searchpath":
            dirs += [d.strip(" '\"") for d in value.strip(" []").split(",") if d.strip()]
        elif key in ("hydra.run.dir", "hydra.sweep.dir") and value and "${" not in value:
            check_folder(value, key)  # Hydra makes it before any job
    search = [f"hydra.searchpath=[{','.join(dirs)}]"] if dirs else []
    jobs = _expand([o for o in args.overrides if not o.lstrip("+~").startswith(("hydra.", "hydra="))])
    failed = []
    for job in jobs:
        try:
            _check_job(args.config_name or config_name, [*search, *job], check)
        except ConfigError as err:  # in a sweep, which job: a key may be valid for one and not for another
            failed.append((job, err))
    if failed:
        raise failed[0][1] if len(jobs) == 1 else _sweep_error(jobs, failed)
    return len(jobs)


def _expand(overrides: list[str]) -> list[list[str]]:
    """Jobs to check: the first value of every sweep, then each other value of one sweep at a time."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob

    choices: list[list[str]] = []
    for raw in overrides:
        try:
            ov = OverridesParser.create().parse_overrides([raw])[0]
        except Exception as err:  # noqa: BLE001 - Hydra's parse errors
            reason = " ".join(str(err).split()).split(" See https://")[0]
            raise ConfigError(raw.lstrip("+~").split("=")[0], f"cannot parse {raw!r}: {reason}") from None
        prefix, value = raw.split("=", 1)[0], ov.value()
        if not ov.is_sweep_override():
            choices.append([raw])
        elif isinstance(value, Glob):  # the options of a config group
            opts = value.filter(sorted(p.stem for p in (CONF_DIR / ov.key_or_group).glob("*.yaml")))
            choices.append([f"{prefix}={v}" for v in opts] or [raw])
        else:
            choices.append([f"{prefix}={v}" for v in ov.sweep_string_iterator()])
    first = [c[0] for c in choices]
    return [first] + [[*first[:i], v, *first[i + 1:]] for i, c in enumerate(choices) for v in c[1:]]


def _check_job(config_name: str, job: list[str], check: Callable[[DictConfig], object] | None) -> None:
    """One job: composed, its schema (with the keys `+`/`++` add, but group selections and, for `++`, keys the
    config has without it), its paths and the stage's check (kept for the run)."""
    cfg = compose(config_name, job, check=False)
    base = compose(config_name, [o for o in job if not o.startswith("++")], check=False) if \
        any(o.startswith("++") for o in job) else cfg
    added = [k for k in (o.lstrip("+").split("=", 1)[0] for o in job if o.startswith("+"))
             if not ("/" in k or "@" in k or (CONF_DIR / k).is_dir())
             and (base is cfg or OmegaConf.select(base, k, default="__missing__") == "__missing__")]
    check_schema(cfg, added)
    for key in [k for k in cfg.get("paths") or {} if k != "output_dir"]:  # writable folders (not Hydra's run dir)
        value = plain_value(cfg.paths, key)  # `...`: a `${hydra:...}` outside a run
        if value is not None and value is not ...:
            check_folder(value, f"paths.{key}")
    if check is not None:
        _PREPARED[_job_key(cfg)] = check(cfg)


def _sweep_error(jobs: list[list[str]], failed: list) -> ConfigError:
    """One line for a sweep whose jobs fail: the first failure, and where a key is unknown to some jobs only (a
    hybrid-only key in a sweep over `controller=hybrid,smooth,cbf`), which of the swept choices take it."""
    job, err = failed[0]
    common = set.intersection(*(set(j) for j in jobs))
    choice = lambda j: " ".join(o for o in j if o not in common)  # noqa: E731 - what the sweep varies in job j
    unknown = [j for j, e in failed if e.field == err.field and "unknown key" in e.reason]
    passed = [j for j in jobs if all(j is not f for f, _ in failed)]
    if len(unknown) == len(failed) and passed:
        take = ", ".join(f"`{choice(j)}`" for j in passed)
        miss = ", ".join(f"`{choice(j)}`" for j in unknown)
        value = next((o for o in job if o.lstrip("+").split("=")[0] == err.field), err.field)
        return ConfigError(err.field, f"a key of the sweep's jobs {take} only, not of {miss}: sweep it over those "
                                      f"alone (e.g. `-m {choice(passed[0])} {value}`) and the others without it")
    return ConfigError(err.field, f"{err.reason} (in the sweep's job `{' '.join(job)}`)")


_PREPARED: dict[str, object] = {}  # what the preflight's check built, by the job's config (without `hydra`)


def _job_key(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(OmegaConf.masked_copy(cfg, [k for k in cfg.keys() if k != "hydra"]))


def prepared(cfg: DictConfig, check: Callable[[DictConfig], object]):
    """What the preflight's `check` built for this job's config in this process (a stage's run uses it: each value
    built and checked once), or `check(cfg)` now (a job the preflight did not reach, a call from Python)."""
    key = _job_key(cfg)
    return _PREPARED.pop(key) if key in _PREPARED else check(cfg)
