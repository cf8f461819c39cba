"""`python -m pipeline.certify.clouds_cli clouds.maps=<ref> clouds.occlusion=heavy clouds.layouts=299 ...`: perception
certified under clouds (issue 44; :mod:`pipeline.certify.clouds`), a Hydra app (conf/certify_clouds.yaml).

For the map and the cells of `clouds.region`: a sound bound per cell and cloud layout (N layouts of the level's
own process), the Clopper-Pearson `eps_bar_delta` per cell, and two checks of it: `samples` positions per cell and
layout rendered with that layout through the real camera (none may pass its layout's bound) and `fresh` frames per
cell under fresh layouts (the share above `eps_bar_delta` should sit under `delta`). With `clouds.gate` (a number,
`camera.gate`'s units; null: no gate) the map's predicted error is bounded too (:mod:`pipeline.certify.gate`): the
table adds `eps_bar_delta_gated`, `flagged_share`, `undecided_share` (a flagged frame is dropped, no error). Writes
`table.csv` (one row per cell) and `clouds.json` (the summary; the run dir's `summary.json` is Hydra's job
record) to the run dir and prints one summary line (two with a gate). Not yet a tracked stage (no id, no
sharding): its outputs are a run's, like `python -m pipeline.simulate`'s. Bad settings: one line, exit 2.
"""

from __future__ import annotations

import numpy as np
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.errors import ConfigError
from pipeline.lineage import resolve_map
from pipeline.render.occlusion import load_occlusion

F = "clouds"


def check(cfg: DictConfig) -> dict:
    """Preflight (no torch): every setting, the map's folder and the cloud level, or one line naming the field."""
    s = tracking.to_plain(cfg.clouds)
    for key, lo, hi in (("delta", 0.0, 1.0), ("confidence", 0.0, 1.0)):
        v = s[key]
        if not isinstance(v, (int, float)) or not lo < v < hi:
            raise ConfigError(f"{F}.{key}", f"must be a number in ({lo:g}, {hi:g}), got {v!r}")
    for key in ("layouts", "threads"):
        if not isinstance(s[key], int) or isinstance(s[key], bool) or s[key] < 1:
            raise ConfigError(f"{F}.{key}", f"must be a positive integer, got {s[key]!r}")
    for key in ("samples", "fresh", "max_depth", "seed"):
        if not isinstance(s[key], int) or isinstance(s[key], bool) or s[key] < 0:
            raise ConfigError(f"{F}.{key}", f"must be a non-negative integer, got {s[key]!r}")
    if s["limit"] is not None and (not isinstance(s["limit"], int) or s["limit"] < 1):
        raise ConfigError(f"{F}.limit", f"must be null or a positive integer, got {s['limit']!r}")
    if not isinstance(s["cell"], (int, float)) or s["cell"] <= 0:
        raise ConfigError(f"{F}.cell", f"must be a positive number, got {s['cell']!r}")
    gate = s.get("gate")
    if gate is not None and (isinstance(gate, bool) or not isinstance(gate, (int, float)) or not 0 < gate < np.inf):
        raise ConfigError(f"{F}.gate", f"must be null or a positive number (camera.gate's world units), got {gate!r}")
    if s["mode"] not in ("crown", "forward", "ibp"):
        raise ConfigError(f"{F}.mode", f"must be crown, forward or ibp, got {s['mode']!r}")
    reg = np.asarray(s["region"], dtype=object)
    if reg.shape != (2, 2):
        raise ConfigError(f"{F}.region", f"must be [[x0, x1], [y0, y1]], got {s['region']!r}")
    occ = load_occlusion(s["occlusion"], field=f"{F}.occlusion")
    folder = resolve_map(s["maps"], cfg.paths.models_dir, field=f"{F}.maps")
    return {"settings": s, "occlusion": occ, "folder": folder}


main = stage_main("certify_clouds", run="pipeline.certify.clouds_run:run", check="pipeline.certify.clouds_cli:check")

if __name__ == "__main__":
    main()
