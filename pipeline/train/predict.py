"""Loading a trained perception map for the next stages: batched inference on uint8 images."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import torch

from pipeline import tracking
from pipeline.cli import REPO_ROOT
from pipeline.errors import DatasetError, ModelError
from pipeline.train.model import PerceptionMap

DEFAULT_MODELS_DIR = REPO_ROOT / "outputs" / "models"


class PerceptionMapPredictor:
    """`predict(images uint8 (N, H, W, 3)) -> (N, 2)` world coordinates, in inference mode, channels_last."""

    def __init__(self, model: PerceptionMap, manifest: dict | None = None, path: Path | None = None,
                 batch_size: int = 1024):
        self.model = model.eval()
        self.manifest = manifest or {}
        self.path = Path(path) if path else None
        self.batch_size = batch_size
        self.id = self.manifest.get("id")
        self.name = self.manifest.get("name", model.hparams.get("name"))
        self.image_shape = model.image_shape
        self.px_per_unit = model.px_per_unit

    def __repr__(self) -> str:
        return f"PerceptionMapPredictor({self.name}-{self.id})"

    def predict(self, images) -> np.ndarray:
        images = np.asarray(images)
        if images.ndim == 3:
            images = images[None]
        if images.ndim != 4 or tuple(images.shape[1:]) != self.image_shape:
            raise ModelError(f"perception map {self.name}: image shape {tuple(images.shape[1:])} does not "
                             f"match the model's {self.image_shape}")
        out = np.empty((len(images), 2), dtype=np.float64)
        with torch.inference_mode():
            for s in range(0, len(images), self.batch_size):
                chunk = images[s : s + self.batch_size]
                if not (chunk.flags.writeable and chunk.flags.c_contiguous):
                    chunk = np.array(chunk)  # memory-mapped/read-only input: torch wants a writable buffer
                batch = torch.from_numpy(chunk)
                out[s : s + len(batch)] = self.model(batch).numpy()
        return out

    __call__ = predict

    def camera(self):
        """The Camera that rendered this map's training data (scene, arena, colours, sizes)."""
        from pipeline.render import Camera

        try:
            return Camera.from_config(self.manifest["render"], self.manifest["scene"])
        except KeyError as err:
            raise ModelError(f"perception map {self.name}: manifest has no {err.args[0]!r} config") from None


def load_perception_map(ref, models_dir=None, *, verify: bool = False) -> PerceptionMapPredictor:
    """A trained map by path, `name-id`, id, or name (the map the current train config makes for that
    dataset recipe; see :mod:`pipeline.lineage`)."""
    from pipeline.lineage import resolve_map

    root = Path(models_dir) if models_dir else DEFAULT_MODELS_DIR
    try:
        folder = resolve_map(ref, root)
    except DatasetError as err:  # unknown name/id: reported as the model's error
        raise ModelError(str(err)) from None
    if verify:
        problems = tracking.verify(folder)
        if problems:
            raise ModelError(f"perception map {folder.name} fails verification: {problems[0]}")
    manifest = tracking.read_manifest(folder)
    blob = torch.load(folder / "model.pt", map_location="cpu", weights_only=True)
    model = PerceptionMap(**blob["hparams"])
    model.load_state_dict(blob["state_dict"])
    return PerceptionMapPredictor(model, manifest=manifest, path=folder)
