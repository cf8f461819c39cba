"""Schemas of the plain settings nodes (no `_target_`): typed dataclasses, keys and types checked in one place.

    timing = load(cfg.camera, "camera", CameraTiming)     # ConfigError("camera.p_fail", "must be a number ...")

A node may hold only the schema's fields; each value must have the field's type (an int is a float; `null`
only where the type allows None); ranges are checked by the dataclass's `__post_init__`.
"""

from __future__ import annotations

import dataclasses
import math
import types
import typing
from typing import Any

from pipeline.errors import ConfigError


def _plain(node) -> dict:
    from omegaconf import DictConfig, OmegaConf

    if isinstance(node, DictConfig):
        return OmegaConf.to_container(node, resolve=True)
    return dict(node or {})


def _type_ok(value, tp) -> bool:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        return any(_type_ok(value, a) for a in typing.get_args(tp))
    if tp is type(None):
        return value is None
    if tp is Any:
        return True
    if tp is bool:
        return isinstance(value, bool)
    if tp is int:
        return isinstance(value, int) and not isinstance(value, bool)
    if tp is float:
        return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
    if tp is str:
        return isinstance(value, str)
    if origin in (list, tuple):
        args = typing.get_args(tp)
        if not isinstance(value, list | tuple):
            return False
        inner = args[0] if args else Any
        return all(_type_ok(v, inner) for v in value)
    return isinstance(value, tp)


def _describe(tp) -> str:
    origin = typing.get_origin(tp)
    if origin in (typing.Union, types.UnionType):
        args = [a for a in typing.get_args(tp) if a is not type(None)]
        return " or ".join(_describe(a) for a in args) + (" (or null)" if len(args) < len(typing.get_args(tp)) else "")
    if origin in (list, tuple):
        args = typing.get_args(tp)
        return f"a list of {_describe(args[0]) if args else 'values'}"
    return {bool: "true or false", int: "an integer", float: "a number", str: "a string"}.get(tp, getattr(tp, "__name__", str(tp)))


def load(node, path: str, schema: type):
    """Instance of dataclass `schema` from a config node, every key and type checked (errors name `path.key`)."""
    data = _plain(node)
    hints = typing.get_type_hints(schema)
    fields = {f.name: f for f in dataclasses.fields(schema) if f.init}
    unknown = sorted(set(data) - set(fields))
    if unknown:
        raise ConfigError(f"{path}.{unknown[0]}", f"unknown key (known: {', '.join(fields)})")
    for k, v in data.items():
        if not _type_ok(v, hints[k]):
            raise ConfigError(f"{path}.{k}", f"must be {_describe(hints[k])}, got {v!r}")
    try:
        return schema(**data)
    except ConfigError as err:
        field = err.field if err.field.startswith(path) else f"{path}.{err.field}"
        raise ConfigError(field, err.reason) from None


def need(cond: bool, field: str, reason: str) -> None:
    """Raise `ConfigError(field, reason)` unless `cond` (range checks of a schema's `__post_init__`)."""
    if not cond:
        raise ConfigError(field, reason)


# ------------------------------------------------------------------------------------------ nodes
@dataclasses.dataclass(frozen=True)
class CameraTiming:
    """`camera`: a frame every `period` seconds (null: every step), lost with probability `p_fail`; with `gate`,
    a frame whose predicted error (a map with an uncertainty head) exceeds `gate` world units is lost too."""

    period: float | None = 0.05
    p_fail: float = 0.0
    gate: float | None = None

    def __post_init__(self):
        need(self.period is None or self.period > 0, "period", f"must be > 0 (or null), got {self.period!r}")
        need(0.0 <= self.p_fail < 1.0, "p_fail", f"must be in [0, 1), got {self.p_fail!r}")
        need(self.gate is None or self.gate > 0, "gate", f"must be > 0 (world units) or null, got {self.gate!r}")


def _pair_range(value, field: str) -> None:
    need(len(value) == 2 and value[0] < value[1], field, f"must be [min, max] with min < max, got {list(value)!r}")


@dataclasses.dataclass(frozen=True)
class InitPoints:
    mode: str = "points"
    points: list[list[float]] = dataclasses.field(default_factory=list)

    def __post_init__(self):
        need(len(self.points) > 0 and all(len(p) == 2 for p in self.points), "points",
             f"must be a non-empty list of [x, y] pairs, got {self.points!r}")


@dataclasses.dataclass(frozen=True)
class InitGrid:
    mode: str = "grid"
    nx: int = 21
    ny: int = 13
    margin: float = 2.0
    exclude_diamond: bool = True

    def __post_init__(self):
        need(self.nx >= 1, "nx", f"must be >= 1, got {self.nx}")
        need(self.ny >= 1, "ny", f"must be >= 1, got {self.ny}")
        need(self.margin >= 0, "margin", f"must be >= 0, got {self.margin}")


@dataclasses.dataclass(frozen=True)
class InitRandom:
    mode: str = "random"
    n: int = 1000
    seed: int = 0
    margin: float = 2.0
    exclude_diamond: bool = True

    def __post_init__(self):
        need(self.n >= 1, "n", f"must be >= 1, got {self.n}")
        need(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")
        need(self.margin >= 0, "margin", f"must be >= 0, got {self.margin}")


@dataclasses.dataclass(frozen=True)
class InitNearK:
    mode: str = "near_k"
    n: int = 200
    seed: int = 0
    band: float = 0.5
    a_range: list[float] = dataclasses.field(default_factory=lambda: [-45.0, -15.0])

    def __post_init__(self):
        need(self.n >= 1, "n", f"must be >= 1, got {self.n}")
        need(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")
        need(self.band > 0, "band", f"must be > 0, got {self.band}")
        _pair_range(self.a_range, "a_range")


INIT_MODES = {"points": InitPoints, "grid": InitGrid, "random": InitRandom, "near_k": InitNearK}


def load_init(node, path: str = "init"):
    """The `init` node: its `mode` picks the schema."""
    mode = _plain(node).get("mode", "points")
    if mode not in INIT_MODES:
        raise ConfigError(f"{path}.mode", f"must be one of {', '.join(INIT_MODES)}, got {mode!r}")
    return load(node, path, INIT_MODES[mode])


@dataclasses.dataclass(frozen=True)
class SimSettings:
    """`sim`: time model, Euler step / record grid, horizon, success radius, recording, seed, the continuous
    integrator's tolerances and the stall thresholds of the outcome classes."""

    model: str = "sampled"
    dt: float = 0.01
    horizon: float = 30.0
    delta: float = 1.0
    record_every: int = 5
    stop_on_success: bool = True
    seed: int = 0
    method: str = "rosenbrock23"
    rtol: float = 1e-6
    atol: float = 1e-4
    h_max: float = 0.25
    stall_speed: float = 0.1
    stall_time: float = 5.0

    def __post_init__(self):
        need(self.dt > 0, "dt", f"must be > 0, got {self.dt}")
        need(self.horizon >= self.dt, "horizon", f"must be >= sim.dt = {self.dt}, got {self.horizon}")
        need(self.delta > 0, "delta", f"must be > 0, got {self.delta}")
        need(self.record_every >= 1, "record_every", f"must be >= 1, got {self.record_every}")
        need(self.seed >= 0, "seed", f"must be >= 0, got {self.seed}")
        need(self.model in ("sampled", "continuous"), "model", f"must be sampled or continuous, got {self.model!r}")
        need(self.method in ("rosenbrock23", "dopri5"), "method", f"must be rosenbrock23 or dopri5, got {self.method!r}")
        for k in ("rtol", "atol", "h_max", "stall_speed", "stall_time"):
            need(getattr(self, k) > 0, k, f"must be > 0, got {getattr(self, k)}")
