"""The perception map `l(theta) ≈ p` (SPEC §2) below every stage: the network (:mod:`.network`), a map loaded by
id with batched prediction and its uncertainty (:mod:`.maps`), the camera in the loop (:mod:`.measure`), and
attacks through the camera (:mod:`.attacks`).

    from pipeline.perception.maps import load_perception_map
    from pipeline.perception import CameraMeasure
    pm = load_perception_map("clean")          # the map the current train config makes for the `clean` recipe
    xy = pm.predict(images)                    # uint8 (N, 60, 100, 3) -> (N, 2) world coordinates
    measure = CameraMeasure(pm.camera(), pm)   # the closed loop's measurement: render, infer, in one batch

This package's face imports no torch (:mod:`.measure` needs none); `maps`, `network` and `attacks` do.
"""

from pipeline.perception.measure import CameraMeasure, FollowerTarget, LeaderTrack, OracleMap

__all__ = ["CameraMeasure", "FollowerTarget", "LeaderTrack", "OracleMap"]
