"""The schema of a config node is the signature of its `_target_`: parameter names, annotated types, defaults.

:func:`signature` reads a target's parameters; :func:`check_value` checks a value against an annotation
(numbers, strings, booleans, `Literal` choices, `X | None`, lists and tuples, mappings, and dataclasses, whose
keys and field types are checked recursively), raising one :class:`ConfigError` naming the key. A target whose
module imports torch or Lightning (at its top level, or through the project's modules it imports), and a target
outside this project, is read from its source without being imported (a config error then answers in about a
second): its keys are checked at composition; so are the values of the project's own targets (their simple
annotations: builtins, `X | None`, `Literal`, `Sequence` as a list); another package's values, by its constructor.
"""

from __future__ import annotations

import ast
import collections.abc
import dataclasses
import functools
import importlib
import importlib.util
import inspect
import math
import sys
import types
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from pipeline.errors import ConfigError

HEAVY = ("torch", "lightning", "pytorch_lightning", "torchvision", "tensorboard", "mlflow", "optuna")


@dataclass(frozen=True)
class Signature:
    """The keywords a target takes: `params` name -> annotation (None: not checked), `required` those without a
    default; `any_keyword`: it takes `**kwargs` (no key is unknown)."""

    target: str
    params: dict[str, Any]
    required: tuple[str, ...] = ()
    any_keyword: bool = False


# ------------------------------------------------------------------------------------------- signatures
@functools.cache
def signature(target: str) -> Signature | None:
    """The parameters of `target` (a dotted path), or None when they cannot be read."""
    module, _, name = target.rpartition(".")
    light = module.split(".")[0] == "pipeline" and not _imports_heavy(module)
    if light or module in sys.modules:
        try:
            obj = getattr(importlib.import_module(module), name)
        except Exception as err:  # noqa: BLE001 - any import problem is the config's fault
            raise ConfigError("_target_", f"cannot import {target!r} ({str(err).splitlines()[0]})") from None
        return _inspect(target, obj)
    return _from_source(target)


def _inspect(target: str, obj) -> Signature | None:
    if inspect.isclass(obj) and obj.__init__ is object.__init__ and not dataclasses.is_dataclass(obj):
        return Signature(target, {})
    fn = obj.__init__ if inspect.isclass(obj) else obj
    try:
        sig = inspect.signature(fn)
    except (TypeError, ValueError):  # builtins without a signature: accept anything
        return None
    try:
        hints = typing.get_type_hints(obj if dataclasses.is_dataclass(obj) else fn)
    except Exception:  # noqa: BLE001 - unresolvable annotations: names only
        hints = {}
    params, required, var_kw = {}, [], False
    for n, p in sig.parameters.items():
        if n == "self" or p.kind is p.VAR_POSITIONAL:
            continue
        if p.kind is p.VAR_KEYWORD:
            var_kw = True
            continue
        params[n] = hints.get(n)
        if p.default is p.empty:
            required.append(n)
    return Signature(target, params, tuple(required), var_kw)


_HEAVY: dict[str, bool] = {}


def _imports_heavy(module: str) -> bool:
    """Whether importing the project module `module` imports torch or Lightning (read from the sources: its own
    top-level imports, its packages' `__init__`, and the project modules those import)."""
    if module not in _HEAVY:
        _HEAVY[module] = False  # provisional while its imports are read (a package's modules import each other)
        _HEAVY[module] = _reads_heavy(module)
    return _HEAVY[module]


def _reads_heavy(module: str) -> bool:
    parts = module.split(".")
    for i in range(2, len(parts)):  # a submodule's import runs its packages' __init__ first
        if _imports_heavy(".".join(parts[:i])):
            return True
    path = _module_file(module)
    if path is None:
        return False
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in ast.parse(path.read_text()).body:
        names = []
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            src = node.module or ""
            if node.level:
                base = package.split(".")
                src = ".".join(base[: len(base) - node.level + 1] + ([src] if src else []))
            names = [src] + [f"{src}.{a.name}" for a in node.names]
        for n in names:
            top = n.split(".")[0]
            if top in HEAVY:
                return True
            if top == "pipeline" and n != module and _module_file(n) is not None and _imports_heavy(n):
                return True
    return False


def _module_file(module: str) -> Path | None:
    """The source file of `module`, found without importing it (nor its parent packages)."""
    top, *rest = module.split(".")
    spec = importlib.util.find_spec(top)
    if spec is None or not spec.submodule_search_locations:
        return Path(spec.origin) if spec is not None and spec.origin and not rest else None
    base = Path(next(iter(spec.submodule_search_locations))).joinpath(*rest)
    for cand in (base / "__init__.py", base.with_suffix(".py")):
        if cand.is_file():
            return cand
    return None


def _from_source(target: str, depth: int = 0) -> Signature | None:
    """Parameter names of `target` read from its source (following `from X import Y` re-exports)."""
    module, _, name = target.rpartition(".")
    path = _module_file(module) if depth < 8 else None
    if path is None:
        return None
    tree = ast.parse(path.read_text())
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    for node in tree.body:
        if isinstance(node, ast.ClassDef) and node.name == name:
            init = next((b for b in node.body if isinstance(b, ast.FunctionDef) and b.name == "__init__"), None)
            return _args(target, init) if init is not None else None
        if isinstance(node, ast.FunctionDef) and node.name == name:
            return _args(target, node)
    for node in ast.walk(tree):  # a re-export
        if isinstance(node, ast.ImportFrom):
            for alias in node.names:
                if (alias.asname or alias.name) == name:
                    src = node.module or ""
                    if node.level:
                        parts = package.split(".")
                        src = ".".join(parts[: len(parts) - node.level + 1] + ([src] if src else []))
                    return _from_source(f"{src}.{alias.name}", depth + 1)
    return None


def _args(target: str, fn: ast.FunctionDef) -> Signature:
    a = fn.args
    args = [x for x in (*a.posonlyargs, *a.args, *a.kwonlyargs) if x.arg != "self"]
    n_pos = len(a.posonlyargs) + len(a.args)
    pos_defaults = n_pos - len(a.defaults)
    pos = [x.arg for x in (*a.posonlyargs, *a.args)]
    required = [n for i, n in enumerate(pos) if i >= 0 and i < pos_defaults and n != "self"]
    required += [x.arg for x, d in zip(a.kwonlyargs, a.kw_defaults) if d is None]
    own = target.split(".")[0] == "pipeline"  # the project's annotations are simple; another package's are not read
    params = {x.arg: (_annotation(x.annotation) if own else None) for x in args}
    return Signature(target, params, tuple(required), a.kwarg is not None)


# annotations of a target read from its source (not imported): builtins, `X | None`, `Literal[...]`, and
# `Sequence[X]` read as `list[X]` (a config value is a list); anything else is not checked here (None)
_SOURCE_NAMES = {"float": float, "int": int, "bool": bool, "str": str, "list": list, "tuple": tuple, "dict": dict,
                 "Sequence": list, "Literal": typing.Literal, "Any": Any}


def _annotation(node):
    try:
        return _read_annotation(node)
    except (KeyError, TypeError, ValueError):
        return None


def _read_annotation(node):
    if node is None:
        raise ValueError("no annotation")
    if isinstance(node, ast.Constant):
        if isinstance(node.value, str) and not node.value.isidentifier():  # a quoted annotation
            return _read_annotation(ast.parse(node.value, mode="eval").body)
        return node.value if node.value is not None else type(None)
    if isinstance(node, ast.Name):
        return _SOURCE_NAMES[node.id]
    if isinstance(node, ast.Attribute) and isinstance(node.value, ast.Name) and node.value.id in ("typing", "abc"):
        return _SOURCE_NAMES[node.attr]
    if isinstance(node, ast.BinOp) and isinstance(node.op, ast.BitOr):
        return _read_annotation(node.left) | _read_annotation(node.right)
    if isinstance(node, ast.Subscript):
        base = _read_annotation(node.value)
        items = node.slice.elts if isinstance(node.slice, ast.Tuple) else [node.slice]
        if base is typing.Literal:
            if not all(isinstance(e, ast.Constant) for e in items):
                raise ValueError("Literal of non-constants")
            return typing.Literal[tuple(e.value for e in items)]
        args = tuple(Ellipsis if isinstance(e, ast.Constant) and e.value is Ellipsis else _read_annotation(e)
                     for e in items)
        return base[args if len(args) > 1 else args[0]]
    raise ValueError("not a simple annotation")


# ---------------------------------------------------------------------------------------------- types
def describe(tp) -> str:
    """The annotation `tp` in words (for error messages)."""
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(describe(a) for a in args) + (" (or null)" if len(args) < len(typing.get_args(tp)) else "")
    if origin is typing.Literal:
        return "one of " + ", ".join(str(c) for c in typing.get_args(tp))
    if origin in (list, tuple, collections.abc.Sequence):
        args = typing.get_args(tp)
        return f"a list of {describe(args[0]) if args else 'values'}"
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return f"a mapping with keys {', '.join(f.name for f in dataclasses.fields(tp) if f.init)}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def check_value(value, tp, path: str) -> None:
    """Raise `ConfigError(path, ...)` unless `value` (plain: from a composed config) fits the annotation `tp`."""
    if tp is None or tp is Any or tp is object:
        return
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        options = typing.get_args(tp)
        if value is None and type(None) in options:
            return
        inner = []
        for opt in options:
            try:
                check_value(value, opt, path)
                return
            except ConfigError as err:
                if err.field != path:  # the value has this option's shape: the error is inside it
                    inner.append(err)
        if inner:
            raise inner[0]
        raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")
    if origin is typing.Literal:
        if value not in typing.get_args(tp):
            raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")
        return
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        _check_dataclass(value, tp, path)
        return
    if origin in (list, tuple, collections.abc.Sequence) or tp in (list, tuple):  # a Sequence: a list in a config
        if not isinstance(value, list | tuple):
            raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        fixed = origin is tuple and len(args) > 1
        if fixed and len(value) != len(args):
            raise ConfigError(path, f"must be a list of {len(args)} values, got {value!r}")
        for i, v in enumerate(value):
            check_value(v, args[i] if fixed else (args[0] if args else None), f"{path}[{i}]")
        return
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            raise ConfigError(path, f"must be a mapping, got {value!r}")
        args = typing.get_args(tp)
        for k, v in value.items():
            check_value(v, args[1] if len(args) == 2 else None, f"{path}.{k}")
        return
    if not _scalar_ok(value, tp):
        raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")


def _scalar_ok(value, tp) -> bool:
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    if isinstance(tp, type):
        return isinstance(value, tp) or isinstance(value, dict)  # an object passed by the caller, or its node
    return True


def _check_dataclass(value, cls, path: str) -> None:
    if isinstance(value, cls):
        return
    if not isinstance(value, dict):
        raise ConfigError(path, f"must be {describe(cls)}, got {value!r}")
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(value) - set(fields))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}", f"unknown key ({cls.__name__} takes {', '.join(fields)})")
    hints = typing.get_type_hints(cls)
    for name, f in fields.items():
        if name not in value:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{path}.{name}", f"missing ({cls.__name__} needs it)")
            continue
        check_value(value[name], hints.get(name), f"{path}.{name}")
