"""Reading an ε-error map back (the experiments stage quotes its ε, by id)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from pathlib import Path

import pandas as pd

from pipeline import tracking
from pipeline.errors import DatasetError
from pipeline.lineage import resolve_errormap
from pipeline.repo import REPO_ROOT


def default_errormaps_dir() -> Path:
    return REPO_ROOT / "outputs" / "errormaps"


def load_error_map(ref, errormaps_dir=None) -> dict:
    """A finished error map by id, `name-id`, path, or a model name that one error map alone has: its
    summary.json plus `"path"` (Path) and `"paths"` (`{file name: Path}`). Unknown or incomplete -> DatasetError."""
    root = Path(errormaps_dir) if errormaps_dir is not None else default_errormaps_dir()
    folder = resolve_errormap(ref, root)
    problems = tracking.verify(folder, full=False)
    if problems:
        raise DatasetError(f"error map {folder}: " + "; ".join(problems[:3]))
    summary = json.loads((folder / "summary.json").read_text())
    summary["path"] = folder
    summary["paths"] = {p.name: p for p in sorted(folder.iterdir()) if p.is_file()}
    return summary


def summary_table(refs, errormaps_dir=None) -> pd.DataFrame:
    """One row per (error map, occlusion level): the headline numbers the experiments stage quotes."""
    rows = []
    for ref in refs:
        s = ref if isinstance(ref, Mapping) else load_error_map(ref, errormaps_dir)  # a summary or a reference
        for lv, r in s["levels"].items():
            rows.append({
                "model": s["model"]["name"], "model_id": s["model"]["id"], "occlusion": lv,
                "mean": r["mean"], "p95": r["p95"], "max": r["max"],
                "near_target_mean": r.get("near_target", {}).get("mean"),
                "near_target_p95": r.get("near_target", {}).get("p95"), "L": r["L"], "L_p99": r["L_p99"],
                "eps_cover": r["eps_cover"], "eps_cover_95": r["eps_cover_95"], "bound_holds": r["bound_holds"],
                "dean_eps_eta_at_0": r["dean"]["eps_eta_at_0"], "dean_eps_C_at_0": r["dean"]["eps_C_at_0"],
                **({"heading_mean_deg": r["heading"]["mean_deg"], "heading_p95_deg": r["heading"]["p95_deg"]}
                   if "heading" in r else {}),  # a pose map's heading error
                "errormap": s["id"],
            })
    return pd.DataFrame(rows)
