"""Typed values: :func:`check_value` checks a value against an annotation (numbers, strings, booleans, `Literal`,
`X | None`, lists, tuples, mappings, dataclasses key by key, `Annotated[X, rule]` with the rules below) and raises one
:class:`ConfigError` naming the key. A config node is checked against its target's annotations
(:mod:`pipeline.config`); an object built from Python checks its arguments the same way (:func:`checked` on its
class, :func:`check_fields` on a dataclass instance) and keeps only its cross-field rules."""
from __future__ import annotations

import collections.abc
import dataclasses
import functools
import inspect
import json
import math
import numbers
import re
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
        bounds = ((">", self.gt), (">=", self.ge), ("<", self.lt), ("<=", self.le))
        return inner + next(f" {op} {b:g}" for op, b in bounds if b is not None)


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
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        words = describe(args[0])
        for r in args[1:]:
            words = r.describe(words) if isinstance(r, RULES) else words
        return words
    if origin in (typing.Union, types.UnionType):
        opts = [a for a in args if a is not type(None)]
        return " or ".join(describe(a) for a in opts) + (" (or null)" if len(opts) < len(args) else "")
    if origin is typing.Literal:
        return "one of " + ", ".join(str(c) for c in args)
    if origin in (list, tuple, collections.abc.Sequence):
        args = [a for a in args if a is not Ellipsis]
        if origin is tuple and len(args) > 1:
            return f"a list of {len(args)} {_plural(describe(args[0]))}" if len(set(args)) == 1 else \
                f"a list of {len(args)} values"
        return f"a list of {_plural(describe(args[0])) if args else 'values'}"
    if dataclasses.is_dataclass(tp):
        return f"a mapping with keys {', '.join(f.name for f in dataclasses.fields(tp) if f.init)}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string", dict: "a mapping"}.get(
        origin or tp, getattr(tp, "__name__", str(tp)))


def _plural(words: str) -> str:
    """`a number` -> `numbers`, `an integer > 0` -> `integers > 0` (the element of a list, in words)."""
    for one in ("a number", "an integer", "a string", "a list", "a mapping"):
        if words.startswith(one):
            return one.split(" ")[1] + "s" + words[len(one):]
    return words


def check_value(value, tp, path: str) -> None:
    """`ConfigError(path, "must be <tp in words>, got <value>")` unless `value` fits `tp` (an element: its own path)."""
    if not _fits(value, tp, path):
        raise ConfigError(path, f"must be {describe(tp)}, got {value!r}")


_ACCEPTED: set[tuple] = set()  # (annotation, value as JSON) pairs accepted in this process


def check_once(value, tp, path: str) -> None:
    """:func:`check_value`, once per process for a plain (JSON) value and annotation (the constructor a node's value
    is passed to, or the node's next build, does not check it again)."""
    try:
        key = (tp, json.dumps(value, sort_keys=True))
        if key in _ACCEPTED:
            return
    except TypeError:  # an array or an object a caller passes (or an annotation that cannot be hashed): checked
        key = None
    check_value(value, tp, path)
    if key is not None:
        _ACCEPTED.add(key)


def _fits(value, tp, path: str) -> bool:
    if tp is None or tp is Any or tp is object:
        return True
    if getattr(value, "ndim", 0) >= 1 and hasattr(value, "tolist"):  # an array a caller passes: a list
        value = value.tolist()
    origin, args = typing.get_origin(tp), typing.get_args(tp)
    if origin is Annotated:
        return _fits(value, args[0], path) and all(r.holds(value) for r in args[1:] if isinstance(r, RULES))
    if origin in (typing.Union, types.UnionType):
        errors = []
        for opt in args:
            try:
                if _fits(value, opt, path):
                    return True
            except ConfigError as err:  # the value has this option's shape: the error is inside it
                errors.append(err)
        if errors:
            raise errors[0]
        return False
    if origin is typing.Literal:
        return value in args
    if dataclasses.is_dataclass(tp) and isinstance(tp, type):
        return _check_dataclass(value, tp, path)
    if origin in (list, tuple, collections.abc.Sequence) or tp in (list, tuple):  # a Sequence: a list in a config
        args = [a for a in args if a is not Ellipsis]
        fixed = origin is tuple and len(args) > 1
        if not isinstance(value, list | tuple) or (fixed and len(value) != len(args)):
            return False
        for i, v in enumerate(value):
            check_value(v, args[i] if fixed else (args[0] if args else None), f"{path}[{i}]")
        return True
    if origin is dict or tp is dict:
        for k, v in value.items() if isinstance(value, dict) else ():
            check_value(v, args[1] if len(args) == 2 else None, f"{path}.{k}")
        return isinstance(value, dict)
    if tp is bool:
        return isinstance(value, bool | np.bool_)  # numpy's too
    if tp in (int, float):
        return isinstance(value, numbers.Integral if tp is int else numbers.Real) and not isinstance(value, bool) \
            and (tp is int or math.isfinite(value))
    if tp in (str, type(None)):
        return isinstance(value, tp)
    try:
        return not isinstance(tp, type) or isinstance(value, tp | dict)  # an object passed by the caller, or its node
    except TypeError:  # a Protocol: not checked
        return True


def _check_dataclass(value, cls, path: str) -> bool:
    if isinstance(value, cls):  # an object a caller built: its class checked it then
        return True
    if not isinstance(value, dict):
        return False
    fields = {f.name: f for f in dataclasses.fields(cls) if f.init}
    unknown = sorted(set(value) - set(fields))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}", f"unknown key ({cls.__name__} takes {', '.join(fields)})")
    hints = type_hints(cls)
    for name, f in fields.items():
        if name in value:
            check_value(value[name], hints.get(name), f"{path}.{name}")
        elif f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING:
            raise ConfigError(f"{path}.{name}", f"missing ({cls.__name__} needs it)")
    return True


# ----------------------------------------------------------------------------------- objects from Python
@functools.cache
def type_hints(obj) -> dict:
    """The annotations of a class (a dataclass's fields) or function, `Annotated` kept."""
    return typing.get_type_hints(obj, include_extras=True)


def check_fields(obj, prefix: str) -> None:
    """Every field of the dataclass instance `obj` against its annotation (`ConfigError("<prefix>.<field>")`)."""
    hints = type_hints(type(obj))
    for f in dataclasses.fields(obj):
        if f.init:
            check_once(getattr(obj, f.name), hints.get(f.name), f"{prefix}.{f.name}" if prefix else f.name)


def checked(prefix: str):
    """Decorator of a class (its constructor) or a function: every argument is checked against its annotation before
    the call runs, errors naming `<prefix>.<keyword>` (empty prefix: a stage's root keys); an object of the annotated
    class (a controller's scene, a network) is taken as its class built it."""

    def wrap(obj):
        fn = obj.__init__ if inspect.isclass(obj) else obj
        sig, source = inspect.signature(fn), obj if dataclasses.is_dataclass(obj) else fn

        @functools.wraps(fn)
        def call(*args, **kwargs):
            try:
                bound = sig.bind(*args, **kwargs).arguments
            except TypeError:  # the call itself says what is missing or unknown
                bound = {}
            hints = type_hints(source)
            for name, value in bound.items():
                kind = sig.parameters[name].kind
                if not (name == "self" or kind in (kind.VAR_POSITIONAL, kind.VAR_KEYWORD)):
                    check_once(value, hints.get(name), f"{prefix}.{name}" if prefix else name)
            return fn(*args, **kwargs)

        if inspect.isclass(obj):
            obj.__init__ = call
        return obj if inspect.isclass(obj) else call

    return wrap
