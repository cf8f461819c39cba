"""Config is the single source of truth: every node names its `_target_`, whose typed signature is its schema.

:func:`check_schema` (run by :func:`compose`): every key of a `_target_` node must be a keyword of its target (no
`**kwargs` swallowing typos) and every value must fit the keyword's annotation (:mod:`pipeline.schema`).
:func:`build` instantiates a node; a value its constructor rejects (a range, a cross-field rule) is a
:class:`ConfigError` naming the node's path.
"""
from __future__ import annotations

import ast
import contextlib
import dataclasses
import functools
import importlib
import importlib.util
import inspect
from collections.abc import Iterable
from pathlib import Path

from omegaconf import DictConfig, ListConfig, OmegaConf

from pipeline.errors import ConfigError, PipelineError, hydra_error
from pipeline.repo import CONF_DIR, REPO_ROOT
from pipeline.schema import check_once, type_hints

META_KEYS = {"_target_", "_partial_", "_convert_", "_recursive_", "_args_"}
if not OmegaConf.has_resolver("repo_root"):
    OmegaConf.register_new_resolver("repo_root", lambda: str(REPO_ROOT))


def resolve(ref: str):
    """`"package.module:function"` -> the object (a stage's work, a scenario's drawing function), imported when used."""
    module, _, name = ref.partition(":")
    return getattr(importlib.import_module(module), name)


# ------------------------------------------------------------------------------------ signatures
@functools.cache
def signature(target: str) -> dict | None:
    """Keyword -> annotation (None: the target checks it) of `target` (a dotted path); None where the keys cannot be
    checked: it takes `**kwargs`, or it is another package's whose source (a plugin not installed) is not found. A
    target of this project is imported (none imports torch: a torch class takes a typed spec, e.g.
    :class:`pipeline.perception.spec.MapSpec`); another package's keys are read from its source (Lightning's
    import would load torch before a config error could answer)."""
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
    """The keywords of another package's `module.name` (their values are its constructor's to check), read from its
    source without importing it, following `from X import name` re-exports."""
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


# ----------------------------------------------------------------------------------------- schema
def _walk(node, path: str = "") -> Iterable[tuple[str, DictConfig]]:
    """Every mapping under `node` with its path; not Hydra's own settings, nor an interpolation (`hybrid:
    ${controller}`: checked where it is written)."""
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
    """The keys and values of one `_target_` node against its target's signature (each value once per process:
    :func:`pipeline.schema.check_once`)."""
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
    """A stage's root-level settings (the keys of its config file that are no node of their own) as the typed
    dataclass `cls`, which checks them (`@checked("")`)."""
    return cls(**{f.name: plain_value(cfg, f.name) for f in dataclasses.fields(cls) if f.name in cfg})


# ------------------------------------------------------------------------------------------ build
def build(node, path: str, /, **kwargs):
    """`instantiate(node)(**kwargs)`: the object a config node describes, its keys and types checked first, errors
    naming `path`."""
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


# ------------------------------------------------------------------------------------------ compose
def compose(config_name: str, overrides: list[str] | None = None, *, check: bool = True) -> DictConfig:
    """Compose a config with Hydra's compose API, also from inside a running `@hydra.main` app (tests, notebooks,
    the paper DAG); Hydra's composition errors are one :class:`ConfigError` line. `hydra:` interpolations are not
    available here: `paths.output_dir` must be overridden (or the caller sets it) before use."""
    from hydra import compose as _compose
    from hydra import initialize_config_dir
    from hydra.core.global_hydra import GlobalHydra

    try:  # inside a running app (tests, the paper DAG): its Hydra; else one initialized for this call only
        with contextlib.nullcontext() if GlobalHydra.instance().is_initialized() else \
                initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
            cfg = _compose(config_name=config_name, overrides=list(overrides or []))
    except PipelineError:
        raise
    except Exception as err:  # noqa: BLE001 - Hydra's composition errors, as one line
        raise hydra_error(err) from None
    if check:
        check_schema(cfg)
    return cfg
