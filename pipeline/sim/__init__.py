"""Batched hybrid-arc simulator (SPEC §1, §3.3, §3.5)."""

from pipeline.sim.disturbances import (
    DISTURBANCES,
    Adversarial,
    Alternating,
    Disturbance,
    Gaussian,
    NoDisturbance,
)
from pipeline.sim.metrics import OUTCOMES, summarise_agents, wilson
from pipeline.sim.simulator import MODELS, TERMINATIONS, SimResult, check_timing, simulate, true_state

__all__ = [
    "DISTURBANCES", "MODELS", "OUTCOMES", "Adversarial", "Alternating", "Disturbance", "Gaussian", "NoDisturbance",
    "TERMINATIONS", "SimResult", "check_timing", "simulate", "summarise_agents", "true_state", "wilson",
]
