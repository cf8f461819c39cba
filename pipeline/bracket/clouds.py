"""The certified error map under clouds as the bracket's `ε̄` (issue 44; docs/bracket.md, "Under clouds").

The clouds app (`python -m pipeline.certify.clouds_cli`, docs/certify.md "Under clouds") writes a tracked folder,
`<paths.certified_dir>/clouds/<map>_<level>-<id>/`, whose `table.csv` gives per cell `P` of positions
`eps_bar_delta(P)`: with confidence `1 - β` (per cell), a frame at any position of `P` rendered under a fresh layout of
the level's cloud process is within `eps_bar_delta(P)` of the truth with probability `>= 1 - δ`. Read as `ε̄`
(`bracket.error_map=<that folder, its name-id or its table.csv>`), the certificate's conclusion becomes a statement in
probability over the clouds, per start certified with it (`bracket.csv`'s `clouds_p_fail`):

    P(the run fails) <= F δ  (+ the lost frames' `(F - L) p^(L+1)` when `camera.p_fail > 0`)

with `F` the start's certified arrival bound in frames (`map_arrival_bound / T_s`): a run whose every frame lies
within its cell's bound is a run the abstraction covers, so it arrives within `F` frames; before that, each frame's
layout is drawn afresh, independently of where the run is, so a union bound over those `F` frames bounds the chance
that any of them leaves its cell's bound. It holds given the Clopper-Pearson statements of the cells the run passes;
each holds at confidence `1 - β`, and all the table's `n` cells together at `1 - n β` at least (Bonferroni:
`certificate.json`'s `clouds.joint_confidence`, 0 when vacuous). This is the honest first version; docs/certify.md
("What the bracket reads from this table, and why it says little yet") says what is better: one statistic per layout over the whole
region (a single confidence), and `δ` small enough that `F δ` says something (at `δ = 0.01` a run of 100 frames is
bounded by 1).

With `bracket.error_map_gated` the table's gated column is read instead: `eps_bar_delta_gated(P)` holds for a frame
with probability `>= 1 - δ` or the frame is flagged, that is, surely dropped by a loop whose `camera.gate` is at most
the table's gate (required, with `bracket.lost_frames >= 1`, the drops being lost frames of the proof). Then `F δ`
bounds the failures of the runs with at most `L` frames dropped in a row: the table bounds how often a frame is
flagged from below, not how many are dropped in a row (`certificate.json` says so). Refused in one line: the gated
column without a gate in the loop or above the table's, a table without one, a pixel budget `κ > 0` (the clouds app
certifies `κ = 0`), a clouds table beside other tables (the smallest of two bounds that each hold with probability
`1 - δ` holds with `1 - 2δ` only), and the camera falsifier's `κ_lo` (it is a clean-image certificate).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import tracking
from pipeline.bracket.bounds import CellTable
from pipeline.errors import ConfigError

SUMMARY = "clouds.json"


def clouds_folder(ref: Path) -> Path | None:
    """The clouds output `ref` names (its folder, or its `table.csv`), None when it is not one."""
    folder = ref if ref.is_dir() else ref.parent
    if not (folder / SUMMARY).is_file() or (ref.is_file() and ref.name != "table.csv"):
        return None
    return folder


@dataclass(frozen=True)
class CloudsBound:
    """What a clouds table claims (module docstring): per cell, within `eps_bar_delta` with probability `>= 1 - delta`
    per frame at confidence `confidence`, for perception map `map_id` under cloud level `level`."""

    map_id: str
    level: str
    layouts: int
    delta: float
    confidence: float
    cells: int
    gate: float | None = None  # the gated column: frames whose predicted error is surely above it are dropped

    @property
    def joint_confidence(self) -> float:
        """Every cell's statement at once (Bonferroni), 0 when vacuous."""
        return max(0.0, 1.0 - self.cells * (1.0 - self.confidence))

    def p_fail(self, frames: np.ndarray, max_lost: int = 0, p_lost: float = 0.0) -> np.ndarray:
        """The bound on a run's failure over the clouds, per start of certified arrival bound `frames` (NaN: not
        certified): `F δ`, plus `(F - L) p^(L+1)` for frames lost with probability `p_lost`, at most 1."""
        f = np.asarray(frames, float)
        lost = np.maximum(f - max_lost, 0.0) * p_lost ** (max_lost + 1) if p_lost > 0 else 0.0
        return np.minimum(1.0, f * self.delta + lost)

    def summary(self) -> dict:
        given = "" if self.gate is None else ", for the runs with at most L frames dropped in a row (not bounded here)"
        return {**asdict(self), "joint_confidence": self.joint_confidence,
                "per_run": "P(fail) <= F delta (+ the lost frames' (F - L) p^(L+1)), F the certified arrival bound in "
                           f"frames, given the statements of the cells the run passes (each at `confidence`){given}"}


def clouds_table(folder: Path, arena=None, gated: bool = False, camera_gate: float | None = None) -> CellTable:
    """The clouds output's table as a :class:`CellTable` of `eps_bar_delta` (`gated`: `eps_bar_delta_gated`, for a
    loop gated at `camera_gate`), with its claim as `.clouds`; one line naming the field where it would not hold."""
    summary = json.loads((folder / SUMMARY).read_text())
    table = pd.read_csv(folder / "table.csv", float_precision="round_trip")  # the app's header: no comment mark
    column = "eps_bar_delta_gated" if gated else "eps_bar_delta"
    gate = (summary.get("gated") or {}).get("gate")
    if gated and (gate is None or column not in table.columns):
        raise ConfigError("bracket.error_map_gated", f"{folder.name} was certified without a gate (clouds.gate): it "
                                                     "has no gated column")
    if gated and (camera_gate is None or camera_gate > float(gate)):
        raise ConfigError("camera.gate", f"the gated column drops the frames whose predicted error is surely above "
                                         f"{float(gate):g} (the table's gate): the loop's gate must be at most that, got "
                                         f"{camera_gate}")
    if column not in table.columns:
        raise ConfigError("bracket.error_map", f"{folder.name}/table.csv has no {column} column")
    out = CellTable(table.rename(columns={column: "eps_bar"})[["x0", "x1", "y0", "y1", "eps_bar"]], arena=arena)
    model = (tracking.read_manifest(folder).get("inputs") or {}).get("model")
    out.clouds = CloudsBound(map_id=str(model), level=str(summary["occlusion"]), layouts=int(summary["layouts"]),
                             delta=float(summary["delta"]), confidence=float(summary["confidence"]),
                             cells=len(table), gate=float(gate) if gated else None)
    out.name = f"clouds {out.clouds.level}: {column} (delta {out.clouds.delta:g})"
    return out


def check_alone(n_refs: int, kappa: float, camera_folder) -> None:
    """A clouds table is read alone, at `κ = 0`, without the camera's `κ_lo` (module docstring), or one line."""
    if n_refs > 1:
        raise ConfigError("bracket.error_map", "a clouds table is read alone: the smallest of bounds that each hold with "
                                               "probability 1 - delta holds with less")
    if kappa > 0:
        raise ConfigError("bracket.error_map_kappa", f"the clouds table certifies kappa 0 (clean pixels under the "
                                                     f"clouds), got {kappa:g}")
    if camera_folder is not None:
        raise ConfigError("bracket.camera_map", "the camera falsifier's kappa_lo is a clean-image certificate, not one "
                                                "under clouds: null with a clouds table")
