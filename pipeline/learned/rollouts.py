"""One evaluation code for every agent (SPEC §6): a policy in the vector environment from given starts, clean or
under the pixel attack on the policy's own network, with per-agent outcomes.

Outcomes: `reached` (`|p - p_T| <= δ`), `collided`, `left_view`, `stalled` (at the horizon, moved less than
`stall_speed * stall_time` over the last `stall_time` seconds: the sim's stall speed and window, on the net
displacement), `timed_out` (the rest).

The attack (:class:`PolicyAttack`): each frame, before the policy reads it, the frame is replaced by
:func:`pipeline.perception.attacks.pixel_attack` (L-inf PGD, `|δ| <= κ` intensity levels, the camera's rounding)
through the network that turns the policy's frame into its decision, pushing that network's output along
`d = -sign(b(p)) e_b` (:func:`pipeline.perception.adversary.proposition1_direction`, from the true position):
for an end-to-end policy its velocity `max d·π(θ + δ)` (to turn it to the other side of the obstacle); for the
paper's architecture and the learned hybrid policy the perception map's estimate (SPEC §3.5's attack through the
camera). The induced output change `d·(out(θ + δ) - out(θ))` and its norm are recorded per frame.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch
from torch import nn

from pipeline.envs.core import OUTCOMES
from pipeline.envs.navigate import NavigateVectorEnv
from pipeline.perception.attacks import pixel_attack, worst_cloud
from pipeline.sim.metrics import Outcome
from pipeline.sim.simulator import stall_threshold

CLASSES = OUTCOMES[1:]  # :class:`pipeline.sim.metrics.Outcome`'s names but `running`


class HeadNet(nn.Module):
    """`net(float frames in [0, 255]) -> (N, 2)` velocities of one head of the imitation network."""

    def __init__(self, model, head: int = 0):
        super().__init__()
        self.model, self.head = model, head

    def forward(self, x):
        return self.model(x * (1.0 / 255.0))[:, self.head]


@dataclass
class PolicyAttack:
    """The pixel attack on `net` (see the module docstring); `along`, `norm`: the induced change per frame."""

    net: nn.Module
    direction_fn: object
    kappa: float = 1.0
    steps: int = 2
    along: list = field(default_factory=list)
    norm: list = field(default_factory=list)

    def __call__(self, images: np.ndarray, p: np.ndarray, alive: np.ndarray) -> np.ndarray:
        out = images.copy()
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            return out
        res = pixel_attack(self.net, images[idx], self.direction_fn(p[idx]), kappa=self.kappa, steps=self.steps)
        out[idx] = res.images
        self.along.append(res.along)
        self.norm.append(res.norm)
        return out

    def summary(self) -> tuple[float, float]:
        if not self.along:
            return 0.0, 0.0
        return float(np.concatenate(self.along).mean()), float(np.concatenate(self.norm).mean())


@dataclass
class PolicyWorstCloud:
    """The worst cloud on `predict` (the network that turns the agent's frame into its decision: a policy's
    velocity, or a map's estimate): each frame, per agent, the worst of `candidates` layouts of `occlusion`'s
    clouds (:func:`pipeline.perception.attacks.worst_cloud`: the one pushing `predict`'s output furthest along
    `d`), drawn from a generator seeded by `seed`; `along`, `norm`: the induced change per frame."""

    camera: object
    occlusion: object
    predict: object
    direction_fn: object
    candidates: int = 4
    seed: int = 0
    along: list = field(default_factory=list)
    norm: list = field(default_factory=list)

    def __post_init__(self):
        self.rng = np.random.default_rng(self.seed)

    def __call__(self, images: np.ndarray, p: np.ndarray, alive: np.ndarray) -> np.ndarray:
        out = images.copy()
        idx = np.flatnonzero(alive)
        if idx.size == 0:
            return out
        res = worst_cloud(self.camera, self.occlusion, p[idx], self.direction_fn(p[idx]), self.predict,
                          candidates=self.candidates, rng=self.rng)
        out[idx] = res.images
        self.along.append(res.along)
        self.norm.append(res.norm)
        return out

    summary = PolicyAttack.summary


def run_policy(obj, policy, starts: np.ndarray, *, seed: int = 0, attack: PolicyAttack | PolicyWorstCloud | None = None,
               frames: int | None = None) -> dict:
    """Every start's episode under `policy` (its `act`: the env's normalised actions, issue 46): `outcome`
    (CLASSES), `time` (s, NaN unless reached), `paths`. The
    stall speed and window are the run's `sim` (:func:`pipeline.sim.simulator.stall_threshold`: `sim.stall_speed`,
    or `sim.stall_share` of the controller's `u_max` when it is null)."""
    stall_speed, stall_time = stall_threshold(obj.sim, obj.controller), obj.sim.stall_time
    venv = NavigateVectorEnv(len(starts), objects_=obj, autoreset=False)
    obs, info = venv.reset(seed=seed, options={"start": np.asarray(starts, float)})
    if hasattr(policy, "x"):
        policy.x = None
    code = np.zeros(len(starts), dtype=np.int8)
    t_end = np.full(len(starts), np.nan)
    paths = [info["position"].copy()]
    frames = frames or venv.core.frames
    with torch.inference_mode(False):
        for _ in range(frames):
            alive = ~venv.done
            seen = obs if attack is None else attack(obs, info["position"], alive)
            obs, _, term, trunc, info = venv.step(policy.act(seen))
            new = (term | trunc) & (code == 0)
            code[new], t_end[new] = info["outcome"][new], info["t"][new]
            paths.append(info["position"].copy())
            if venv.done.all():
                break
    paths = np.array(paths)
    window = int(round(stall_time / venv.core.period))
    moved = np.hypot(*(paths[-1] - paths[max(0, len(paths) - 1 - window)]).T)
    at_horizon = (code == Outcome.RUNNING) | (code == Outcome.TIMED_OUT)
    code = np.where(at_horizon & (moved < stall_speed * stall_time), Outcome.STALLED,
                    np.where(code == Outcome.RUNNING, Outcome.TIMED_OUT, code))
    outcome = np.asarray(OUTCOMES)[code]
    return {"outcome": outcome, "time": np.where(outcome == "reached", t_end, np.nan), "paths": paths}
