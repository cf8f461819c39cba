"""A multirun that summarises itself: a Hydra callback (conf/hydra/default.yaml, `callbacks.summary`).

- `on_job_end` writes `summary.json` into the job's folder: its number, overrides, status and headline metrics.
  Each stage names its headline function in its own config (`hydra.callbacks.summary.headline`,
  `"module:function"`, `function(result) -> {metric: value}`): data its id and split sizes, train the map's
  validation and test MAE, errormap the p95 error per cloud level, experiments the success rates of the
  scenario's summary table.
- `on_multirun_end` reads every job's `summary.json` into one table, one row per job (overrides, then metrics),
  written beside the jobs' folders as `summary.csv` and `summary.md`, and printed.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import numpy as np
from hydra.experimental.callback import Callback
from omegaconf import DictConfig

from pipeline.config import resolve

SUMMARY = "summary.json"


def _plain(value):
    """A JSON-able scalar (numpy numbers, paths); floats rounded for the table."""
    if hasattr(value, "item") and callable(value.item):
        value = value.item()
    if isinstance(value, float):
        return round(value, 4) if math.isfinite(value) else None
    if isinstance(value, bool | int | str) or value is None:
        return value
    return str(value)


def headline_of(ref: str | None, result) -> dict[str, Any]:
    """The headline metrics of a job's result: `ref` ("module:function") applied to it; a number (what a job
    returns to an Optuna sweeper) is `{"objective": value}`."""
    if isinstance(result, int | float) and not isinstance(result, bool):
        return {"objective": _plain(float(result))}
    if ref is None or result is None:
        return {}
    return {str(k): _plain(v) for k, v in (resolve(ref)(result) or {}).items()}


class SweepSummary(Callback):
    """`headline`: the stage's `"module:function"` (set by each stage's config)."""

    def __init__(self, headline: str | None = None):
        self.headline = headline

    def on_job_end(self, config: DictConfig, job_return, **kwargs: Any) -> None:
        from hydra.core.utils import JobStatus

        hydra = config.hydra
        entry = {"job": int(hydra.job.get("num", 0) or 0), "overrides": list(job_return.overrides or []),
                 "status": "ok" if job_return.status == JobStatus.COMPLETED else "failed", "metrics": {}}
        if job_return.status == JobStatus.COMPLETED:
            try:
                entry["metrics"] = headline_of(self.headline, job_return.return_value)
            except Exception as err:  # noqa: BLE001 - a summary never fails a finished job
                entry["metrics"] = {"headline_error": f"{type(err).__name__}: {err}"}
        else:
            entry["error"] = str(job_return._return_value).splitlines()[0] if job_return._return_value else ""
        out = Path(hydra.runtime.output_dir)
        out.mkdir(parents=True, exist_ok=True)
        (out / SUMMARY).write_text(json.dumps(entry, indent=2) + "\n")

    def on_multirun_end(self, config: DictConfig, **kwargs: Any) -> None:
        sweep_dir = Path(config.hydra.sweep.dir)
        table = summary_table(sweep_dir)
        if table is None:
            return
        table.to_csv(sweep_dir / "summary.csv", index=False)
        text = markdown(table)
        (sweep_dir / "summary.md").write_text(text)
        print(f"\n[sweep] {len(table)} jobs -> {sweep_dir / 'summary.csv'}\n{text}", flush=True)


def summary_table(sweep_dir: Path):
    """One row per job of a sweep folder (`*/summary.json`, in job order): job, overrides, status, metrics."""
    import pandas as pd

    entries = sorted((json.loads(p.read_text()) for p in Path(sweep_dir).glob(f"*/{SUMMARY}")),
                     key=lambda e: e["job"])
    if not entries:
        return None
    rows = [{"job": e["job"], "overrides": " ".join(e["overrides"]), "status": e["status"], **e["metrics"]}
            for e in entries]
    return pd.DataFrame(rows)


def markdown(df) -> str:
    cols = list(df.columns)
    cell = lambda v: "–" if v is None or (isinstance(v, float) and not math.isfinite(v)) else str(v)  # noqa: E731
    lines = ["| " + " | ".join(cols) + " |", "|" + "|".join("---" for _ in cols) + "|"]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join(lines) + "\n"


# ------------------------------------------------------------------------------- the stages' headlines
# Each stage's config names its function (`hydra.callbacks.summary.headline`); they live here, not in the stages'
# packages, so that what a table shows never changes an output's id (the code of a stage is part of its ids).
def data_headline(out: dict) -> dict:
    """data: the dataset's name-id, its split sizes, and whether an up-to-date one was re-used."""
    return {"dataset": f"{out['name']}-{out['id']}", **{f"n_{s}": n for s, n in out["counts"].items()},
            "reused": bool(out.get("skipped"))}


def train_headline(out: dict) -> dict:
    """train: the map's name-id, its best validation MAE, its test-split MAE and the MAE at each evaluation
    level (px)."""
    m = out.get("metrics") or {}
    row = {"map": f"{out['name']}-{out['id']}", "val_mae_px": m.get("val_mae_px"),
           "test_mae_px": (m.get("test_split") or {}).get("mae_px")}
    row.update({f"mae_px[{k}]": v["mae_px"] for k, v in m.items()
                if isinstance(v, dict) and "mae_px" in v and k != "test_split"})
    return row


def errormap_headline(out: dict) -> dict:
    """errormap: the p95 of the error over the operational set at each cloud level (world units), per map."""
    results = out["maps"] if "maps" in out else [out]
    row = {}
    for r in results:
        s = r["summary"]
        prefix = f"{s['name']} " if len(results) > 1 else ""
        row[f"{prefix}errormap"] = Path(str(r["path"])).name
        row.update({f"{prefix}p95[{lv}]": v.get("p95") for lv, v in s["levels"].items()})
    return row


def experiments_headline(out: dict) -> dict:
    """experiments: the success rates of the scenario's summary table (`summary`, else the first table with a
    `success_rate` column; per controller where it has one), else the share of successful agents."""
    tables = out["results"].tables
    order = [n for n in ("summary", "sweep") if n in tables] + [n for n in tables if n not in ("summary", "sweep")]
    row: dict = {"experiment": out["id"], "cached": bool(out.get("cached"))}
    for name in order:
        df = tables[name]
        if "success_rate" in df.columns:
            if "controller" in df.columns:
                rates = df.groupby("controller", sort=False)["success_rate"].mean()
                row.update({f"success[{c}]": float(v) for c, v in rates.items()})
            else:
                row["success_rate"] = float(df["success_rate"].mean())
            return row
    if "metrics" in tables and "success" in tables["metrics"].columns:
        row["success_rate"] = float(tables["metrics"]["success"].mean())
    return row


def simulate_headline(out: dict) -> dict:
    """simulate: the share of agents that reached the target, collided, and the median time to target."""
    m = out["metrics"]
    return {"agents": len(m), "success_rate": float(m["success"].mean()), "collision_rate": float(m["collision"].mean()),
            "median_time_to_target": _median(m["time_to_target"])}


def _median(x) -> float:
    """The median of the finite values, NaN (without numpy's 'Mean of empty slice' warning) when there are none."""
    v = np.asarray(x, dtype=float)
    v = v[np.isfinite(v)]
    return float(np.median(v)) if v.size else float("nan")
