"""Control core (SPEC §3): scene and covering, potentials, hybrid and smooth/CBF controllers.

Pure numpy on batches of `(N, 2)` points; no Hydra, no I/O.
"""

from pipeline.control.controllers import (
    CONTROLLERS,
    CBFController,
    Controller,
    HybridController,
    SmoothController,
    saturate,
)
from pipeline.control.covering import (
    diamond_vertices,
    in_covering_set,
    in_diamond,
    sq_dist_to_wedge,
    sq_dist_to_wedge_grad,
    wedge_coords,
)
from pipeline.control.potentials import (
    barrier,
    barrier_grad,
    potential,
    potential_and_grad,
    potential_grad,
    smooth_potential,
    smooth_potential_grad,
)
from pipeline.control.scene import Scene

__all__ = [
    "CONTROLLERS", "CBFController", "Controller", "HybridController", "SmoothController", "Scene",
    "barrier", "barrier_grad", "diamond_vertices", "in_covering_set", "in_diamond", "potential",
    "potential_and_grad", "potential_grad", "saturate", "smooth_potential", "smooth_potential_grad",
    "sq_dist_to_wedge", "sq_dist_to_wedge_grad", "wedge_coords",
]
