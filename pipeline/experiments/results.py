"""What a scenario computes (cached; its id is the hash of what computes it, `stage.cache_key`): tables, arrays and
small facts, and the statistics its tables report."""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.sim.metrics import summarise_agents


# --------------------------------------------------------------------------------------- results
@dataclass
class Results:
    """What a scenario computes (cached): tables, arrays and small facts (JSON)."""

    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def save(self, folder: Path) -> None:
        for name, df in self.tables.items():
            df.to_csv(folder / f"{name}.csv", index=False)
        if self.arrays:
            np.savez_compressed(folder / "arrays.npz", **self.arrays)
        (folder / "info.json").write_text(json.dumps(self.info, indent=2, default=_json_default) + "\n")

    @classmethod
    def load(cls, folder: Path) -> Results:
        info = json.loads((folder / "info.json").read_text())
        tables = {p.stem: pd.read_csv(p, float_precision="round_trip") for p in sorted(folder.glob("*.csv"))}
        arrays = {}
        if (folder / "arrays.npz").is_file():
            with np.load(folder / "arrays.npz", allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        return cls(tables, arrays, info)


def _json_default(o):
    if isinstance(o, np.integer | np.floating | np.bool_):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# -------------------------------------------------------------------------------------- statistics
def mean_ci(x: np.ndarray, z: float = 1.96):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return math.nan, math.nan, math.nan
    m = float(x.mean())
    h = float(z * x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan
    return m, m - h, m + h


def median_ci(x: np.ndarray, rng: np.random.Generator, n_boot: int = 1000):
    """Median with a 95% bootstrap interval (vectorised resampling)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return math.nan, math.nan, math.nan
    boot = np.median(x[rng.integers(0, len(x), (n_boot, len(x)))], axis=1)
    return float(np.median(x)), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def summarise(metrics: pd.DataFrame, by: list[str], seed: int = 0, delta_practical: float | None = None) -> pd.DataFrame:
    """Monte Carlo table (`pipeline.sim.metrics.summarise_agents`: success/collision with Wilson CIs, outcome
    classes, clearance median/p05/min, final-distance quantiles, practical success) plus a bootstrap CI of the
    median time to target and a CI of the mean jump count."""
    table = summarise_agents(metrics, by, delta_practical=delta_practical)
    rng = np.random.default_rng(seed)
    extra = []
    for _, g in metrics.groupby(by, sort=False):
        _, t_lo, t_hi = median_ci(g.loc[g["success"].astype(bool), "time_to_target"].to_numpy(), rng)
        _, j_lo, j_hi = mean_ci(g["jumps"].to_numpy())
        extra.append({"median_time_lo": t_lo, "median_time_hi": t_hi, "mean_jumps_lo": j_lo, "mean_jumps_hi": j_hi})
    return pd.concat([table, pd.DataFrame(extra)], axis=1)
