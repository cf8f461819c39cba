"""Lost frames in the proof (SPEC §5.6): a frame lost (`camera.p_fail`) or dropped by the gate (`camera.gate`) as a
nondeterministic event of the abstraction, with at most `L = bracket.lost_frames` consecutive frames lost.

What the loop does with a lost frame (:class:`pipeline.sim.closed_loop.SampledLoop`), and what the abstraction takes:

- **held** (`camera.predict: false`, the paper's failure model): the estimate `m` of the last delivered frame is
  kept, so the input is the one held since then and no mode decision happens. That frame was taken at most `L`
  frames earlier, within `L T_s v̄` of the position now (`v̄` the largest speed of the law: `u_max`, or the push-out
  speed when larger), with its own error bound there: the input is the law's at some
  `m ∈ P ⊕ (ε̄(P ⊕ L T_s v̄) + L T_s v̄)`, and a node may keep its mode (`keep_mode`).
- **predicted** (`camera.predict: true`, dead reckoning): `m ← m + T_s u`, the vehicle's own held input, exact for
  the single integrator, so `m - p` stays the last delivered frame's error: `m ∈ P ⊕ ε̄(P ⊕ L T_s v̄)`, the mode
  decided at `m` as on a delivered frame. Past `max_drift` (the uncertainty grows by `drift` per unit predicted) the
  vehicle stops until a frame arrives: when `L T_s v̄ drift > max_drift` can happen, 0 joins the inputs (`may_stop`).

The first frame is always delivered (a vehicle starts with an estimate). The certificate then holds for every run
with at most `L` consecutive losses; with independent losses of probability `p` per frame, a run of `N` frames has
more with probability at most `(N - L) p^(L+1)` (a union bound over the windows of `L + 1` frames after the first):
:func:`LostFrames.p_more`. :func:`lost_frames` builds the model from the config and refuses, in one line, what it
does not cover.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from pipeline.bracket.abstraction import dilate
from pipeline.errors import ConfigError


@dataclass(frozen=True)
class LostFrames:
    """At most `max_lost` consecutive frames lost, held or predicted (module docstring); `speed` the law's `v̄`."""

    max_lost: int
    predict: bool
    period: float
    speed: float
    drift: float = 0.1
    max_drift: float = 2.0

    @property
    def reach(self) -> float:
        """How far the position may be from the last delivered frame's: `L T_s v̄`."""
        return self.max_lost * self.period * self.speed

    @property
    def keep_mode(self) -> bool:
        return self.max_lost > 0 and not self.predict

    @property
    def may_stop(self) -> bool:
        return self.predict and self.reach * self.drift >= self.max_drift * (1 - 1e-9)  # the sum of L steps may round up

    def eps(self, inner):
        """The error bound of the perceived point behind the held input (module docstring), from `inner`'s."""
        return inner if self.max_lost == 0 else Stale(inner, self.reach, 0.0 if self.predict else self.reach)

    def p_more(self, p_fail: float, n_frames: int) -> float:
        """An upper bound on the probability that a run of `n_frames` frames loses more than `max_lost` in a row."""
        if p_fail <= 0:
            return 0.0
        return min(1.0, max(0, n_frames - self.max_lost) * p_fail ** (self.max_lost + 1))

    def describe(self) -> str:
        if self.max_lost == 0:
            return "every frame delivered"
        how = "predicted (dead reckoning)" if self.predict else "held"
        return f"up to {self.max_lost} consecutive frames lost, {how}" + (", the stop included" if self.may_stop else "")


class Stale:
    """`ε̄` of a frame taken within `reach` of the cell, plus `add`: the largest bound over the cell grown by
    `reach` (the position of the last delivered frame), and the distance travelled since when the estimate is held."""

    def __init__(self, inner, reach: float, add: float):
        self.inner, self.reach, self.add = inner, float(reach), float(add)
        self.name = f"{getattr(inner, 'name', 'ε̄')}, stale by up to {self.reach:g}"

    def __call__(self, points, boxes=None, frame=None):
        if boxes is None:
            raise ValueError("a stale bound needs the grid cells")
        grown = dilate(boxes, np.full(len(boxes), self.reach))
        return self.inner(points, boxes=grown, frame=frame) + self.add


def lost_frames(sim, camera, bs, laws) -> dict[str, LostFrames]:
    """The loop's frame model as the proof takes it (SPEC §5.6, :mod:`pipeline.bracket.lost`); what it does not
    model is refused in one line: the continuous-time loop, frames lost or gated with no bound on consecutive losses
    (`bracket.lost_frames`), a law without a speed limit when frames may be lost."""
    if sim.model != "sampled":
        raise ConfigError("sim.model", f"the bracket proves the sampled loop (a frame every camera.period, the input "
                                       f"held between frames), not sim.model={sim.model}: sampled here")
    losing = camera.p_fail > 0 or camera.gate is not None
    if losing and bs.lost_frames == 0:
        cause = f"camera.p_fail = {camera.p_fail:g}" if camera.p_fail > 0 else f"camera.gate = {camera.gate:g}"
        field_ = "camera.p_fail" if camera.p_fail > 0 else "camera.gate"
        raise ConfigError(field_, f"{cause} loses frames, and the proof assumes every frame arrives unless "
                                  "bracket.lost_frames (the most consecutive lost frames it covers) is >= 1")
    if camera.predict and camera.innovation is not None:
        _check_innovation(camera.innovation, bs)
    if bs.lost_frames > 0 and any(law.u_max is None for law in laws.values()):
        raise ConfigError("bracket.lost_frames", "a law without a speed limit (u_max null): a lost frame's input "
                                                 "comes from a frame taken an unbounded distance away")
    return {name: LostFrames(bs.lost_frames, camera.predict, camera.period,
                             0.0 if law.u_max is None else max(law.u_max, law.push_speed), camera.drift,
                             camera.max_drift) for name, law in laws.items()}


def _check_innovation(innovation: float, bs) -> None:
    """`camera.innovation` rejects no frame of a loop whose frames err by at most `innovation / 2` (two of them
    differ by at most twice that; `pipeline.sim.closed_loop.DeadReckoning`): the proof covers it where every `ε` it
    reasons about is that small, a per-cell map bound not at all."""
    largest = max([*bs.eps, bs.eps_max])
    if bs.error_map is not None:
        raise ConfigError("camera.innovation", "the proof covers the innovation check for a uniform ε only (frames "
                                               "within innovation / 2 are never rejected), not with "
                                               "bracket.error_map: camera.innovation=null")
    if innovation < 2 * largest:
        raise ConfigError("camera.innovation", f"the proof covers a loop that rejects no frame within its ε: needs "
                                               f">= 2 x the largest ε tried ({largest:g}: bracket.eps, "
                                               f"bracket.eps_max) = {2 * largest:g}, got {innovation:g}")
