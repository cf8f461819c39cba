"""A target's signature, the schema of its config node: its keywords, their annotations, which are required.

A project target whose module does not import torch or Lightning (read from the sources, through the project
modules it imports) is imported and inspected. Any other target is read from its source without being imported,
so that a config error answers before torch is: its keywords, and for the project's own targets their
annotations, evaluated among the names of :mod:`pipeline.schema` and :mod:`typing` (`test_config_truth` checks
that every keyword of every target the configs name has an annotation that evaluates).
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
import importlib.util
import inspect
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pipeline.schema
from pipeline.errors import ConfigError

HEAVY = ("torch", "lightning", "pytorch_lightning", "torchvision", "tensorboard", "mlflow", "optuna")
NAMES = {**vars(typing), **vars(pipeline.schema), "Sequence": list}  # a config's sequence is a list


@dataclass(frozen=True)
class Signature:
    """`params`: keyword -> annotation (None: not checked); `required`: those without a default; `any_keyword`:
    it takes `**kwargs` (no key is unknown)."""

    target: str
    params: dict[str, Any]
    required: tuple[str, ...] = ()
    any_keyword: bool = False


@functools.cache
def signature(target: str) -> Signature | None:
    """The parameters of `target` (a dotted path), or None when they cannot be read."""
    module, _, name = target.rpartition(".")
    if module.split(".")[0] != "pipeline" or _heavy(module):
        return _from_source(module, name)
    try:
        obj = getattr(importlib.import_module(module), name)
    except Exception as err:  # noqa: BLE001 - any import problem is the config's fault
        raise ConfigError("_target_", f"cannot import {target!r} ({str(err).splitlines()[0]})") from None
    if inspect.isclass(obj) and obj.__init__ is object.__init__ and not dataclasses.is_dataclass(obj):
        return Signature(target, {})
    fn = obj.__init__ if inspect.isclass(obj) else obj
    hints = pipeline.schema.type_hints(obj if dataclasses.is_dataclass(obj) else fn)
    try:
        every = inspect.signature(fn).parameters.values()
    except (TypeError, ValueError):  # a builtin without a signature: accept anything
        return None
    params = [p for p in every if p.name != "self" and p.kind not in (p.VAR_POSITIONAL, p.VAR_KEYWORD)]
    return Signature(target, {p.name: hints.get(p.name) for p in params},
                     tuple(p.name for p in params if p.default is p.empty), any(p.kind is p.VAR_KEYWORD for p in every))


def _file(module: str) -> Path | None:
    """The source file of `module`, found without importing it (nor its parent packages)."""
    top, *rest = module.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or not spec.submodule_search_locations:
        return Path(spec.origin) if spec is not None and spec.origin and not rest else None
    base = Path(next(iter(spec.submodule_search_locations))).joinpath(*rest)
    return next((c for c in (base / "__init__.py", base.with_suffix(".py")) if c.is_file()), None)


def _imports(module: str) -> list[str]:
    """The modules `module`'s top level imports (relative imports resolved)."""
    path = _file(module)
    if path is None:
        return []
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    out = []
    for node in ast.parse(path.read_text()).body:
        if isinstance(node, ast.Import):
            out += [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            src = ".".join(base + ([node.module] if node.module else []))
            out += [src] + [f"{src}.{a.name}" for a in node.names]
    return out


_BUSY: set[str] = set()


@functools.cache
def _heavy(module: str) -> bool:
    """Whether importing the project module `module` imports torch or Lightning: its packages' `__init__`s, its
    own top-level imports and the project modules those import."""
    if module in _BUSY:  # a package's modules import each other: decided by the others
        return False
    _BUSY.add(module)
    try:
        parts = module.split(".")
        mods = [".".join(parts[:i]) for i in range(2, len(parts))] + _imports(module)
        return any(m.split(".")[0] in HEAVY or (m.split(".")[0] == "pipeline" and m != module and _file(m) is not None
                                                 and _heavy(m)) for m in mods)
    finally:
        _BUSY.discard(module)


def _from_source(module: str, name: str, depth: int = 0) -> Signature | None:
    """The keywords of `module.name` read from its source (following `from X import Y` re-exports)."""
    path = _file(module) if depth < 8 else None
    if path is None:
        return None
    tree = ast.parse(path.read_text())
    for node in tree.body:
        if isinstance(node, ast.ClassDef | ast.FunctionDef) and node.name == name:
            init = node if isinstance(node, ast.FunctionDef) else \
                next((b for b in node.body if isinstance(b, ast.FunctionDef) and b.name == "__init__"), None)
            if init is None and "dataclass" in ast.unparse(node.decorator_list):  # its fields are its keywords
                fields = [b for b in node.body if isinstance(b, ast.AnnAssign) and isinstance(b.target, ast.Name)]
                init = ast.FunctionDef(name, ast.arguments([], [], None, [ast.arg(f.target.id, f.annotation)
                                                                             for f in fields],
                                                           [f.value for f in fields], None, []), [], [])
            return None if init is None else _keywords(f"{module}.{name}", init)
    for imp in _imports(module):
        if imp.rpartition(".")[2] == name and imp != f"{module}.{name}":  # a re-export
            return _from_source(*imp.rpartition(".")[::2], depth + 1)
    return None


def _keywords(target: str, fn: ast.FunctionDef) -> Signature:
    a = fn.args
    pos = [x for x in (*a.posonlyargs, *a.args)]
    required = [x.arg for x in pos[: len(pos) - len(a.defaults)]]
    required += [x.arg for x, d in zip(a.kwonlyargs, a.kw_defaults) if d is None]
    own = target.split(".")[0] == "pipeline"  # another package's annotations are its constructor's to check
    params = {x.arg: (_annotation(x.annotation) if own else None) for x in (*pos, *a.kwonlyargs) if x.arg != "self"}
    return Signature(target, params, tuple(r for r in required if r != "self"), a.kwarg is not None)


def _annotation(node):
    """An annotation from source, evaluated among the names of pipeline.schema and typing (None: it names anything
    else, or there is none)."""
    try:
        text = ast.unparse(node) if node is not None else None
        text = ast.literal_eval(text) if text and text[0] in "'\"" else text  # a quoted annotation
        return eval(text, dict(NAMES)) if text else None  # noqa: S307 - the project's own source
    except Exception:  # noqa: BLE001
        return None
