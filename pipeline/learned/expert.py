"""The expert of the imitation (SPEC §6): the hybrid controller at the true state, its mode carried along the
trajectory it labels (initialised by §3.3's rule at the trajectory's start), and its flow in each mode.

:func:`mode_flows` gives, at true positions `p`, the guarded flow of mode `q` (SPEC §3.3, as the sampled loop
holds it) and whether `p` lies in mode `q`'s flow set `V_q <= χ V_{3-q}` (where the learned hybrid policy's
mode-`q` head is used and trained).
"""

from __future__ import annotations

import numpy as np

from pipeline.envs.policies import ArchitecturePolicy
from pipeline.learned.network import HEADS


class TrueState:
    """The perfect perception map of an expert: `predict` returns the true states set by :meth:`see`."""

    name = "true_state"

    def __init__(self):
        self.state = None

    def see(self, state: np.ndarray) -> TrueState:
        self.state = np.asarray(state, dtype=float)
        return self

    def predict(self, images) -> np.ndarray:
        return self.state


class Expert:
    """The hybrid controller on the true state, one logic state per agent (an ArchitecturePolicy with a perfect map).

    Its labels are velocities in world units (what the network imitates); `act` is the env's normalised action
    (`velocity / scale`, `scale` the env's: None, the controller's `u_max`, the env's own when it is the env's
    controller). Each of `act`, `velocity`, `labels` advances the logic state one frame: call one per frame."""

    def __init__(self, controller, plant, scene, period: float, scale=None):
        self.eye = TrueState()
        self.policy = ArchitecturePolicy(self.eye, controller, plant, scene, period, name="expert", scale=scale)
        self.controller, self.plant, self.period = controller, plant, period

    def velocity(self, state: np.ndarray, restarted: np.ndarray | None = None) -> np.ndarray:
        """The controller's held input at the true states (world units)."""
        self.eye.see(state)
        return self.policy.velocity(state, restarted)

    def act(self, state: np.ndarray, restarted: np.ndarray | None = None) -> np.ndarray:
        """The env's action: :meth:`velocity` over the env's scale."""
        self.eye.see(state)
        return self.policy.act(state, restarted)

    def labels(self, state: np.ndarray, restarted: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """`(labels (N, HEADS, 2), mask (N, HEADS))`, velocities in world units: the expert's (its mode carried),
        each mode's flow. The env's action of the first is `env.core.action(labels[:, 0])`."""
        out = np.zeros((len(state), HEADS, 2))
        mask = np.ones((len(state), HEADS), dtype=bool)
        out[:, 0] = self.velocity(state, restarted)
        out[:, 1:], mask[:, 1:] = mode_flows(self.controller, self.plant.point(state), self.policy.x.i, self.period)
        return out, mask


def mode_flows(controller, p: np.ndarray, i: np.ndarray, period: float) -> tuple[np.ndarray, np.ndarray]:
    """The guarded flow of each mode at `p` `(N, 2, 2)` and its flow set `(N, 2)` (active obstacles `i`)."""
    flows = np.zeros((len(p), 2, 2))
    inside = np.zeros((len(p), 2), dtype=bool)
    for q in (1, 2):
        xd = {"i": np.asarray(i), "q": np.full(len(p), q, dtype=np.int8)}
        ev = controller.evaluate(p, xd)
        u = controller.flow_map(p, xd, None, ev=ev)
        flows[:, q - 1], _ = controller.hold(u, p, xd, ev, period)
        inside[:, q - 1] = controller.flow_set(p, xd, None, ev=ev)
    return flows, inside
