"""The closed loop's parts built from a composed config: the one builder `simulate`, the experiments' context, the
Gymnasium environments and the bracket read their scene, vehicle, sim and camera settings and their feedback
laws from (issue 47), with the checks between them (the frame period a whole number of steps, the vehicle's
time model) done once, here."""

from __future__ import annotations

from dataclasses import dataclass

from omegaconf import DictConfig

from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.plants import Plant, SingleIntegrator, explain_steering
from pipeline.sim.settings import CameraSettings, SimSettings, check_vehicle, frame_steps


@dataclass(frozen=True)
class LoopParts:
    """`scene`, the vehicle `plant` (the single integrator when the config has no `vehicle`), the `sim` and
    `camera` settings (checked together); `law` builds a feedback law on the vehicle's steering scene."""

    scene: object
    plant: Plant
    sim: SimSettings
    camera: CameraSettings

    def law(self, node, field: str = "controller", scene=None):
        """The feedback law of `node` (its config `field`) steering the vehicle's steered point in
        `plant.steering_scene(scene)` (the unicycle's discs grown by its look-ahead, SPEC §3.7; default: the run's
        scene); a scene the grown discs make invalid is one line saying so."""
        try:
            return build(node, field, scene=self.plant.steering_scene(scene or self.scene))
        except ConfigError as err:
            raise explain_steering(self.plant, err) from None


def loop_parts(cfg: DictConfig) -> LoopParts:
    """The parts of the run's closed loop (module docstring); bad input is one ConfigError line naming the key."""
    scene = build(cfg.scene, "scene")
    plant = build(cfg.vehicle, "vehicle") if cfg.get("vehicle") is not None else SingleIntegrator()
    sim, camera = build(cfg.sim, "sim"), build(cfg.camera, "camera")
    frame_steps(sim.dt, camera.period)
    check_vehicle(plant, sim)
    return LoopParts(scene, plant, sim, camera)
