"""Errors a user can act on. Stages print them as one line and exit non-zero (see `pipeline.cli`)."""

import difflib
import re


class PipelineError(Exception):
    """Base class: an error caused by the user's input, reported without a traceback."""


class ConfigError(PipelineError, ValueError):
    """An invalid configuration value. `field` is the config key (e.g. `controller.chi`)."""

    def __init__(self, field: str, reason: str):
        self.field = field
        self.reason = reason
        super().__init__(f"{field}: {reason}")


class DatasetError(PipelineError):
    """A dataset that is unknown, incomplete or fails verification."""


class ModelError(PipelineError):
    """A perception map that is unknown or does not fit its input."""


EXTRAS = {"hydra/launcher": "launchers", "hydra/sweeper": "search"}  # pyproject's extras for Hydra's plugins


def hydra_error(err: BaseException) -> ConfigError:
    """Hydra's and OmegaConf's composition errors (their own messages span several lines) as one `ConfigError`; an
    option of a plugin's group that is not installed says which extra it comes with."""
    from hydra.errors import MissingConfigException

    text = str(err)
    if isinstance(err, MissingConfigException) and text.startswith("Cannot find primary config"):
        return unknown_config(str(err.missing_cfg_file), text)
    if isinstance(err, MissingConfigException) and err.missing_cfg_file:
        group, _, option = str(err.missing_cfg_file).rpartition("/")
        opts = f" (available: {', '.join(sorted(err.options))})" if err.options else ""
        extra = f"; its plugin comes with `pip install -c constraints.txt -e '.[{EXTRAS[group]}]'`" \
            if group in EXTRAS else ""
        return ConfigError(group or option, f"unknown option {option!r}{opts}{extra}")
    m = re.search(r"Could not override '([^']+)'", text)
    if m and ("not in struct" in text or "ConfigKeyError" in text or "To append" in text):
        key = re.sub(r"\.(\d+)(?=\.|$)", r"[\1]", m.group(1))  # a list element as the schema names it: obstacles[0]
        return ConfigError(key, "unknown key (not in the config; check the spelling)")
    cause = err.__cause__ or err.__context__
    while cause is not None:
        if getattr(cause, "full_key", None):
            return ConfigError(str(cause.full_key), str(cause).splitlines()[0])
        cause = cause.__cause__ or cause.__context__
    m = re.search(r"Error merging override (\S+)", text)
    if m:
        return ConfigError(m.group(1).split("=")[0].lstrip("+"), f"invalid value in {m.group(1)!r}")
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return ConfigError("overrides", " ".join(lines[:2]) if lines else type(err).__name__)


def unknown_config(name: str, text: str) -> ConfigError:
    """`--config-name` naming no config: the configs of the search path's folders (Hydra's message lists them;
    conf/'s top-level yaml files), the closest first."""
    from pathlib import Path

    names = sorted({p.stem for d in re.findall(r"path=file://(\S+)", text) for p in Path(d).glob("*.yaml")})
    close = difflib.get_close_matches(name, names, n=len(names), cutoff=0.6)
    return ConfigError("--config-name", f"unknown config {name!r}; the configs of conf/, the closest first: "
                                        f"{', '.join([*close, *(n for n in names if n not in close)])}")
