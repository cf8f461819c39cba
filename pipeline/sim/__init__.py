"""The closed loop (SPEC §1, §3.3, §3.5): plant + feedback law + measurement as one hybrid system, simulated in
batches by the solvers of :mod:`pipeline.hybrid`; disturbances, outcomes and the reviewer's tables."""

from pipeline.sim.closed_loop import ContinuousLoop, SampledLoop, true_state
from pipeline.sim.disturbances import (
    Adversarial,
    Alternating,
    Disturbance,
    Gaussian,
    NoDisturbance,
    WorldAlternating,
)
from pipeline.sim.metrics import OUTCOMES, summarise_agents, wilson
from pipeline.sim.settings import CameraSettings, SimSettings, frame_steps
from pipeline.sim.simulator import MODELS, TERMINATIONS, SimResult, simulate

__all__ = [
    "MODELS", "OUTCOMES", "Adversarial", "Alternating", "CameraSettings", "ContinuousLoop",
    "Disturbance", "Gaussian", "NoDisturbance", "SampledLoop", "SimResult", "SimSettings", "TERMINATIONS",
    "frame_steps", "simulate", "summarise_agents", "true_state", "wilson", "WorldAlternating",
]
