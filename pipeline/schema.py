"""The schema of a config node is the signature of its `_target_` (:mod:`pipeline.signatures`).

:func:`check_value` checks a value against an annotation (numbers, strings, booleans, `Literal`, `X | None`, lists,
tuples, mappings, dataclasses key by key, `Annotated[X, rule]` with the rules below), raising one
:class:`ConfigError` naming the key. An object built from Python checks its arguments the same way (:func:`checked`
on its class, :func:`check_fields` on a dataclass instance); objects keep only their cross-field rules.
"""
from __future__ import annotations

import collections.abc
import contextvars
import dataclasses
import functools
import inspect
import math
import numbers
import re
import sys
import types
import typing
from dataclasses import dataclass
from typing import Annotated, Any

import numpy as np

from pipeline.errors import ConfigError
from pipeline.repo import CONF_DIR


# ------------------------------------------------------------------------------------------------ rules
# a rule of `Annotated[X, rule]`: `holds(value)`, and `describe(words of X)` for the message
@dataclass(frozen=True)
class Range:
    """A number's interval (on a list: every element's)."""

    gt: float | None = None
    ge: float | None = None
    lt: float | None = None
    le: float | None = None

    def holds(self, v) -> bool:
        if isinstance(v, list | tuple):
            return all(self.holds(x) for x in v)
        return ((self.gt is None or v > self.gt) and (self.ge is None or v >= self.ge)
                and (self.lt is None or v < self.lt) and (self.le is None or v <= self.le))

    def describe(self, inner: str) -> str:
        lo = f"({self.gt:g}" if self.gt is not None else f"[{self.ge:g}" if self.ge is not None else None
        hi = f"{self.lt:g})" if self.lt is not None else f"{self.le:g}]" if self.le is not None else None
        if lo and hi:
            return f"{inner} in {lo}, {hi}"
        if lo:
            return f"{inner} > {self.gt:g}" if self.gt is not None else f"{inner} >= {self.ge:g}"
        return f"{inner} < {self.lt:g}" if self.lt is not None else f"{inner} <= {self.le:g}"


@dataclass(frozen=True)
class NonEmpty:
    """A list with at least one element (`distinct`: and no repeats)."""

    distinct: bool = False

    def holds(self, v) -> bool:
        return len(v) > 0 and (not self.distinct or len({repr(x) for x in v}) == len(v))

    def describe(self, inner: str) -> str:
        return f"a non-empty list of {'distinct ' if self.distinct else ''}{inner.removeprefix('a list of ')}"


@dataclass(frozen=True)
class Pattern:
    """A string that matches `regex` (whole), described as `words`."""

    regex: str
    words: str

    def holds(self, v) -> bool:
        return re.fullmatch(self.regex, v) is not None

    def describe(self, inner: str) -> str:
        return self.words


@dataclass(frozen=True)
class Ascending:
    """Numbers in increasing order (`[min, max]` with `min < max`; `strict=False`: `<=`)."""

    strict: bool = True

    def holds(self, v) -> bool:
        return all(a < b if self.strict else a <= b for a, b in zip(v, v[1:]))

    def describe(self, inner: str) -> str:
        order = "<" if self.strict else "<="
        return f"{inner}, [min, max] with min {order} max" if inner.startswith("a list of 2 ") else \
            f"{inner} in increasing order"


@dataclass(frozen=True)
class Node:
    """A config node that names its `_target_` (an option of a config group), built where it is used."""

    def holds(self, v) -> bool:
        return isinstance(v, dict) and "_target_" in v

    def describe(self, inner: str) -> str:
        return "a config node with a `_target_` (an option of its config group)"


@dataclass(frozen=True)
class Option:
    """The name of an option of a config group (`conf/<group>/<name>.yaml`)."""

    group: str

    def holds(self, v) -> bool:
        return (CONF_DIR / self.group / f"{v}.yaml").is_file()

    def describe(self, inner: str) -> str:
        return f"an option of conf/{self.group}/ ({', '.join(sorted(p.stem for p in (CONF_DIR / self.group).glob('*.yaml')))})"


Positive = Annotated[float, Range(gt=0)]
NonNegative = Annotated[float, Range(ge=0)]
Share = Annotated[float, Range(ge=0, le=1)]  # a probability, a share of the images
OpenShare = Annotated[float, Range(gt=0, lt=1)]  # the open unit interval
PositiveInt = Annotated[int, Range(ge=1)]
NonNegativeInt = Annotated[int, Range(ge=0)]
Pair = tuple[float, float]  # a point [x, y]
Interval = Annotated[tuple[float, float], Ascending()]  # [min, max], min < max
RGB = Annotated[tuple[float, float, float], Range(ge=0, le=255)]  # a colour, intensity levels
Kappa = Annotated[float, Range(ge=0, le=255)]  # a pixel attack's budget, in intensity levels (of 255)
Name = Annotated[str, Pattern(r"[^./\\\s](?:[^/\\]*[^/\\\s])?",
                              "a non-empty folder-safe name (no '/', '\\', leading '.' or surrounding spaces)")]
Device = Annotated[str, Pattern(r"auto|cpu|cuda(?::\d+)?", "auto, cpu, cuda or cuda:N")]
RULES = (Range, NonEmpty, Pattern, Ascending, Node, Option)


# ---------------------------------------------------------------------------------------------- types
def describe(tp) -> str:
    """The annotation `tp` in words (for error messages)."""
    origin = typing.get_origin(tp)
    if origin is Annotated:
        inner, *rules = typing.get_args(tp)
        words = describe(inner)
        for r in rules:
            words = r.describe(words) if isinstance(r, RULES) else words
        return words
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(describe(a) for a in args) + (" (or null)" if len(args) < len(typing.get_args(tp)) else "")
    if origin is typing.Literal:
        return "one of " + ", ".join(str(c) for c in typing.get_args(tp))
    if origin in (list, tuple, collections.abc.Sequence):
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        if origin is tuple and len(args) > 1:
            return f"a list of {len(args)} {_plural(describe(args[0]))}" if len(set(args)) == 1 else \
                f"a list of {len(args)} values"
        return f"a list of {_plural(describe(args[0])) if args else 'values'}"
    if origin is dict:
        return "a mapping"
    if dataclasses.is_dataclass(tp):
        return f"a mapping with keys {', '.join(f.name for f in dataclasses.fields(tp) if f.init)}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(
        tp, getattr(tp, "__name__", str(tp)))


def _plural(words: str) -> str:
    """`a number` -> `numbers`, `an integer > 0` -> `integers > 0` (the element of a list, in words)."""
    for one, many in (("a number", "numbers"), ("an integer", "integers"), ("a string", "strings"),
                      ("a list", "lists"), ("a mapping", "mappings")):
        if words.startswith(one):
            return many + words[len(one):]
    return words


def check_value(value, tp, path: str) -> None:
    """Raise `ConfigError(path, ...)` unless `value` (plain: from a composed config, or what a caller passes)
    fits the annotation `tp`: `must be <tp in words>, got <value>`, naming the innermost key or element."""
    if not _fits(value, tp, path):
        raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")


def _fits(value, tp, path: str) -> bool:
    """Whether `value` has the shape (and the rules) of `tp` at `path`; an element or key inside it that does not
    fit raises, naming its own path."""
    if tp is None or tp is Any or tp is object:
        return True
    if getattr(value, "ndim", 0) >= 1 and hasattr(value, "tolist"):  # an array a caller passes: a list
        value = value.tolist()
    origin = typing.get_origin(tp)
    if origin is Annotated:
        inner, *rules = typing.get_args(tp)
        return _fits(value, inner, path) and all(r.holds(value) for r in rules if isinstance(r, RULES))
    if origin in (typing.Union, types.UnionType):
        if value is None and type(None) in typing.get_args(tp):
            return True
        inner = None
        for opt in typing.get_args(tp):
            try:
                if _fits(value, opt, path):
                    return True
            except ConfigError as err:  # the value has this option's shape: the error is inside it
                inner = inner or err
        if inner is not None:
            raise inner
        return False
    if origin is typing.Literal:
        return value in typing.get_args(tp)
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _check_dataclass(value, tp, path)
    if origin in (list, tuple, collections.abc.Sequence) or tp in (list, tuple):  # a Sequence: a list in a config
        args = [a for a in typing.get_args(tp) if a is not Ellipsis]
        fixed = origin is tuple and len(args) > 1
        if not isinstance(value, list | tuple) or (fixed and len(value) != len(args)):
            return False
        for i, v in enumerate(value):
            check_value(v, args[i] if fixed else (args[0] if args else None), f"{path}[{i}]")
        return True
    if origin is dict or tp is dict:
        if not isinstance(value, dict):
            return False
        args = typing.get_args(tp)
        for k, v in value.items():
            check_value(v, args[1] if len(args) == 2 else None, f"{path}.{k}")
        return True
    return _scalar_ok(value, tp)


def _scalar_ok(value, tp) -> bool:
    if tp is type(None):
        return value is None
    if tp is bool:
        return isinstance(value, bool | np.bool_)  # numpy's too
    if tp is int:
        return isinstance(value, numbers.Integral) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, numbers.Real) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    if isinstance(tp, type):
        try:
            return isinstance(value, tp) or isinstance(value, dict)  # an object passed by the caller, or its node
        except TypeError:  # a Protocol: not checked
            return True
    return True


def _check_dataclass(value, cls, path: str) -> bool:
    if isinstance(value, cls):  # an object a caller built: its fields, named where they sit
        check_fields(value, path)
        return True
    if not isinstance(value, dict):
        return False
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(value) - set(fields))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}", f"unknown key ({cls.__name__} takes {', '.join(fields)})")
    hints = type_hints(cls)
    for name, f in fields.items():
        if name not in value:
            if f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
                raise ConfigError(f"{path}.{name}", f"missing ({cls.__name__} needs it)")
            continue
        check_value(value[name], hints.get(name), f"{path}.{name}")
    return True


# ----------------------------------------------------------------------------------- objects from Python
@functools.cache
def type_hints(obj) -> dict:
    """The annotations of a class (a dataclass's fields) or function, `Annotated` kept; a name that does not
    resolve (an import for type checkers only) is not checked."""
    try:
        return typing.get_type_hints(obj, include_extras=True)
    except Exception:  # noqa: BLE001 - one unresolvable name: resolve the others one by one
        out = {}
        target = inspect.unwrap(obj)
        space = {**vars(sys.modules[target.__module__]), **vars(typing)}
        for k, v in getattr(target, "__annotations__", {}).items():
            try:
                out[k] = eval(v, space) if isinstance(v, str) else v  # noqa: S307 - the project's own annotations
            except Exception:  # noqa: BLE001
                out[k] = None
        return out


def _is_object(tp) -> bool:
    """An annotation naming an object the caller passes (a scene, a plant), not a config value: the constructor
    checks it itself."""
    if typing.get_origin(tp) in (typing.Union, types.UnionType):
        return any(_is_object(a) for a in typing.get_args(tp))
    return isinstance(tp, type) and not dataclasses.is_dataclass(tp) and \
        tp not in (bool, int, float, str, list, tuple, dict, type(None))


def check_fields(obj, prefix: str) -> None:
    """Every field of the dataclass instance `obj` against its annotation (`ConfigError("<prefix>.<field>")`)."""
    hints = type_hints(type(obj))
    for f in dataclasses.fields(obj):
        if f.init:
            check_value(getattr(obj, f.name), hints.get(f.name), f"{prefix}.{f.name}" if prefix else f.name)


# (target's name, keywords) that `pipeline.config.build` has checked in the target's node: a value is checked
# once, where its node is, not again by the constructor it is passed to (the target's own @checked call only)
CHECKED_KEYWORDS: contextvars.ContextVar[tuple[str, frozenset]] = contextvars.ContextVar(
    "checked_keywords", default=("", frozenset()))


def _check_arguments(sig: inspect.Signature, source, prefix: str, objects, args, kwargs) -> None:
    """The arguments of one call (bound to `sig`) against the annotations of `source` (but `objects`, and the
    keywords the target's config node checked already: :data:`CHECKED_KEYWORDS`, consumed by this call)."""
    target, done = CHECKED_KEYWORDS.get()
    if target and target == getattr(source, "__qualname__", "").split(".")[0]:
        CHECKED_KEYWORDS.set(("", frozenset()))
        objects = (*objects, *done)
    try:
        bound = sig.bind(*args, **kwargs)
    except TypeError:  # let the call itself say what is missing or unknown
        return
    hints = type_hints(source)
    for name, value in bound.arguments.items():
        tp = hints.get(name)
        if name == "self" or name in objects or _is_object(tp) or sig.parameters[name].kind in (inspect.Parameter.VAR_POSITIONAL,
                                                                              inspect.Parameter.VAR_KEYWORD):
            continue
        check_value(value, tp, f"{prefix}.{name}" if prefix else name)


def checked(prefix: str, objects: tuple[str, ...] = ()):
    """Decorator of a class (its constructor) or a function: every argument is checked against its annotation
    (types, choices, ranges, nested dataclasses) before the call runs, as the config checks the class's node;
    errors name `<prefix>.<keyword>` (a config path re-prefixes them with the node's own,
    `pipeline.config.build`; an empty prefix: a stage's root keys). Arguments annotated with another class (a
    network, a plant) and those named in `objects` (a controller's scene) are objects the caller passes, the
    callee's to check."""

    def wrap(obj):
        fn = obj.__init__ if inspect.isclass(obj) else obj
        sig = inspect.signature(fn)
        source = obj if dataclasses.is_dataclass(obj) else fn

        @functools.wraps(fn)
        def call(*args, **kwargs):
            _check_arguments(sig, source, prefix, objects, args, kwargs)
            return fn(*args, **kwargs)

        if not inspect.isclass(obj):
            return call
        obj.__init__ = call
        return obj

    return wrap
