"""A target's signature, the schema of its config node: parameter names, annotated types, defaults.

:func:`signature` reads a target's parameters. A target whose module imports torch or Lightning (at its top
level, or through the project's modules it imports), and a target outside this project, is read from its source
without being imported (a config error then answers in about a second): its keys are checked at composition; so
are the values of the project's own targets (their simple annotations: builtins, `X | None`, `Literal`,
`Sequence` as a list, the aliases of :mod:`pipeline.schema` and `Annotated[X, Range(...)]`); another package's
values, by its constructor. :mod:`pipeline.schema` checks a value against such an annotation.
"""

from __future__ import annotations

import ast
import dataclasses
import functools
import importlib
import importlib.util
import inspect
import sys
import typing
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any

from pipeline.errors import ConfigError
from pipeline.schema import ALIASES, RULES

HEAVY = ("torch", "lightning", "pytorch_lightning", "torchvision", "tensorboard", "mlflow", "optuna")


@dataclass(frozen=True)
class Signature:
    """The keywords a target takes: `params` name -> annotation (None: not checked), `required` those without a
    default; `any_keyword`: it takes `**kwargs` (no key is unknown)."""

    target: str
    params: dict[str, Any]
    required: tuple[str, ...] = ()
    any_keyword: bool = False


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
        hints = typing.get_type_hints(obj if dataclasses.is_dataclass(obj) else fn, include_extras=True)
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


# annotations of a target read from its source (not imported): builtins, `X | None`, `Literal[...]`,
# `Sequence[X]` read as `list[X]` (a config value is a list), the schema's aliases and `Annotated[X, Range(...)]`
# (a rule of pipeline.schema with constant arguments); anything else is not checked here (None)
_SOURCE_NAMES = {"float": float, "int": int, "bool": bool, "str": str, "list": list, "tuple": tuple, "dict": dict,
                 "Sequence": list, "Literal": typing.Literal, "Any": Any, "Annotated": Annotated, **ALIASES}


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
        if base is Annotated:
            return Annotated[(_read_annotation(items[0]), *(_read_rule(e) for e in items[1:]))]
        if base is typing.Literal:
            if not all(isinstance(e, ast.Constant) for e in items):
                raise ValueError("Literal of non-constants")
            return typing.Literal[tuple(e.value for e in items)]
        args = tuple(Ellipsis if isinstance(e, ast.Constant) and e.value is Ellipsis else _read_annotation(e)
                     for e in items)
        return base[args if len(args) > 1 else args[0]]
    raise ValueError("not a simple annotation")


def _read_rule(node):
    """`Range(gt=0)` (a rule of :mod:`pipeline.schema` called with constants) read from source."""
    rules = {r.__name__: r for r in RULES}
    if not (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id in rules):
        raise ValueError("not a rule")
    return rules[node.func.id](*(ast.literal_eval(a) for a in node.args),
                               **{k.arg: ast.literal_eval(k.value) for k in node.keywords})
