"""The camera `theta = h(p)` (SPEC §1): batched renderer, world-to-pixel map, occlusion clouds.

    from pipeline.render import Camera, load_occlusion
    cam = Camera(scene)                       # 60 x 100 px arena of SPEC §1
    imgs = cam.render(leader_xy, follower_xy, occlusion=load_occlusion("heavy"), rng=rng)
"""

from pipeline.render.camera import (
    DEFAULT_ARENA,
    DEFAULT_COLORS,
    Camera,
    RenderResult,
    pixel_to_world,
    save_png,
    world_to_pixel,
)
from pipeline.render.occlusion import CloudSample, Occlusion, load_occlusion, occlusion_levels

__all__ = [
    "DEFAULT_ARENA",
    "DEFAULT_COLORS",
    "Camera",
    "CloudSample",
    "Occlusion",
    "RenderResult",
    "load_occlusion",
    "occlusion_levels",
    "pixel_to_world",
    "save_png",
    "world_to_pixel",
]
