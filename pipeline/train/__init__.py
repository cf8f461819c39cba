"""Train stage (SPEC §2): CNN perception maps `l(theta) ≈ p` on tracked datasets.

    from pipeline.train import load_perception_map
    pm = load_perception_map("clean")          # latest map trained on the `clean` dataset
    xy = pm.predict(images)                    # uint8 (N, 60, 100, 3) -> (N, 2) world coordinates
"""

from pipeline.train.model import PerceptionMap
from pipeline.train.predict import DEFAULT_MODELS_DIR, PerceptionMapPredictor, load_perception_map

__all__ = ["DEFAULT_MODELS_DIR", "PerceptionMap", "PerceptionMapPredictor", "load_perception_map"]
