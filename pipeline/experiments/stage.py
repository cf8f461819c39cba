"""The experiments stage: `python -m pipeline.experiments experiment=<id>` (one paper figure/table each).

Each scenario's numbers are computed once and cached as a tracked output
`outputs/experiments/<experiment>-<id>/` (id = hash of the experiment, scene, controller, camera, sim and render
configs, the perception-map ids and the code version); re-running with nothing changed only re-draws.
Figures (PNG + PDF) and tables (CSV + Markdown + LaTeX) go to `outputs/paper/`, with an `index.md`.
"""

from __future__ import annotations

import json
import sys
import time
from pathlib import Path

from pipeline import tracking
from pipeline.errors import ConfigError
from pipeline.experiments.common import Context, Outputs, Results, write_index
from pipeline.experiments.scenarios import REGISTRY

CODE = ("experiments", "control", "sim", "render")


def _command(cfg, exp_id: str) -> str:
    try:
        from hydra.core.hydra_config import HydraConfig

        overrides = list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - not under @hydra.main (tests, the paper DAG)
        overrides = [f"experiment={exp_id}"]
    if not any(o.startswith("experiment=") for o in overrides):
        overrides.insert(0, f"experiment={exp_id}")
    return "python -m pipeline.experiments " + " ".join(overrides)


def run(cfg) -> dict:
    t0 = time.perf_counter()
    exp = tracking.to_plain(cfg.get("experiment")) or {}
    exp_id = exp.get("id")
    if exp_id not in REGISTRY:
        raise ConfigError("experiment", f"unknown experiment {exp_id!r}; known: {', '.join(sorted(REGISTRY))}")
    scen = REGISTRY[exp_id]()
    ctx = Context(cfg)
    key_parts = {
        "experiment": exp, "scene": ctx.scene_cfg, "controller": tracking.to_plain(cfg.controller),
        "camera": tracking.to_plain(cfg.camera), "sim": tracking.to_plain(cfg.sim),
        "render": tracking.to_plain(cfg.render), "perception": ctx.perception, "scale": ctx.scale,
        "maps": ctx.map_ids(scen.maps), "code": tracking.code_version(*CODE),
    }
    if exp_id == "perception_closeness":
        key_parts["errormap"] = ctx.eps_perception("clean", "none")[1]
    cid = tracking.content_id(key_parts)
    root = Path(cfg.paths.outputs_dir) / "experiments"
    folder = root / f"{exp_id}-{cid}"
    cached = tracking.is_complete(folder) and not cfg.get("force", False)
    if cached:
        res = Results.load(folder)
        print(f"[experiments] {exp_id}: re-using cached results {folder}")
    else:
        res = scen.compute(ctx)
        with tracking.tracked_output(root, exp_id, cid, {"kind": "experiment", **key_parts}) as tmp:
            res.save(tmp)
    paper_dir = Path(cfg.paths.paper_dir)
    out = Outputs(paper_dir, exp_id)
    scen.draw(ctx, res, out)
    # the raw per-agent metrics of the scenario, next to its figures
    if "metrics" in res.tables:
        res.tables["metrics"].to_csv(paper_dir / f"metrics_{exp_id}.csv", index=False)
        out.items.append({"kind": "metrics", "files": [f"metrics_{exp_id}.csv"],
                          "caption": "raw per-agent metrics (one row per simulated vehicle)"})
    entry = {"id": exp_id, "title": exp.get("title", exp_id), "paper": exp.get("paper", "–"),
             "command": _command(cfg, exp_id), "inputs": dict(ctx.used), "cache": str(folder),
             "items": out.items}
    (paper_dir / "index").mkdir(parents=True, exist_ok=True)
    (paper_dir / "index" / f"{exp_id}.json").write_text(json.dumps(entry, indent=2) + "\n")
    index = write_index(paper_dir)
    files = [f for it in out.items for f in it["files"]]
    print(f"[experiments] {exp_id}: {len(files)} files in {paper_dir} ({time.perf_counter() - t0:.0f} s); "
          f"index {index}", file=sys.stdout)
    return {"id": exp_id, "cache": folder, "cached": cached, "results": res, "files": [paper_dir / f for f in files]}
