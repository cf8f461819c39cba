"""Per-agent outcomes and the table a reviewer asks for (issue 12 §2).

:class:`Outcome` is the one vocabulary of how a run ended, for the simulator, the Gymnasium environments, the
bracket's falsifier and the learned agents' rollouts (each produces the classes its loop can reach: the
simulator has no arena stop, so `OUTCOMES`, its table's classes, has no `left_view`).

`outcome(...)` classifies each agent as `reached`, `collided`, `stalled` (slower than `stall_speed` for the
last `stall_time` seconds away from the target: the undesired equilibria of the smooth and CBF controllers,
Proposition 1) or `timed_out` (still moving at the horizon). `summarise_agents(df, by)` turns a per-agent
table (the columns of `SimResult.metrics_frame()`) into one row per group. Pure numpy/pandas.
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np
import pandas as pd


class Outcome(IntEnum):
    """How a run ended: `RUNNING` (not yet), `REACHED` the success disc, `COLLIDED` with an obstacle, `LEFT_VIEW`
    (left the camera's view, the arena), `STALLED` (at the horizon, slower than the stall speed: an undesired
    equilibrium, Proposition 1) or `TIMED_OUT` (still moving at the horizon; the environments' truncation)."""

    RUNNING = 0
    REACHED = 1
    COLLIDED = 2
    LEFT_VIEW = 3
    STALLED = 4
    TIMED_OUT = 5


NAMES = tuple(o.name.lower() for o in Outcome)  # "running", "reached", ... indexed by code
OUTCOMES = ("reached", "collided", "stalled", "timed_out")  # the simulator's classes (its table's columns)


class StallMonitor:
    """Positions on a grid of `stall_time / n_samples` seconds, the last `stall_time` seconds kept (ring buffer).

    An agent is *stalled* at the end if its mean speed over the last `stall_time` seconds is below
    `stall_speed`: the displacement between the mean positions of the window's first and last halves
    (samples every `stall_time / n_samples`), divided by the time between them. Averaging catches an
    equilibrium and a vehicle chattering in place (Proposition 1's adversary) alike.
    """

    def __init__(self, n: int, stall_speed: float, stall_time: float, dt: float, n_samples: int = 10):
        self.speed, self.time = stall_speed, stall_time
        self.every = max(1, round(stall_time / n_samples / dt))  # steps of dt between samples
        self.period = self.every * dt
        self.size = math.ceil(stall_time / self.period) + 1
        self.buf = np.full((self.size, n, 2), np.nan)
        self.count = 0

    def sample(self, p: np.ndarray) -> None:
        """Store `p` `(n, 2)`; call at times `k * period`, k = 0, 1, 2, ..."""
        self.buf[self.count % self.size] = p
        self.count += 1

    def stalled(self, p_end: np.ndarray) -> np.ndarray:
        """Boolean `(n,)`: within `stall_speed * stall_time` of `p_end` over the last `stall_time` seconds."""
        if self.count < self.size:  # less history than stall_time
            return np.zeros(len(p_end), dtype=bool)
        order = (self.count + np.arange(self.size)) % self.size  # oldest first
        half = self.size // 2
        first, last = self.buf[order[:half]].mean(axis=0), self.buf[order[-half:]].mean(axis=0)
        gap = (self.size - half) * self.period  # time between the two halves' mean sample times
        return np.hypot(*(last - first).T) <= self.speed * gap


def outcome(success: np.ndarray, collision: np.ndarray, stalled: np.ndarray) -> np.ndarray:
    """`collided` > `reached` > `stalled` > `timed_out`, per agent (string array)."""
    return np.select([collision, success, stalled], ["collided", "reached", "stalled"], "timed_out").astype(object)


# ------------------------------------------------------------------------------------------------ tables


def wilson(successes, n, z: float = 1.96):
    """95% Wilson score interval of a binomial proportion (works for 0 and n successes)."""
    s, n = np.asarray(successes, float), np.asarray(n, float)
    with np.errstate(invalid="ignore", divide="ignore"):
        p = np.where(n > 0, s / np.maximum(n, 1), np.nan)
        denom = 1 + z**2 / n
        centre = (p + z**2 / (2 * n)) / denom
        half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / denom
    # rounding: no -3e-17 at k = 0, no 1 - 1e-16 at k = n; the interval holds the rate
    return np.clip(np.minimum(centre - half, p), 0.0, 1.0), np.clip(np.maximum(centre + half, p), 0.0, 1.0)


def _q(x: pd.Series, q: float) -> float:
    x = x.to_numpy(float)
    x = x[np.isfinite(x)]
    return float(np.quantile(x, q)) if len(x) else math.nan


def summarise_agents(df: pd.DataFrame, by: list[str] | str, delta_practical: float | None = None) -> pd.DataFrame:
    """One row per group of `by`: the per-agent table of `SimResult.metrics_frame()` summarised.

    Columns: `n`; `success_rate` with its 95% Wilson interval (`success_lo`, `success_hi`) at the run's
    `delta`; `collision_rate` (with interval); the share of each outcome class (`reached`, `collided`,
    `stalled`, `timed_out`); per-agent minimum clearance summarised over agents (`clearance_median`,
    `clearance_p05`) and its global minimum (`clearance_min`); final distance to the target (`final_median`,
    `final_p90`); `median_time` to target over the successful agents; `mean_jumps`; and with
    `delta_practical`, `success_practical` (+ interval): not collided and came within `delta_practical` of
    the target (`min_target_distance`; the practical tolerance tied to the perception error, e.g. the map's
    near-target p95). A run stops an agent at `delta`, so a `delta_practical < delta` needs
    `stop_on_success=false`.
    """
    by = [by] if isinstance(by, str) else list(by)
    rows = []
    for key, g in df.groupby(by, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        n = len(g)
        succ = g["success"].to_numpy(bool)
        coll = g["collision"].to_numpy(bool)
        s_lo, s_hi = wilson(succ.sum(), n)
        c_lo, c_hi = wilson(coll.sum(), n)
        row = {**dict(zip(by, key)), "n": n,
               "success_rate": succ.mean(), "success_lo": float(s_lo), "success_hi": float(s_hi),
               "collision_rate": coll.mean(), "collision_lo": float(c_lo), "collision_hi": float(c_hi)}
        if "outcome" in g:
            shares = g["outcome"].value_counts(normalize=True)
            row |= {k: float(shares.get(k, 0.0)) for k in OUTCOMES}
        clear = g["min_clearance"]
        row |= {"clearance_median": _q(clear, 0.5), "clearance_p05": _q(clear, 0.05),
                "clearance_min": float(clear.min()),
                "final_median": _q(g["final_error"], 0.5), "final_p90": _q(g["final_error"], 0.9),
                "median_time": _q(g.loc[succ, "time_to_target"], 0.5),
                "mean_jumps": float(g["jumps"].mean())}
        if delta_practical is not None:
            closest = g["min_target_distance"] if "min_target_distance" in g else g["final_error"]
            ok = ~coll & (closest.to_numpy(float) <= float(delta_practical))
            p_lo, p_hi = wilson(ok.sum(), n)
            row |= {"delta_practical": float(delta_practical), "success_practical": ok.mean(),
                    "success_practical_lo": float(p_lo), "success_practical_hi": float(p_hi)}
        rows.append(row)
    return pd.DataFrame(rows)
