"""Writing an ε-error map's folder: the CSV tables, `fields.npz`, the figures and `summary.json`
(docs/errormap.md lists the files and the summary's keys)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline.control import Scene
from pipeline.errormap.analysis import jsonable
from pipeline.errormap.figures import figures
from pipeline.errormap.settings import ErrorMapSettings


def write_outputs(folder: Path, summary: dict, fields: dict, results: dict, scene: Scene, arena,
                  settings: ErrorMapSettings, samples: np.ndarray, sample_err_vec: np.ndarray) -> None:
    """CSV tables, summary.json, fields.npz and the figures (docs/errormap.md)."""
    levels = list(results)
    rows = []
    for lv, r in results.items():
        for region, st in (("operational", {k: r[k] for k in ("n", "mean", "median", "p95", "max", "rms")}),
                           ("arena", r["arena"])):
            rows.append({"level": lv, "region": region, **st})
    pd.DataFrame(rows).to_csv(folder / "stats.csv", index=False)
    pd.DataFrame([{"level": lv, "region": reg, "L_max": r[f"L{suf}max"], "L_p99": r[f"L{suf}p99"]}
                  for lv, r in results.items()
                  for reg, suf in (("operational", "_"), ("arena", "_arena_"))]).to_csv(
        folder / "lipschitz.csv", index=False)
    pd.DataFrame([{"level": lv, "eps": e, "coverage": f, "L": r["L"]}
                  for lv, r in results.items()
                  for e, f in zip(r["coverage"]["eps"], r["coverage"]["fraction"])]).to_csv(
        folder / "coverage.csv", index=False)
    dean_rows = []
    dean_sets = {lv: r["dean"] for lv, r in results.items()}
    dean_sets["train"] = summary["train_samples"]["dean"]
    for lv, d in dean_sets.items():
        dean_rows += [{"data": lv, "kind": "front", "eps_C": c, "eps_eta": e} for c, e in (d["front"] or [])]
        dean_rows += [{"data": lv, "kind": "at", "eps_C": c, "eps_eta": e} for c, e in (d["at"] or [])]
    pd.DataFrame(dean_rows, columns=["data", "kind", "eps_C", "eps_eta"]).to_csv(folder / "dean_fit.csv", index=False)
    pd.DataFrame([{"level": lv, **{k: r["error_vs_distance"][k][b] for k in
                                   ("lo", "hi", "count", "mean", "median", "p95", "max")}}
                  for lv, r in results.items() for b in range(len(r["error_vs_distance"]["lo"]))]).to_csv(
        folder / "error_vs_distance.csv", index=False)
    heading = [{"level": lv, "region": region, **{k: st[k] for k in ("n", "mean_deg", "median_deg", "p95_deg",
                                                                   "max_deg")}}
               for lv, r in results.items() if "heading" in r
               for region, st in (("operational", r["heading"]), ("arena", r["heading"]["arena"]),
                                  ("near_target", r["heading"]["near_target"]))]
    if heading:  # a pose map: the heading error beside the position error
        pd.DataFrame(heading).to_csv(folder / "heading.csv", index=False)
    np.savez_compressed(folder / "fields.npz", samples=samples.astype(np.float32),
                        sample_err=sample_err_vec.astype(np.float32), **fields)
    figs = figures(folder, fields, results, scene, arena, settings, levels)
    summary["files"] = sorted(p.name for p in folder.iterdir()) + ["summary.json"]
    summary["figures"] = figs
    (folder / "summary.json").write_text(json.dumps(jsonable(summary), indent=2) + "\n")
