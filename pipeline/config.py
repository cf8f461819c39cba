"""Config is the single source of truth: every node names its `_target_`, whose typed signature is its schema.
:func:`check_schema` (run by :func:`compose`): every key of a `_target_` node must be a keyword of its target (no
`**kwargs` swallowing typos) and every value must fit the keyword's annotation (:mod:`pipeline.schema`). :func:`build`
instantiates a node; a value its constructor rejects (a range, a cross-field rule) is a :class:`ConfigError` naming
the node's path."""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import functools
import importlib
import importlib.util
import inspect
import pickle
from collections.abc import Iterable
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import ConfigError, hydra_error
from pipeline.repo import CONF_DIR, REPO_ROOT
from pipeline.schema import check_once, type_hints

META_KEYS = {"_target_", "_partial_", "_convert_", "_recursive_", "_args_"}
if not OmegaConf.has_resolver("repo_root"):
    OmegaConf.register_new_resolver("repo_root", lambda: str(REPO_ROOT))


def resolve(ref: str):
    """`"package.module:function"` -> the object (a stage's work, a scenario's drawing function), imported when used."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


@functools.cache
def signature(target: str) -> dict | None:
    """Keyword -> annotation (None: the target checks it) of `target`; None: not checkable (`**kwargs`, a source not
    found). Ours are imported (none imports torch); another package's are read from its source (no import)."""
    module, _, name = target.rpartition(".")
    if module.split(".")[0] != "pipeline":
        return _keys_from_source(module, name)
    try:
        obj = getattr(importlib.import_module(module), name)
    except Exception as err:  # noqa: BLE001 - any import problem is the config's fault
        raise ConfigError("_target_", f"cannot import {target!r} ({str(err).splitlines()[0]})") from None
    hints = type_hints(obj if dataclasses.is_dataclass(obj) or not inspect.isclass(obj) else obj.__init__)
    every = inspect.signature(obj).parameters.values()
    return None if any(p.kind is p.VAR_KEYWORD for p in every) else \
        {p.name: hints.get(p.name) for p in every if p.kind is not p.VAR_POSITIONAL}


def _keys_from_source(module: str, name: str, depth: int = 0) -> dict | None:
    """Another package's `module.name`'s keywords, read from its source (no import), following re-exports."""
    top, *rest = module.split(".")
    spec = importlib.util.find_spec(top) if depth < 8 else None
    base = Path(next(iter(spec.submodule_search_locations))).joinpath(*rest) \
        if spec is not None and spec.submodule_search_locations else None
    path = next((c for c in (base / "__init__.py", base.with_suffix(".py")) if c.is_file()), None) if base else None
    for node in ast.parse(path.read_text()).body if path else ():
        if isinstance(node, ast.ImportFrom) and any((a.asname or a.name) == name for a in node.names):
            package = module.split(".")[: None if path.name == "__init__.py" else -1]
            where = package[: len(package) - node.level + 1] if node.level else []
            real = next(a.name for a in node.names if (a.asname or a.name) == name)
            return _keys_from_source(".".join(p for p in (*where, node.module) if p), real, depth + 1)
        if isinstance(node, ast.ClassDef | ast.FunctionDef) and node.name == name:
            init = node if isinstance(node, ast.FunctionDef) else \
                next((b for b in node.body if isinstance(b, ast.FunctionDef) and b.name == "__init__"), None)
            a = init.args if init is not None else None
            return None if a is None or a.kwarg is not None else \
                {x.arg: None for x in (*a.posonlyargs, *a.args, *a.kwonlyargs) if x.arg != "self"}
    return None  # a plugin not installed: Hydra says so when it builds the node


def _walk(node, path: str = "") -> Iterable[tuple[str, DictConfig]]:
    """Every mapping under `node` with its path; not Hydra's settings, nor an interpolation (checked where written)."""
    if isinstance(node, DictConfig):
        yield path, node
        items = [(f"{path}.{k}" if path else str(k), k) for k in node.keys() if path or k != "hydra"]
    else:
        items = [(f"{path}[{i}]", i) for i in range(len(node))] if isinstance(node, ListConfig) else []
    for where, k in items:
        if not (OmegaConf.is_interpolation(node, k) or OmegaConf.is_missing(node, k)):
            yield from _walk(node[k], where)


def plain_value(node: DictConfig, key):
    """A node's value as plain Python, or `...` when it cannot be resolved here (`${hydra:...}` outside a run)."""
    try:
        value = OmegaConf.select(node, str(key), throw_on_resolution_failure=True)
    except Exception:  # noqa: BLE001 - an interpolation that needs a running Hydra app
        return ...
    return OmegaConf.to_container(value, resolve=True) if isinstance(value, DictConfig | ListConfig) else value


def check_node(node: DictConfig, path: str) -> None:
    """One `_target_` node's keys and values against its target's signature (:func:`pipeline.schema.check_once`)."""
    try:
        params = signature(str(node["_target_"]))
    except ConfigError as err:
        raise ConfigError(f"{path}._target_" if path else "_target_", err.reason) from None
    values = {k: plain_value(node, k) for k in node.keys()}
    if params is None:
        return
    for k, value in values.items():
        where = f"{path}.{k}" if path else str(k)
        if k not in params and k not in META_KEYS:
            raise ConfigError(where, f"unknown key ({node['_target_']} takes {', '.join(params)})")
        if k not in META_KEYS and value is not ... and not (isinstance(value, dict) and "_target_" in value):
            check_once(value, params[k], where)  # (a node is checked as a node)


def check_schema(cfg: DictConfig, added: Iterable[str] = ()) -> None:
    """Unknown keys and wrong values anywhere in `cfg` (targets' signatures) and keys added by `+`/`++` overrides."""
    for path, node in _walk(cfg):
        if isinstance(node.get("_target_"), str):
            check_node(node, path)
    for key in added:  # one added to a `_target_` node is checked with its node
        node = OmegaConf.select(cfg, key.rpartition(".")[0]) if "." in key else cfg
        if not (isinstance(node, DictConfig) and "_target_" in node):
            raise ConfigError(key, "unknown key (not in the config; check the spelling: `+` does not add keys here)")


def settings(cfg: DictConfig, cls):
    """A stage's root-level settings (its config file's keys that are no node) as the dataclass `cls`, checked."""
    return cls(**{f.name: plain_value(cfg, f.name) for f in dataclasses.fields(cls) if f.name in cfg})


def build(node, path: str, /, **kwargs):
    """`instantiate(node)(**kwargs)`: the object a node describes, keys and types checked first, errors naming `path`."""
    from hydra.errors import InstantiationException
    from hydra.utils import instantiate

    node = node if isinstance(node, DictConfig) else OmegaConf.create(node)
    if "_target_" not in node:
        raise ConfigError(path, "needs a `_target_` (pick one of the options of its config group)")
    check_node(node, path)
    try:  # partial: Hydra would turn a dataclass keyword (a Scene) into a config node
        part = instantiate(node, _partial_=True, _convert_="all", _recursive_=False)
    except InstantiationException as err:  # a target that does not import (another package's plugin)
        raise ConfigError(f"{path}._target_", str(err).splitlines()[0]) from None
    try:
        obj = part(**kwargs)
    except ConfigError as err:  # named by the node's path, but a field of an object passed in (a controller's
        field = err.field  # `scene`) keeps its own name (`scene.obstacles[0,4]`, not `controller.obstacles[0,4]`)
        if path and not any(field == o or field.startswith((o + ".", o + "[")) for o in (*kwargs, path)):
            field = f"{path}.{field.split('.', 1)[-1]}" if field not in ("", "_target_") else path
        raise ConfigError(field, err.reason) from None
    except (TypeError, ValueError) as err:  # (a PipelineError other than a ConfigError is neither: it is raised)
        raise ConfigError(path, f"invalid parameters for {node['_target_']}: {err}") from None
    return obj


def compose(config_name: str, overrides: list[str] | None = None, *, check: bool = True) -> DictConfig:
    """Hydra's compose (also in a running app), errors as one line, no `hydra:` interpolations. The group choices
    compose once per process (0.15 s); a call gets its own copy (unpickled, 1.4 ms) with its values set by Hydra."""
    from hydra._internal.config_loader_impl import ConfigLoaderImpl
    from hydra.core.global_hydra import GlobalHydra
    from hydra.core.override_parser.overrides_parser import OverridesParser

    try:
        parsed = OverridesParser.create().parse_overrides(list(overrides or ()))
        kinds = [_kind(o) for o in parsed]
        late = [o for o, k in zip(parsed, kinds) if k == "value" and None not in kinds]  # else all as Hydra, in order
        early = tuple(o.input_line for o in parsed if o not in late)
        cfg = pickle.loads(_composed(config_name, early, GlobalHydra.instance().is_initialized()))
        ConfigLoaderImpl._apply_overrides_to_config(late, cfg)
    except Exception as err:  # noqa: BLE001 - Hydra's errors (no stage code runs here), as one line
        raise hydra_error(err) from None
    return check_schema(cfg) or cfg if check else cfg


def _kind(o) -> str | None:
    """"group" (conf/'s or Hydra's: picks defaults), "value" (Hydra sets it after composing), None (an add, ...)."""
    group = o.key_or_group.startswith("hydra") or (CONF_DIR / o.key_or_group.replace(".", "/")).is_dir()
    if o.is_add() or o.is_force_add() or o.is_sweep_override():
        return None
    return "group" if group else None if o.package or o.is_delete() or isinstance(o.value(), dict) else "value"


@functools.lru_cache(maxsize=256)
def _composed(config_name: str, overrides: tuple[str, ...], inside_app: bool) -> bytes:
    """One composition, pickled (an error is raised, never kept), with a running app's Hydra or one of its own."""
    import hydra

    with contextlib.nullcontext() if inside_app else \
            hydra.initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
        return pickle.dumps(hydra.compose(config_name=config_name, overrides=list(overrides)))
