"""Hybrid systems on batches and the two solvers that take any of them (the Hybrid Equations Toolbox's shape).

A system is its four maps (`flow_map`, `jump_map`, `flow_set`, `jump_set`; jumps take priority in `C ∩ D`) on a
batch of states :class:`State`, with its plant (the flowing part). :func:`solve_sampled` runs it as a
sampled-data loop (a frame every `every` steps, the input held in between); :func:`solve_continuous`
integrates its flow adaptively and locates its jumps in time. Neither solver names a controller or a plant.
"""

from pipeline.hybrid.continuous import METHODS, solve_continuous
from pipeline.hybrid.sampled import solve_sampled
from pipeline.hybrid.state import State
from pipeline.hybrid.system import Arc, HybridSystem, Monitor

__all__ = ["METHODS", "Arc", "HybridSystem", "Monitor", "State", "solve_continuous", "solve_sampled"]
