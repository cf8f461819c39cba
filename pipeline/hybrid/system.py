"""What a solver needs of a hybrid system and of what it watches along an arc.

:class:`HybridSystem` is the Hybrid Equations Toolbox's `HybridSystem` (`flowMap`, `jumpMap`,
`flowSetIndicator`, `jumpSetIndicator`) on batches: four maps of a :class:`~pipeline.hybrid.state.State`,
jumps taking priority where `x ∈ C ∩ D`. Its `plant` is the flowing part; `input(x)` is the part of the flow
map a sampled-data loop holds between frames (`flow_map(x) = plant.flow(x.c, input(x))`), and `sample` is
what happens at a frame (a measurement is taken). A system with no plant input (a bouncing ball) has
`input(x) = None` and a plant whose `step` integrates its free flow.

:class:`Monitor` is what the solvers watch along the arc without knowing what it means: stop sets (an
agent's run ends when it enters one), the first time each of them is entered, and running minima. The
closed loop's monitor (arrival at the target, collision with an obstacle) lives in `pipeline.sim`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from pipeline.hybrid.state import State


class HybridSystem:
    """`H = (C, F, D, G)` on batches of states (the defaults: everywhere flow, never jump)."""

    # the flowing part: `flow(c, w)`, `step(c, w, h)`, `speed(w)`, `inputs` and `position(c)` (see
    # pipeline.plants.Plant; the arc length is that of `position`, a projection of `c`)
    plant = None
    recorded: tuple[str, ...] = ()  # arrays of `x.d` a solver records along the arc (besides `c`)

    def initial(self, c0: np.ndarray, rng: np.random.Generator) -> State:
        """The state at `t = 0` from the plant's initial state (the first frame is always taken)."""
        return State(np.array(c0, dtype=float))

    def input(self, x: State):
        """The plant input at `x` (what a sampled loop holds between two frames)."""
        return None

    def flow_map(self, x: State) -> np.ndarray:
        """`F(x)`: the time derivative of `x.c` `(N, n)`."""
        return self.plant.flow(x.c, self.input(x))

    def jump_map(self, x: State) -> State:
        """`G(x)`: the state after a jump (evaluated where `x ∈ D`)."""
        return x

    def flow_set(self, x: State) -> np.ndarray:
        """`x ∈ C` `(N,)` bool."""
        return np.ones(len(x), dtype=bool)

    def jump_set(self, x: State) -> np.ndarray:
        """`x ∈ D` `(N,)` bool."""
        return np.zeros(len(x), dtype=bool)

    def sample(self, x: State, frame: int, rng: np.random.Generator, active: np.ndarray) -> State:
        """What happens at frame `frame > 0` (a measurement): the state after it. Nothing by default."""
        return x

    def frame_counts(self, x: State, w) -> dict[str, np.ndarray]:
        """Per-frame indicators a sampled loop adds up per agent (`Arc.counts`): none by default."""
        return {}

    def saturated(self, flow: np.ndarray) -> np.ndarray | None:
        """Rows of a flow value on a clipped branch of `F` (a kink the continuous solver must not step over), or
        None when `F` is smooth."""
        return None


class Monitor:
    """Stop sets and running minima along an arc (the default: nothing to watch, runs end at the horizon).

    `codes` names the stop sets (termination codes 1, 2, ... in this order; 0 is the horizon, and
    `len(codes) + 1` a non-finite state). `stops[k]` says whether entering set `k` ends the run (else its first
    entry time is only recorded).
    """

    codes: tuple[str, ...] = ()
    stops: tuple[bool, ...] = ()

    def start(self, c: np.ndarray) -> np.ndarray:
        """Stop code per agent at `t = 0` `(N,)` int8 (0: runs)."""
        return np.zeros(len(c), dtype=np.int8)

    def step(self, k: int, t: float, c: np.ndarray, active: np.ndarray) -> np.ndarray:
        """After step `k` of the sampled loop (time `t`): stop code per agent (0: runs)."""
        return np.zeros(len(c), dtype=np.int8)

    # the continuous solver locates stop sets in time (`conditions[k - 1]`: membership of set k, searched in
    # `precedence` order) and looks inside a step that may graze the first set of `precedence`
    conditions: tuple[Callable[[np.ndarray], np.ndarray], ...] = ()
    precedence: tuple[int, ...] = ()

    def graze(self, c0: np.ndarray, c1: np.ndarray) -> np.ndarray | None:
        """Rows whose step `c0 -> c1` may pass through the first stop set between its ends (None: never)."""
        return None

    def observe(self, idx: np.ndarray, c: np.ndarray, ends: bool) -> None:
        """A point of the arc the solver looked at, for agents `idx` (`ends`: a step's end; else a point inside
        a step or on the record grid): running minima."""

    def entered(self, code: int, idx: np.ndarray, t: np.ndarray) -> None:
        """Agents `idx` entered stop set `code` at times `t` (the continuous solver's located events)."""

    def sample_grid(self) -> tuple[float, np.ndarray] | None:
        """`(period, buffer)` of a ring buffer of positions `(rows, N, 2)` the continuous solver fills on a
        regular time grid (None: none)."""
        return None

    def finish(self, t_end: float) -> None:
        """The run ended at `t_end` (the last time any agent moved)."""


@dataclass
class Arc:
    """A batched hybrid arc `(t, j, x)` and how each agent's run ended."""

    t: np.ndarray                    # (T,) recorded times
    c: np.ndarray                    # (T, N, n) recorded flowing state
    d: dict[str, np.ndarray]         # recorded logic/held arrays, (T, N, ...) each
    w: np.ndarray | None             # (T, N, k) the plant input at the recorded times (None without input)
    j: np.ndarray                    # (T, N) jump counts
    final: State                     # the state at the end of each agent's run
    termination: np.ndarray          # (N,) int8: 0 horizon, 1.. the monitor's stop sets, then non-finite
    jumps: np.ndarray                # (N,) jumps
    outside: np.ndarray              # (N,) frames (sampled) or entries (continuous) outside C ∪ D
    path: np.ndarray                 # (N,) arc length of the plant's position
    t_end: float = 0.0               # the last time any agent ran
    stats: dict = field(default_factory=dict)
    counts: dict = field(default_factory=dict)  # (N,) sums of the system's per-frame indicators (sampled)


def row_norm(X: np.ndarray) -> np.ndarray:
    """Row norms of positions (or of their rates) `(k, p)`: `hypot` in the plane, `|x|` on a line (the arc length)."""
    if X.shape[1] == 2:
        return np.hypot(X[:, 0], X[:, 1])
    return np.abs(X[:, 0]) if X.shape[1] == 1 else np.sqrt((X * X).sum(axis=1))


def record_rows(n_steps: int, record_every: int, record: bool) -> int:
    """Rows of a recorded arc: every `record_every` steps and `t = 0` (only the final state without recording)."""
    return n_steps // record_every + 1 if record else 1
