"""What a scenario computes with: the `Context` built once from the run's composed config (settings, scene,
vehicle, camera and sim settings), which is the composed objects (:mod:`.composed`), the maps by id (:mod:`.maps`)
and the run helpers (:mod:`.runs`). Cached results depend on this code, not on the drawing code."""

from __future__ import annotations

from pipeline import tracking
from pipeline.config import settings
from pipeline.control import Scene
from pipeline.experiments.composed import Composed
from pipeline.experiments.maps import MapsById
from pipeline.experiments.runs import Runs
from pipeline.experiments.settings import ExperimentSettings
from pipeline.sim.composed import loop_parts


class Context(Composed, MapsById, Runs):
    """Everything a scenario needs, built from the composed config; maps are loaded lazily, by id, with
    `load_map(folder, models_dir=, device=)` (the stage passes `pipeline.perception.maps.load_perception_map`; a
    preflight check passes none: it loads no map and imports no torch)."""

    def __init__(self, cfg, load_map=None):
        self.cfg = cfg
        self._load_map = load_map
        self.settings: ExperimentSettings = settings(cfg, ExperimentSettings)
        self.scene_cfg = tracking.to_plain(cfg.scene)
        # the loop's parts (pipeline.sim.composed, the one builder): the plant of every run (`vehicle`, SPEC §3.7)
        # is the one whose steered point the controllers steer in its steering scene
        self.parts = loop_parts(cfg)
        self.scene: Scene = self.parts.scene
        self.arena = self.scene.bounds
        self.scale = self.settings.scale
        self.perception = self.settings.perception
        self.camera_settings, self.sim, self.vehicle = self.parts.camera, self.parts.sim, self.parts.plant
        self.dt, self.horizon, self.delta = self.sim.dt, self.sim.horizon, self.sim.delta
        self.frame_period = self.camera_settings.period
        self.gate = self.camera_settings.gate  # camera.gate: doubtful frames of a map with an uncertainty head are failures
        self.seed = self.sim.seed
        self.warned: set[str] = set()  # steering warnings printed (once each)
        self.used: dict[str, str] = {}  # inputs used (map/dataset/error-map ids), for the index
        self._maps: dict = {}
        self.bar = None  # the stage's progress (pipeline.progress): one step per simulation (a batch of agents)
        self.label = ""  # what the scenario is at (a sweep's cell), shown with each step

    def load_map_with(self, load_map) -> None:
        """Load maps with `load_map` from now on (the run's context is the preflight's, which loads none)."""
        self._load_map = load_map
