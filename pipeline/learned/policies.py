"""Learned policies over the environments' frames (same interface as :mod:`pipeline.envs.policies`).

- :class:`ImitatedPolicy`: the end-to-end policy `π(θ)`: head 0 of the imitation network (a feedback continuous
  in the image: Proposition 1 applies to it).
- :class:`LearnedHybridPolicy`: heads 1 and 2 (the imitated flows of mode 1 and 2), switched by §3.3's hysteresis
  on the perception map's estimate `m = l(θ)` (the HyRL idea through the camera): the mode logic is the hybrid
  controller's own (:class:`pipeline.envs.policies.ArchitecturePolicy`), the velocity the network's.

The network gives velocities in world units (:class:`pipeline.learned.network.VelocityPolicy`, trained on the
expert's velocities); `act` hands the env its normalised action, that velocity over the env's `scale`
(`env.core.scale`, issue 46), `velocity` the network's own output.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline.envs.core import to_action
from pipeline.envs.policies import ArchitecturePolicy, frames
from pipeline.errors import ConfigError
from pipeline.perception.maps import PerceptionMapPredictor, load_perception_map
from pipeline.perception.network import PerceptionNet


class ImitatedPolicy:
    """Head `head` of the network; `scale`: the env's (its action is `velocity / scale`)."""

    name = "imitated"

    def __init__(self, model, scale, head: int = 0):
        self.model, self.head, self.scale = model, head, np.asarray(scale, dtype=float)

    def reset(self, obs, idx=None) -> None:
        pass

    def velocity(self, obs, restarted=None) -> np.ndarray:
        return self.model.act(torch.from_numpy(np.ascontiguousarray(frames(obs))), self.head).double().numpy()

    def act(self, obs, restarted=None) -> np.ndarray:
        return to_action(self.velocity(obs, restarted), self.scale)


class LearnedHybridPolicy(ArchitecturePolicy):
    """The mode by the hysteresis on the map's estimate; the velocity by the imitated flow of that mode."""

    def __init__(self, model, perception_map, controller, plant, scene, period: float, scale=None):
        super().__init__(perception_map, controller, plant, scene, period, name="learned_hybrid", scale=scale)
        self.model = model

    def velocity(self, obs, restarted=None) -> np.ndarray:
        super().velocity(obs, restarted)  # the hybrid logic on the map's estimate (its mode jumps)
        q = torch.from_numpy(np.asarray(self.mode, dtype=np.int64))
        return self.model.act(torch.from_numpy(np.ascontiguousarray(frames(obs))), q).double().numpy()


def load_map(ref, models_dir):
    """The perception map `maps.clean`: a tracked map (name, name-id, id, folder), or a training checkpoint
    (`.ckpt`, e.g. a map whose build has not finished: its best epoch so far), named by its file."""
    path = Path(str(ref))
    if path.suffix == ".ckpt":
        if not path.is_file():
            raise ConfigError("maps.clean", f"no checkpoint {path}")
        blob = torch.load(path, map_location="cpu", weights_only=False)  # a Lightning checkpoint: the map's fields
        model = PerceptionNet.of(**blob["hyper_parameters"])
        model.load_state_dict(blob["state_dict"])
        return PerceptionMapPredictor(model, manifest={"name": "checkpoint", "id": path.stem}, device="cpu")
    return load_perception_map(ref, models_dir, device="cpu")
