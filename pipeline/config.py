"""Config is the single source of truth: every node names its `_target_`, whose typed signature is its schema.

- :func:`check_schema` walks a composed config: every key of a `_target_` node must be a keyword of its target
  (no `**kwargs` swallowing typos) and every value must fit the keyword's annotation (types, `Literal` choices,
  nested dataclasses key by key; :mod:`pipeline.schema`); `+`/`++` overrides may add only such keywords.
  :func:`compose` runs it on every composition, so a bad key, type or choice is one `ConfigError` naming it.
- :func:`build` instantiates a node with `hydra.utils.instantiate`; a value its constructor rejects (a range or a
  cross-field rule) becomes a :class:`ConfigError` naming the node's path.
- :func:`check_paths` rejects output paths that are files or cannot be created.
- :func:`pipeline.preflight.preflight` composes every job of a command line (each sweep value) and runs those
  checks plus the stage's own cheap check, so a bad input is one line and exit code 2 before any job starts.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import ConfigError, PipelineError
from pipeline.repo import CONF_DIR, REPO_ROOT
from pipeline.schema import CHECKED_KEYWORDS, check_value, type_hints
from pipeline.signatures import signature

META_KEYS = {"_target_", "_partial_", "_convert_", "_recursive_", "_args_", "name"}


def _register_resolvers() -> None:
    if not OmegaConf.has_resolver("repo_root"):
        OmegaConf.register_new_resolver("repo_root", lambda: str(REPO_ROOT))


_register_resolvers()


# ------------------------------------------------------------------------------------------ build
def resolve(ref: str):
    """`"package.module:function"` -> the object (a stage's work, a scenario's drawing function), imported when used."""
    import importlib

    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


def _reprefix(err: ConfigError, path: str, objects=()) -> ConfigError:
    """`err` naming the config path `path`; a field of an object passed in (`objects`, e.g. the `scene` a controller
    checks against) keeps its own name (`scene.obstacles[0,4]`, not `controller.obstacles[0,4]`)."""
    field = err.field
    if any(field == o or field.startswith((o + ".", o + "[")) for o in objects):
        return err
    if path and not (field == path or field.startswith(path + ".") or field.startswith(path + "[")):
        tail = field.split(".", 1)[-1] if "." in field else field
        field = f"{path}.{tail}" if field not in ("", "_target_") else path
    return ConfigError(field, err.reason)


def build(node, path: str, /, **kwargs):
    """`instantiate(node)(**kwargs)`: the object a config node describes, its keys and types checked first, errors
    naming `path`. `name` is a label of the node (the table row), not a keyword, unless the target takes it."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    if not isinstance(node, DictConfig):
        node = OmegaConf.create(node)
    if "_target_" not in node:
        raise ConfigError(path, "needs a `_target_` (pick one of the options of its config group)")
    check_node(node, path)
    sig = signature(str(node["_target_"]))
    drop = [k for k in node.keys() if k == "name" and sig is not None and "name" not in sig.params]
    clean = OmegaConf.masked_copy(node, [k for k in node.keys() if k not in drop]) if drop else node
    keys = frozenset(str(k) for k in clean.keys()) - META_KEYS if sig is not None else frozenset()
    token = CHECKED_KEYWORDS.set((str(node["_target_"]).rpartition(".")[2], keys))  # its constructor skips them
    try:
        # partial first: Hydra would turn a dataclass keyword (a Scene) into a config node
        obj = instantiate(clean, _partial_=True, _convert_="all", _recursive_=False)(**kwargs)
    except ConfigError as err:
        raise _reprefix(err, path, kwargs) from None
    except PipelineError:
        raise
    except InstantiationException as err:
        cause = err.__cause__
        while cause is not None and not isinstance(cause, PipelineError):
            cause = cause.__cause__
        if isinstance(cause, ConfigError):
            raise _reprefix(cause, path, kwargs) from None
        if cause is not None:
            raise cause from None
        raise ConfigError(path, str(err).splitlines()[0]) from None
    except (TypeError, ValueError) as err:
        raise ConfigError(path, f"invalid parameters for {node['_target_']}: {err}") from None
    finally:
        CHECKED_KEYWORDS.reset(token)
    if drop and hasattr(type(obj), "name") and not isinstance(type(obj).name, property):
        obj.name = str(node["name"])  # the label of the node (a controller's row in a table)
    return obj


# ----------------------------------------------------------------------------------------- schema
def _walk(node, path: str = "") -> Iterable[tuple[str, DictConfig]]:
    if isinstance(node, DictConfig):
        yield path, node
        for k in node.keys():
            if (k == "hydra" and not path) or _is_alias(node, k):
                continue
            try:
                child = node._get_node(k)._dereference_node() if OmegaConf.is_interpolation(node, k) else node[k]
            except Exception:  # noqa: BLE001 - unresolvable interpolation (hydra:...) is not a schema matter
                continue
            yield from _walk(child, f"{path}.{k}" if path else str(k))
    elif isinstance(node, ListConfig):
        for i, child in enumerate(node):
            if isinstance(child, DictConfig | ListConfig):
                yield from _walk(child, f"{path}[{i}]")


def _is_alias(node: DictConfig, key) -> bool:
    """`hybrid: ${controller}`: a node interpolated from another, checked where it is written."""
    if not OmegaConf.is_interpolation(node, key):
        return False
    try:
        return isinstance(node._get_node(key)._dereference_node(), DictConfig)
    except Exception:  # noqa: BLE001 - unresolvable here (hydra:...)
        return False


def _plain_value(node: DictConfig, key):
    """A node's value as plain Python, or `...` when it cannot be resolved here (`${hydra:...}` outside a run)."""
    try:
        value = OmegaConf.select(node, str(key), throw_on_resolution_failure=True)
    except Exception:  # noqa: BLE001 - an interpolation that needs a running Hydra app
        return ...
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, DictConfig | ListConfig) else value


_CHECKED_NODES: set[tuple[str, str]] = set()  # (path, the node's values): checked once per process


def check_node(node: DictConfig, path: str) -> None:
    """The keys and values of one `_target_` node against its target's signature; a node with the same path and
    values checked before in this process (the preflight's, then the stage's build) is not checked again."""
    try:
        sig = signature(str(node["_target_"]))
    except ConfigError as err:
        raise ConfigError(f"{path}._target_" if path else "_target_", err.reason) from None
    if sig is None:
        return
    seen = (path, repr({k: _plain_value(node, k) for k in node.keys()}))
    if seen in _CHECKED_NODES:
        return
    for k in node.keys():
        if k in META_KEYS:
            continue
        where = f"{path}.{k}" if path else str(k)
        if k not in sig.params:
            if sig.any_keyword:
                continue
            raise ConfigError(where, f"unknown key ({node['_target_']} takes {', '.join(sig.params)})")
        value = _plain_value(node, k)
        if value is ... or (isinstance(value, dict) and "_target_" in value):
            continue  # checked as its own node
        check_value(value, sig.params[k], where)
    _CHECKED_NODES.add(seen)


def settings(cfg: DictConfig, cls):
    """A stage's root-level settings (the keys of its config file that are no node of their own) as the typed
    dataclass `cls`: every field's value checked against its annotation, then the object's own rules."""
    import dataclasses

    hints = type_hints(cls)
    values = {}
    for f in dataclasses.fields(cls):
        if f.name in cfg:
            values[f.name] = _plain_value(cfg, f.name)
            check_value(values[f.name], hints[f.name], f.name)
    return cls(**values)


def check_schema(cfg: DictConfig, added: Iterable[str] = ()) -> None:
    """Unknown keys and wrong values anywhere in `cfg` (targets' signatures) and keys added by `+`/`++` overrides."""
    for path, node in _walk(cfg):
        if "_target_" in node and isinstance(node["_target_"], str):
            check_node(node, path)
    for key in added:
        parent, _, leaf = key.rpartition(".")
        node = OmegaConf.select(cfg, parent) if parent else cfg
        if isinstance(node, DictConfig) and "_target_" in node:
            sig = signature(str(node["_target_"]))
            if sig is None or sig.any_keyword or leaf in sig.params:
                continue
            raise ConfigError(key, f"unknown key ({node['_target_']} takes {', '.join(sig.params)})")
        raise ConfigError(key, "unknown key (not in the config; check the spelling: `+` does not add keys here)")


def check_folder(value, field: str) -> None:
    """`value` must be a folder this process can write in, or one it can create: tried for real (a uniquely
    named temporary folder made in it, or in its nearest existing parent when it is missing, then removed), so
    a read-only or virtual filesystem (`/proc/...`), a file in the way or a missing permission is one
    `ConfigError` naming `field`. Nothing is left behind, and checks running at once never meet."""
    import tempfile

    p = Path(str(value)).expanduser()
    if p.exists() and not p.is_dir():
        raise ConfigError(field, f"{p} is a file, not a folder")
    parent = p
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    if not parent.is_dir():
        raise ConfigError(field, f"cannot create {p}: {parent} is a file")
    try:
        tempfile.TemporaryDirectory(dir=parent, prefix=".write-check-").cleanup()
    except OSError as err:
        raise ConfigError(field, f"cannot create or write {p}: {err.strerror or err}") from None


def check_paths(paths) -> None:
    """Every `paths.*` entry (but the Hydra run dir) must be a folder this process can write, or create."""
    if paths is None:
        return
    for key in paths.keys():
        if key == "output_dir":
            continue
        try:
            value = paths[key]
        except Exception:  # noqa: BLE001 - hydra: interpolations outside a run
            continue
        if value is not None:
            check_folder(value, f"paths.{key}")


# ----------------------------------------------------------------------------------------- compose
def compose(config_name: str, overrides: list[str] | None = None, *, check: bool = True) -> DictConfig:
    """Compose a config with Hydra's compose API, also from inside a running `@hydra.main` app (tests, notebooks,
    the paper DAG). `hydra:` interpolations are not available here: `paths.output_dir` must be overridden (or the
    caller sets it) before use."""
    from hydra import compose as _compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    gh = GlobalHydra.instance()
    if gh.is_initialized():
        cfg = _compose(config_name=config_name, overrides=list(overrides or []))
    else:
        try:
            with initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
                cfg = _compose(config_name=config_name, overrides=list(overrides or []))
        finally:
            GlobalHydra.instance().clear()
    if check:
        check_schema(cfg)
    return cfg


def hydra_error_line(err: BaseException) -> str:
    """One line for Hydra/OmegaConf composition errors (their own messages span several lines)."""
    from hydra.errors import MissingConfigException

    if isinstance(err, MissingConfigException) and err.missing_cfg_file:
        group, _, option = str(err.missing_cfg_file).rpartition("/")
        opts = f" (available: {', '.join(sorted(err.options))})" if err.options else ""
        return f"{group or option}: unknown option {option!r}{opts}"
    text = str(err)
    m = re.search(r"Could not override '([^']+)'", text)
    if m and ("not in struct" in text or "ConfigKeyError" in text or "To append" in text):
        key = re.sub(r"\.(\d+)(?=\.|$)", r"[\1]", m.group(1))  # a list element as the schema names it: obstacles[0]
        return f"{key}: unknown key (not in the config; check the spelling)"
    m = re.search(r"Could not find '([^']+)'", text)
    if m:
        group, _, option = m.group(1).rpartition("/")
        avail = re.findall(r"^\t(\S+)$", text, flags=re.M)
        return f"{group or option}: unknown option {option!r}" + (f" (available: {', '.join(avail)})" if avail else "")
    cause = err.__cause__ or err.__context__
    while cause is not None:
        full_key = getattr(cause, "full_key", None)
        if full_key:
            reason = str(cause).splitlines()[0]
            return f"{full_key}: {reason}"
        cause = cause.__cause__ or cause.__context__
    m = re.search(r"Error merging override (\S+)", text)
    if m:
        return f"{m.group(1).split('=')[0].lstrip('+')}: invalid value in {m.group(1)!r}"
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    return " ".join(lines[:2]) if lines else type(err).__name__
