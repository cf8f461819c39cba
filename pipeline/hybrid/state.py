"""A batch of hybrid states: the flowing part `c` `(N, n)` and named logic or held arrays (each `(N, ...)`)."""

from __future__ import annotations

import numpy as np


class State:
    """`x = (c, d)`: `c` flows (the plant's state), the arrays of `d` change at jumps only (logic variables such as
    the mode `q`, and values a sampled loop holds between frames, such as the measurement `m`).

    Read the arrays as attributes (`x.c`, `x.q`, `x.m`). A State is not changed in place by the maps of a
    system: they return new States (which may share unchanged arrays).
    """

    __slots__ = ("c", "d")

    def __init__(self, c: np.ndarray, **d: np.ndarray):
        self.c = c
        self.d = d

    def __getattr__(self, name: str) -> np.ndarray:
        try:
            return self.d[name]
        except KeyError:
            raise AttributeError(name) from None

    def __len__(self) -> int:
        return len(self.c)

    def __repr__(self) -> str:
        parts = ", ".join(f"{k}{tuple(v.shape)}" for k, v in self.d.items() if v is not None)
        return f"State(c{tuple(self.c.shape)}{', ' + parts if parts else ''})"

    def replace(self, c: np.ndarray | None = None, **d: np.ndarray) -> State:
        """A new State with some arrays replaced (the others shared)."""
        return State(self.c if c is None else c, **{**self.d, **d})

    def take(self, idx) -> State:
        """The states of the agents `idx` (copies)."""
        return State(self.c[idx], **{k: (None if v is None else v[idx]) for k, v in self.d.items()})

    def where(self, mask: np.ndarray, other: State) -> State:
        """Rows of `other` where `mask`, else of `self`."""
        def pick(a, b):
            if a is None or b is a:  # an array the jump left alone keeps its identity (and any memo on it)
                return a
            m = mask.reshape(-1, *([1] * (a.ndim - 1)))
            return np.where(m, b, a).astype(a.dtype, copy=False)

        return State(pick(self.c, other.c), **{k: pick(v, other.d[k]) for k, v in self.d.items()})

    def put(self, idx, sub: State) -> None:
        """Write the states `sub` into the rows `idx` (in place; used by the solvers on their own copies)."""
        self.c[idx] = sub.c
        for k, v in self.d.items():
            if v is not None:
                v[idx] = sub.d[k]
