"""The falsifier through the camera (issue 28, SPEC §5.5): `κ_hi` per controller and start.

The falsifier of :mod:`pipeline.bracket.falsifier` moves the perceived position directly (`m = p + e`, `|e| <= ε`).
Here the loop perceives what a perception map reads off the rendered image: each frame, at the true position `p`,
the camera renders `x = h(p)` and the adversary adds an L-infinity pixel perturbation `|δ| <= κ` (intensity levels
of 255, the image clipped to `[0, 255]`, delivered as uint8); the law gets `m = l(x + δ)` (`l` the map's network).
`δ` is found by `steps` projected sign-gradient steps (PGD, from the clean image, step `2.5 κ / steps`, the rule
of :func:`pipeline.perception.attacks.pixel_attack`) maximising `d . l(x + δ)`, the estimate error's projection on
a target direction `d` that the state falsifier's adversaries choose:

- ``fixed``: `d = -sign(b(p)) e_b`, §3.5's direction (Proposition 1's attack);
- ``mode_aware``: `d` is the direction :func:`pipeline.bracket.falsifier.mode_aware_error` picks (a mode jump, else a
  push-out, else the least progress) among `n_dirs` directions around the clean estimate `l(x)`, at the radius the
  attack reached on the run's previous frame (the first frame: a probe along the fixed direction).

The PGD is batched over runs with a budget per run (every run of one bisection step in one batch of images): it is
:func:`~pipeline.perception.attacks.pixel_attack` with a budget per image.
`κ_hi` is the smallest budget found failing by bisection on the integer levels `[0, kappa_max]` (a uint8 image moves
by whole levels: `κ` and `floor(κ)` deliver the same images); `κ = 0` is the map's own error (the clean loop, no
attack): a start it already breaks has `κ_hi = 0`; `inf`: no failure up to `kappa_max`. As for `ε_hi`, the search is a
heuristic, so `κ_hi` is an upper bound of the margin in pixels, and each failure comes with its trajectory.

The receding-horizon search is left out here: its candidates would each need images and PGD per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from pipeline.bracket.falsifier import attack, directions, fixed_error, mode_aware_error, scatter
from pipeline.bracket.loop import RUNNING, FrameLoop
from pipeline.perception.attacks import pixel_attack

CAMERA_ADVERSARIES = ("fixed", "mode_aware")
REACH_FLOOR = 0.05  # world units: the smallest radius of the mode-aware choice (a budget that moved nothing yet)


# ------------------------------------------------------------------------------------------ PGD per run
def pgd(net, images: np.ndarray, direction: np.ndarray, kappa: np.ndarray, steps: int, *, device="cpu",
        batch_size: int = 256) -> tuple[np.ndarray, np.ndarray]:
    """`(clean, attacked)` estimates `(N, 2)`: :func:`pipeline.perception.attacks.pixel_attack` on uint8 images
    `(N, H, W, 3)` towards `direction` `(N, 2)` with a budget `kappa` `(N,)` per image (levels; `floor(κ)` after
    the camera's rounding), from the clean image. `net`: the network contract of :mod:`pipeline.perception.attacks`
    (float NHWC in `[0, 255]` -> world coordinates)."""
    res = pixel_attack(net, images, direction, kappa=kappa, steps=steps, device=device, batch_size=batch_size)
    return res.clean, res.attacked


# ------------------------------------------------------------------------------------------ the loop
@dataclass
class CameraSearch:
    """PGD `steps` per frame, the mode-aware adversary's `n_dirs`, the torch `device` and images per batch."""

    steps: int = 3
    n_dirs: int = 16
    device: str = "cpu"
    batch_size: int = 256


class CameraLoop:
    """A :class:`FrameLoop` seen through `camera` (`render(p) -> uint8 (N, H, W, 3)`) and a perception network."""

    def __init__(self, loop: FrameLoop, net, camera, search: CameraSearch | None = None):
        self.loop, self.net, self.camera = loop, net, camera
        self.search = search or CameraSearch()
        self.dirs = directions(self.search.n_dirs)

    def perceive(self, p: np.ndarray, kappa: np.ndarray, direction: np.ndarray, steps: int | None = None):
        """`(clean, attacked)` estimates at the true positions `p` under budgets `kappa` towards `direction`."""
        s = self.search
        return pgd(self.net, self.camera.render(p), direction, kappa, s.steps if steps is None else steps,
                   device=s.device, batch_size=s.batch_size)

    def frame_error(self, st: dict, kappa: np.ndarray, kind: str, reach: np.ndarray):
        """The perception error `m - p` `(N, 2)` of one frame under adversary `kind`, and the attack's reach (the
        length of the estimate's move it achieved, for the next frame's mode-aware choice)."""
        p = st["p"]
        d = fixed_error(self.loop, st, np.ones(len(p)))  # unit: -sign(b(p)) e_b
        if kind == "fixed":
            clean, att = self.perceive(p, kappa, d)
        elif kind == "mode_aware":
            fresh = np.isnan(reach)
            if fresh.any():  # the first frame: the reach of the fixed direction
                c0, a0 = self.perceive(p[fresh], kappa[fresh], d[fresh])
                reach = reach.copy()
                reach[fresh] = np.hypot(*(a0 - c0).T)
            clean, _ = self.perceive(p, kappa, d, steps=0)
            E = mode_aware_error(self.loop, st, np.maximum(reach, REACH_FLOOR), self.dirs, base=clean)
            norm = np.hypot(*E.T)
            target = np.where(norm[:, None] > 0, E / np.where(norm > 0, norm, 1.0)[:, None], d)
            clean, att = self.perceive(p, kappa, target)
        else:
            raise ValueError(f"unknown camera adversary {kind!r}: one of {CAMERA_ADVERSARIES}")
        return att - p, np.hypot(*(att - clean).T)


def run_camera(cl: CameraLoop, p0: np.ndarray, kappa: np.ndarray, kind: str, record: bool = True) -> dict:
    """Runs from `p0` `(N, 2)` through the camera under adversary `kind` with budgets `kappa` `(N,)`; the final
    batch (and the true positions per frame `path` `(F + 1, N, 2)` with `record`). Ended runs render nothing."""
    loop = cl.loop
    p0 = np.asarray(p0, float)
    kappa = np.asarray(kappa, float)
    n = len(p0)
    reach = np.full(n, np.nan)
    probe = {"p": p0, "xd": loop.controller.initial_state(p0)}
    e, reach = cl.frame_error(probe, kappa, kind, reach)
    st = loop.start(p0, e)  # frame 0 perceives the same image for the initial state and the first input
    path = [st["p"].copy()] if record else None
    while st["frame"] < loop.n_frames and (st["outcome"] == RUNNING).any():
        if st["frame"] > 0:
            rows = np.flatnonzero(st["outcome"] == RUNNING)
            e = np.zeros((n, 2))
            e[rows], reach[rows] = cl.frame_error(FrameLoop.take(st, rows), kappa[rows], kind, reach[rows])
        st = loop.step(st, e)
        if record:
            path.append(st["p"].copy())
    if record:
        st["path"] = np.stack(path)
    return st


# ------------------------------------------------------------------------------------------ κ_hi
@dataclass
class CameraBracket:
    """Per start: `kappa_hi` (levels; inf: no failure up to `kappa_max`), the adversary (`none`: the clean loop
    fails, `κ_hi = 0`) and outcome of the counterexample at `kappa_hi`, its path `(F + 1, N, 2)` (NaN rows for
    starts without one); `tried`: `(budgets tried, failures)` per step."""

    kappa_hi: np.ndarray
    adversary: np.ndarray
    outcome: np.ndarray
    path: np.ndarray
    tried: list = field(default_factory=list)


def falsify_camera(cl: CameraLoop, p0: np.ndarray, kappa_max: int,
                   adversaries=CAMERA_ADVERSARIES) -> CameraBracket:
    """`κ_hi` per start by bisection on the integer levels `[0, kappa_max]` (module docstring)."""
    loop, p0 = cl.loop, np.asarray(p0, float)
    n = len(p0)
    kappa_hi, which = np.full(n, np.inf), np.full(n, "", dtype=object)
    outc, path = np.zeros(n, np.int8), np.full((loop.n_frames + 1, n, 2), np.nan)
    tried = []

    def run(_loop, p, k, kind, _search):
        return run_camera(cl, p, k, kind)

    def trial(rows, kappa, kinds, names):
        res = attack(loop, p0[rows], kappa, None, kinds, run=run)
        failed, idx, out, pth = scatter(n, rows, res, loop)
        k_all = np.full(n, np.inf)
        k_all[rows] = kappa
        better = failed & (k_all < kappa_hi)
        kappa_hi[better], outc[better] = k_all[better], out[better]
        which[better] = [names[i] for i in idx[better]]
        path[:, better] = pth[:, better]
        tried.append((sorted({float(k) for k in kappa}), int(failed.sum())))
        return failed[rows]

    every = np.arange(n)
    trial(every, np.zeros(n), ("fixed",), ("none",))  # κ = 0: no attack, the map's own error
    lo, hi = np.zeros(n, int), np.full(n, int(kappa_max))
    rows = np.flatnonzero(~np.isfinite(kappa_hi))
    if rows.size:
        trial(rows, hi[rows].astype(float), adversaries, adversaries)
    while True:
        rows = np.flatnonzero(np.isfinite(kappa_hi) & (kappa_hi > 0) & (hi - lo > 1))
        if rows.size == 0:
            break
        mid = (lo[rows] + hi[rows]) // 2
        failed = trial(rows, mid.astype(float), adversaries, adversaries)
        hi[rows] = np.where(failed, mid, hi[rows])
        lo[rows] = np.where(failed, lo[rows], mid)
    return CameraBracket(kappa_hi=kappa_hi, adversary=which, outcome=outc, path=path, tried=tried)
