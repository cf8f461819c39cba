"""`python -m pipeline.certify.clouds_cli clouds.maps=<ref> clouds.occlusion=heavy clouds.layouts=299 ...`: perception
certified under clouds (issue 44; :mod:`pipeline.certify.clouds`), a Hydra app (conf/certify_clouds.yaml).

For the map and the cells of `clouds.region`: a sound bound per cell and cloud layout (N layouts of the level's own
process), the Clopper-Pearson `eps_bar_delta` per cell, and two checks of it: `samples` positions per cell and
layout rendered with that layout through the real camera (none may pass its layout's bound) and `fresh` frames per
cell under fresh layouts (the share above `eps_bar_delta` should sit under `delta`). With `clouds.gate` (a number,
`camera.gate`'s units; `clean`: the map's own clean-image gate from its manifest; null: no gate) the map's predicted
error is bounded too (:mod:`pipeline.certify.gate`): the table adds `eps_bar_delta_gated`, `flagged_share`,
`undecided_share` (a flagged frame is dropped, no error). Writes `table.csv` (one row per cell) and `clouds.json`
(the summary) into a tracked folder, `<paths.certified_dir>/clouds/<map>_<level>-<id>/` (the id: the settings that
determine its bytes, the map's id, its scene and the code), and prints one summary line (two with a gate). In shards
like the certify stage (:mod:`.shards`: `clouds.shards`, `clouds.shard`, chunks of `clouds.chunk` cells). Bad
settings: one line, exit 2.
"""

from __future__ import annotations

import dataclasses
from dataclasses import asdict, dataclass
from typing import Literal

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.errors import ConfigError
from pipeline.lineage import resolve_map
from pipeline.render.occlusion import load_occlusion
from pipeline.schema import NonNegative, NonNegativeInt, OpenShare, Positive, PositiveInt, checked

F = "clouds"


@checked(F)
@dataclass(frozen=True)
class CloudsSettings:
    """The keys under `clouds.` (conf/certify_clouds.yaml describes each)."""

    maps: str = "occluded_keypoint"
    occlusion: str = "heavy"
    layouts: PositiveInt = 299
    delta: OpenShare = 0.01
    confidence: OpenShare = 0.95
    seed: NonNegativeInt = 0
    draw: Literal["per_chunk", "shared"] = "per_chunk"
    cell: Positive = 0.25
    region: list[list[float]] = dataclasses.field(default_factory=lambda: [[-30.0, -11.5], [-2.0, 2.0]])
    limit: PositiveInt | None = None
    mode: Literal["crown", "forward", "ibp"] = "crown"
    tolerance: Positive = 1.0
    max_depth: NonNegativeInt = 0
    samples: NonNegativeInt = 2
    fresh: NonNegativeInt = 200
    threads: PositiveInt = 1
    gate: Literal["clean"] | Positive | None = None
    dtype: Literal["float32", "float64"] = "float32"
    float_margin: NonNegative = 0.002
    chunk: PositiveInt = 64
    shards: PositiveInt = 1
    shard: NonNegativeInt | None = None
    force: bool = False
    progress: bool = True

    def __post_init__(self):
        ok = len(self.region) == 2 and all(len(r) == 2 and r[0] < r[1] for r in self.region)
        if not ok:
            raise ConfigError(f"{F}.region", f"must be [[x0, x1], [y0, y1]] with x0 < x1 and y0 < y1, got "
                                             f"{self.region!r}")
        if self.shard is not None and self.shard >= self.shards:
            raise ConfigError(f"{F}.shard", f"must be below {F}.shards ({self.shards}): shards are 0 .. "
                                            f"{self.shards - 1}, got {self.shard}")

    def recipe(self) -> dict:
        """What determines the output's bytes (the map apart: it enters the id by its own id)."""
        return {k: v for k, v in asdict(self).items() if k not in VOLATILE}


VOLATILE = ("maps", "threads", "shards", "shard", "force", "progress")


def check(cfg: DictConfig) -> dict:
    """Preflight (no torch): every setting, the map's folder and the cloud level, or one line naming the field."""
    s = CloudsSettings(**tracking.to_plain(cfg.clouds))
    occ = load_occlusion(s.occlusion, field=f"{F}.occlusion")
    folder = resolve_map(s.maps, cfg.paths.models_dir, field=f"{F}.maps")
    if s.gate == "clean":  # the number enters the id: the same output as passing it
        s = dataclasses.replace(s, gate=clean_gate(folder))
    return {"settings": s, "occlusion": occ, "folder": folder}


def clean_gate(folder) -> float:
    """The map's own clean-image gate (its manifest's `metrics.calibration.clean_gate.gate_px`: the operating point
    the train stage fitted, docs/train.md; 1 px = 1 world unit here), or one line naming `clouds.gate`."""
    gate = ((tracking.read_manifest(folder).get("metrics") or {}).get("calibration") or {}).get("clean_gate") or {}
    if not isinstance(gate.get("gate_px"), (int, float)):
        raise ConfigError(f"{F}.gate", f"clean: perception map {folder.name} has no clean gate in its manifest (a map "
                                       "trained with model.uncertainty=gaussian has one); give the gate as a number")
    return float(gate["gate_px"])


main = stage_main("certify_clouds", run="pipeline.certify.clouds_run:run", check="pipeline.certify.clouds_cli:check")

if __name__ == "__main__":
    main()
