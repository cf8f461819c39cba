"""Control core (SPEC §3): scene and coverings, potentials, the hybrid controller and the smooth/CBF baselines.

Pure numpy on batches of `(N, 2)` points; no Hydra, no I/O. The feedback laws are pure (their logic state is
passed in and returned); `pipeline.sim` closes the loop with a plant and a measurement.
"""

from pipeline.control.baselines import CBFController, SmoothController
from pipeline.control.covering import (
    diamond_vertices,
    in_covering_set,
    in_diamond,
    sq_dist_to_wedge,
    sq_dist_to_wedge_grad,
    wedge_coords,
)
from pipeline.control.feedback import Feedback, saturate
from pipeline.control.hybrid import HybridController
from pipeline.control.potentials import (
    barrier,
    barrier_grad,
    potential,
    potential_and_grad,
    potential_grad,
    smooth_potential,
    smooth_potential_grad,
)
from pipeline.control.scene import Arena, Barrier, Covering, Obstacle, Scene

__all__ = [
    "Arena", "Barrier", "CBFController", "Covering", "Feedback", "HybridController", "Obstacle", "Scene",
    "SmoothController", "barrier", "barrier_grad", "diamond_vertices", "in_covering_set", "in_diamond",
    "potential", "potential_and_grad", "potential_grad", "saturate", "smooth_potential", "smooth_potential_grad",
    "sq_dist_to_wedge", "sq_dist_to_wedge_grad", "wedge_coords",
]
