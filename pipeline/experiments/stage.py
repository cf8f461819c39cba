"""The experiments stage: `python -m pipeline.experiments experiment=<id>` (one paper figure/table each).

The scenario is instantiated from its bundle (`experiment._target_`), with every object it uses built from the
composed config (controllers, disturbances, cloud levels, scenes, camera). Its numbers are computed once and
cached as a tracked output `outputs/experiments/<experiment>-<id>/`; the id hashes exactly what the
computation reads: the scenario's parameters (not its title), the scene(s), the controllers, disturbances and
cloud levels it uses, camera, sim and render settings, the ids of its perception and error maps, and the code
that computes (not the drawing code). Re-running with nothing changed only re-draws; changing a baseline's
parameter recomputes. Figures (PNG + PDF) and tables (CSV + Markdown + LaTeX) go to
`outputs/side/<experiment>-<id>/` with an `index.md`; only `publish=true` (what `make paper` passes) writes them
to `outputs/paper/`, in the paper's figure order (`view_dir`; `publish=auto`: the paper folder unless its lock
pins another computation of the experiment).
"""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from hydra.core.hydra_config import HydraConfig

from pipeline import tracking
from pipeline.config import resolve
from pipeline.experiments.checks import check
from pipeline.experiments.context import Context
from pipeline.experiments.redraw import drawing_key, drawn_entry
from pipeline.experiments.report import Outputs, publish
from pipeline.experiments.results import Results
from pipeline.experiments.scenario import Scenario
from pipeline.lineage import pinned_folders
from pipeline.perception.maps import load_perception_map, resolve_device
from pipeline.plants import SingleIntegrator
from pipeline.preflight import prepared
from pipeline.profiling import phase, record
from pipeline.progress import progress

# the code whose changes change the numbers (figures.py and report.py only draw)
COMPUTE_CODE = ("experiments/scenario", "experiments/paper/theory", "experiments/paper/camera_loop", "experiments/generalisation/maps",
                "experiments/multi/fields", "experiments/multi/unicycle", "experiments/context", "experiments/composed",
                "experiments/maps", "experiments/runs", "experiments/results", "experiments/attacks/camera",
                "experiments/attacks/margin", "experiments/multi/dense",
                "perception/measure", "perception/metrics", "perception/attacks", "perception/adversary", "control",
                "hybrid", "plants", "sim", "render", "data/sampling", "data/recipe")


def _command(cfg, exp_id: str) -> str:
    try:
        overrides = list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - not under @hydra.main (tests, the paper DAG)
        overrides = [f"experiment={exp_id}"]
    if not any(o.startswith("experiment=") for o in overrides):
        overrides.insert(0, f"experiment={exp_id}")
    return "python -m pipeline.experiments " + " ".join(overrides)


def view_dir(cfg, exp_id: str, folder: Path) -> tuple[Path, bool]:
    """Where a run's figures and tables go, and whether a lock sent them aside.

    `publish: false` (the default): `paths.side_dir/<experiment>-<id>/`; `true` (make paper passes it):
    `paths.paper_dir`; `auto`: the paper dir, unless a lock there (`*.lock.yaml`, written by make paper) pins
    another computation of this experiment; then the side dir, and the pinned paper's figure stays as it is."""
    publish = cfg.get("publish", False)
    paper_dir, side = Path(cfg.paths.paper_dir), Path(cfg.paths.side_dir) / folder.name
    if publish == "auto":
        pinned = pinned_folders(paper_dir, "experiments")
        aside = exp_id in pinned and pinned[exp_id] != folder.name
        return (side if aside else paper_dir), aside
    return (paper_dir if publish else side), False


def cache_key(cfg, scen: Scenario, ctx: Context) -> dict:
    """Everything the computation reads (resolved), and nothing it does not."""
    plain = {k: tracking.to_plain(cfg[k]) for k in ("experiment", "scene", "camera", "sim", "render", "controllers",
                                                    "disturbances", "occlusions", "other_scene") if k in cfg}
    used = scen.uses()
    exp = {k: v for k, v in plain["experiment"].items() if k not in scen.DRAW_ONLY}
    key = {
        "experiment": exp, "scene": plain["scene"], "camera": plain["camera"], "sim": plain["sim"],
        "render": plain["render"], "perception": ctx.perception, "scale": ctx.scale,
        "controllers": {n: plain["controllers"][n] for n in used["controllers"]},
        "disturbances": {n: plain["disturbances"][n] for n in used["disturbances"]},
        "occlusions": {n: plain["occlusions"][n] for n in used["occlusions"]},
        "maps": ctx.map_ids(scen.maps), "code": tracking.code_version(*COMPUTE_CODE),
    }
    if "other_scene" in plain:
        key["other_scene"] = plain["other_scene"]
    if not isinstance(ctx.vehicle, SingleIntegrator):  # the paper's vehicle keeps the key it always had
        key["vehicle"] = tracking.to_plain(cfg.vehicle)
    if not ctx.vehicle.heading:  # a vehicle without a heading reads no heading from the camera
        key["camera"] = {k: v for k, v in key["camera"].items() if k not in ("heading", "heading_noise")}
    errormaps = {k: (s["id"] if (s := ctx.error_map(k)) else "oracle") for k in getattr(scen, "errormaps", ())}
    if errormaps:
        key["errormaps"] = errormaps
    return key


def check_reads(scen: Scenario, ctx: Context) -> None:
    """The composed nodes the computation read (`ctx.read`: controllers, disturbances, cloud levels) must all be in
    its cache key (`scen.uses()`): a node read and not keyed would let a changed node reuse a stale result."""
    used = scen.uses()
    missing = sorted(f"{g}.{n}" for g, n in getattr(ctx, "read", ()) if n not in used.get(g, ()))
    if missing:
        raise RuntimeError(f"experiment {scen.id!r} read {', '.join(missing)}, which its uses() does not list: its "
                           "cache key would not change with them (add them to the scenario's uses())")


def run(cfg) -> dict:
    t0 = time.perf_counter()
    scen, ctx = prepared(cfg, check)  # the preflight's, when it checked this job
    resolve_device(cfg.get("device", "auto"))  # `device=cuda` without a GPU: one line, before any work
    ctx.load_map_with(load_perception_map)
    key_parts = cache_key(cfg, scen, ctx)
    cid = tracking.content_id(key_parts)
    root = Path(cfg.paths.outputs_dir) / "experiments"
    folder = root / f"{scen.id}-{cid}"
    cached = tracking.exists(folder, "experiment result") and not cfg.get("force", False)
    if cached:
        tracking.check_intact(folder, "experiment result", f"{_command(cfg, scen.id)} force=true")
        res = Results.load(folder)
        print(f"[experiments] {scen.id}: re-using cached results {folder}")
    else:
        print(f"[experiments] {scen.id}: computing {folder.name} ...", flush=True)
        with progress(desc=f"[experiments] {scen.id}", unit="runs") as ctx.bar, phase("compute"):
            res = scen.compute(ctx)  # one bar step per simulation
        ctx.bar = None
        check_reads(scen, ctx)  # before the result is stored under a key that may miss what it read
        with tracking.tracked_output(root, scen.id, cid, {"kind": "experiment", "code_version": key_parts["code"],
                                                          **key_parts}) as tmp:
            res.save(tmp)
    paper_dir, aside = view_dir(cfg, scen.id, folder)
    if aside:
        print(f"[experiments] {scen.id}: the lock in {cfg.paths.paper_dir} pins another computation of {scen.id}; this "
              f"run ({folder.name}) writes to {paper_dir} and leaves the paper's figures as pinned (publish=true: "
              "write there anyway)")
    drawn = drawing_key(cfg, folder)
    if (entry := drawn_entry(paper_dir, scen.id, drawn)) is not None:
        files = [paper_dir / f for it in entry["items"] for f in it["files"]]
        print(f"[experiments] {scen.id}: its {len(files)} files in {paper_dir} are up to date (drawn from "
              f"{folder.name}; nothing redrawn)")
        record(f"experiments {scen.id}", cached=cached, drawn=False)
        return {"id": scen.id, "cache": folder, "cached": cached, "results": res, "files": files}
    out = Outputs(paper_dir, scen.id)
    with phase("draw"):
        resolve(scen.figures)(scen, ctx, res, out)
    # the raw per-agent metrics of the scenario, next to its figures
    if "metrics" in res.tables:
        res.tables["metrics"].to_csv(paper_dir / f"metrics_{scen.id}.csv", index=False)
        out.items.append({"kind": "metrics", "files": [f"metrics_{scen.id}.csv"],
                          "caption": "raw per-agent metrics (one row per simulated vehicle)"})
    entry = {"id": scen.id, "title": scen.title, "paper": scen.paper, "command": _command(cfg, scen.id),
             "inputs": dict(ctx.used), "cache": os.path.relpath(folder, paper_dir), "items": out.items, "drawn": drawn}
    index = publish(paper_dir, entry)
    files = [f for it in out.items for f in it["files"]]
    record(f"experiments {scen.id}", cached=cached, drawn=True)
    print(f"[experiments] {scen.id}: {len(files)} files in {paper_dir} ({time.perf_counter() - t0:.0f} s); "
          f"index {index}", file=sys.stdout)
    return {"id": scen.id, "cache": folder, "cached": cached, "results": res, "files": [paper_dir / f for f in files]}
