"""Preflight: every job of a command line (each value of a sweep) composed and checked before any job runs.

:func:`preflight` splits a Hydra command line into its config name and overrides, expands the sweeps into the
jobs to check (the first value of every sweep, then each other value of one sweep at a time), composes each
(:func:`pipeline.config.compose`) and runs the schema check (unknown keys, `+`/`++` additions, types),
the output paths' check and the stage's own cheap check, so a bad input is one line and exit code 2.
"""

from __future__ import annotations

import fnmatch
from collections.abc import Callable

from omegaconf import DictConfig, OmegaConf

from pipeline.config import check_folder, check_paths, check_schema, compose, hydra_error_line
from pipeline.errors import ConfigError, PipelineError
from pipeline.repo import CONF_DIR

_SKIP_FLAGS = {"-h", "--help", "--hydra-help", "-i", "--info", "-c", "--cfg", "--resolve", "-sc", "--shell-completion",
               "--version"}
_VALUE_FLAGS = {"-cn", "--config-name", "-cp", "--config-path", "-cd", "--config-dir", "-p", "--package",
                "--experimental-rerun"}


def _split_argv(argv: list[str], config_name: str) -> tuple[str, list[str], bool]:
    """(config name, task overrides, skip) from a Hydra command line."""
    overrides, it = [], iter(argv)
    for a in it:
        if a in _SKIP_FLAGS or a.startswith("--info") or a.startswith("--cfg"):
            return config_name, [], True
        if a in _VALUE_FLAGS:
            value = next(it, "")
            if a in ("-cn", "--config-name"):
                config_name = value
            continue
        if a.startswith("--config-name="):
            config_name = a.split("=", 1)[1]
            continue
        if a in ("-m", "--multirun") or a.startswith("-"):
            continue
        key = a.lstrip("+~").split("=", 1)[0]
        if key == "hydra" or key.startswith(("hydra.", "hydra/")):
            continue
        overrides.append(a)
    return config_name, overrides, False


def _search_path(argv: list[str]) -> list[str]:
    """The `hydra.searchpath=[...]` override that puts a user's own config folders beside the project's: from
    `--config-dir DIR` / `-cd DIR` and from the command line's own `hydra.searchpath=[...]` (empty: none), so
    that the preflight composes the scenes and starts a user keeps outside the repository as Hydra will."""
    import os

    dirs, it = [], iter(argv)
    for a in it:
        if a in ("-cd", "--config-dir"):
            dirs.append("file://" + os.path.abspath(next(it, "")))
        elif a.startswith("--config-dir="):
            dirs.append("file://" + os.path.abspath(a.split("=", 1)[1]))
        elif a.lstrip("+").startswith("hydra.searchpath="):
            value = a.split("=", 1)[1].strip()
            dirs += [d.strip().strip("'\"") for d in value.strip("[]").split(",") if d.strip()]
    return [f"hydra.searchpath=[{','.join(dirs)}]"] if dirs else []


def _group_options(group: str) -> list[str]:
    return sorted(p.stem for p in (CONF_DIR / group).glob("*.yaml"))


def _expand(overrides: list[str]) -> list[list[str]]:
    """Jobs to check: the first value of every sweep, then each other value of one sweep at a time."""
    from hydra.core.override_parser.overrides_parser import OverridesParser
    from hydra.core.override_parser.types import Glob

    parser = OverridesParser.create()
    parsed = []
    for raw in overrides:
        try:
            parsed += parser.parse_overrides([raw])
        except Exception as err:  # noqa: BLE001 - Hydra's parse errors
            reason = " ".join(str(err).split()).split(" See https://")[0]
            raise ConfigError(raw.lstrip("+~").split("=")[0], f"cannot parse {raw!r}: {reason}") from None
    choices: list[list[str]] = []
    for ov, raw in zip(parsed, overrides):
        if not ov.is_sweep_override():
            choices.append([raw])
            continue
        prefix = raw.split("=", 1)[0]
        value = ov.value()
        if isinstance(value, Glob):
            opts = [o for o in _group_options(ov.key_or_group)
                    if any(fnmatch.fnmatch(o, p) for p in value.include)
                    and not any(fnmatch.fnmatch(o, p) for p in value.exclude)]
            vals = opts or [raw.split("=", 1)[1]]
        else:
            vals = list(ov.sweep_string_iterator())
        choices.append([f"{prefix}={v}" for v in vals])
    jobs = [[c[0] for c in choices]]
    for i, c in enumerate(choices):
        for v in c[1:]:
            job = [cc[0] for cc in choices]
            job[i] = v
            jobs.append(job)
    return jobs


def _added_keys(job: list[str]) -> list[str]:
    """Keys that `+key=value` / `++key=value` overrides add (group selections are not keys)."""
    out = []
    for o in job:
        if not o.startswith("+"):
            continue
        key = o.lstrip("+").split("=", 1)[0]
        if "/" in key or "@" in key or (CONF_DIR / key).is_dir():
            continue
        out.append(key)
    return out


_EXTRAS = {"hydra/launcher": "launchers", "hydra/sweeper": "search"}  # pyproject's extras for Hydra's plugins


def _check_hydra_groups(config_name: str, argv: list[str]) -> None:
    """`hydra/launcher=joblib` without its plugin installed: one line naming the extra, not Hydra's 9 lines."""
    groups = [a for a in argv if a.lstrip("+").split("=", 1)[0].startswith("hydra/")]
    if not groups:
        return
    try:
        compose(config_name, groups, check=False)
    except Exception as err:  # noqa: BLE001 - Hydra's composition errors, in one line
        raise _composition_error(err) from None


def _composition_error(err: BaseException) -> ConfigError:
    line = hydra_error_line(err)
    field, _, reason = line.partition(": ")
    extra = _EXTRAS.get(field)
    hint = f"; its plugin comes with `pip install -c constraints.txt -e '.[{extra}]'`" if extra else ""
    return ConfigError(field, (reason or line) + hint)


def preflight(config_name: str, argv: list[str], check: Callable[[DictConfig], None] | None = None) -> int:
    """Compose and check every job of a command line; returns the number of jobs checked."""
    config_name, overrides, skip = _split_argv(argv, config_name)
    if skip:
        return 0
    for a in argv:  # Hydra creates its run/sweep dir before any job: an explicit one is checked here
        key, _, value = a.lstrip("+").partition("=")
        if key in ("hydra.run.dir", "hydra.sweep.dir") and value and "${" not in value:
            check_folder(value, key)
    search = _search_path(argv)
    _check_hydra_groups(config_name, argv)
    jobs = _expand(overrides)
    failed = []
    for job in jobs:
        try:
            _check_job(config_name, [*search, *job], check)
        except ConfigError as err:  # in a sweep, which job: a key may be valid for one and not for another
            if len(jobs) == 1:
                raise
            failed.append((job, err))
    if failed:
        raise _sweep_error(jobs, failed)
    return len(jobs)


def _sweep_error(jobs: list[list[str]], failed: list) -> ConfigError:
    """One line for a sweep whose jobs fail: the first failure, and where a key is unknown to some jobs only (a
    hybrid-only key in a sweep over `controller=hybrid,smooth,cbf`), which of the swept choices take it."""
    job, err = failed[0]
    common = set.intersection(*(set(j) for j in jobs))

    def choice(j: list[str]) -> str:  # what the sweep varies in job j
        return " ".join(o for o in j if o not in common)

    unknown = [j for j, e in failed if e.field == err.field and "unknown key" in e.reason]
    passed = [j for j in jobs if all(j is not f for f, _ in failed)]
    if len(unknown) == len(failed) and passed:
        take = ", ".join(f"`{choice(j)}`" for j in passed)
        miss = ", ".join(f"`{choice(j)}`" for j in unknown)
        value = next((o for o in job if o.lstrip("+").split("=")[0] == err.field), err.field)
        return ConfigError(err.field, f"a key of the sweep's jobs {take} only, not of {miss}: sweep it over those "
                                      f"alone (e.g. `-m {choice(passed[0])} {value}`) and the others without it")
    return ConfigError(err.field, f"{err.reason} (in the sweep's job `{' '.join(job)}`)")


def _check_job(config_name: str, job: list[str], check: Callable[[DictConfig], None] | None) -> None:
    try:
        cfg = compose(config_name, job, check=False)
    except PipelineError:
        raise
    except Exception as err:  # noqa: BLE001 - Hydra composition errors, reported in one line
        raise _composition_error(err) from None
    added = _added_keys(job)
    base = None
    if any(o.startswith("++") for o in job):
        base = compose(config_name, [o for o in job if not o.startswith("++")], check=False)
    added = [k for k in added if base is None or OmegaConf.select(base, k, default="__missing__") == "__missing__"]
    check_schema(cfg, added)
    check_paths(cfg.get("paths"))
    if check is not None:
        _PREPARED[_job_key(cfg)] = check(cfg)


_PREPARED: dict[str, object] = {}  # what the preflight's check built, by the job's config (without `hydra`)
_MISSING = object()


def _job_key(cfg: DictConfig) -> str:
    return OmegaConf.to_yaml(OmegaConf.masked_copy(cfg, [k for k in cfg.keys() if k != "hydra"]))


def prepared(cfg: DictConfig, check: Callable[[DictConfig], object]):
    """What the preflight's `check` built for this job's config in this process (a stage's run uses it: each value
    built and checked once), or `check(cfg)` now (a job the preflight did not reach, a call from Python)."""
    got = _PREPARED.pop(_job_key(cfg), _MISSING)
    return check(cfg) if got is _MISSING else got
