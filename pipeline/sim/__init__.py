"""Batched hybrid-arc simulator (SPEC §1, §3.3, §3.5)."""

from pipeline.sim.disturbances import (
    DISTURBANCES,
    Adversarial,
    Alternating,
    Disturbance,
    Gaussian,
    NoDisturbance,
)
from pipeline.sim.simulator import TERMINATIONS, SimResult, check_timing, simulate, true_state

__all__ = [
    "DISTURBANCES", "Adversarial", "Alternating", "Disturbance", "Gaussian", "NoDisturbance",
    "TERMINATIONS", "SimResult", "check_timing", "simulate", "true_state",
]
