"""`make paper`: the DAG data -> train -> errormap -> experiments, each stage as its own Hydra job.

Inputs are pinned by id from stage to stage: the paper job computes the id each stage's config produces
(with the `args` overrides), passes `maps.clean=clean-<id>` etc. to the next stage, and writes
`outputs/paper/paper.lock.yaml` listing every dataset, map, error map and experiment result with its config
hash and code version, and the run's debug level. Stages skip work whose tracked output is up to date (checked
against its manifest first), and figures whose inputs did not change are not redrawn, so a second `make paper`
with nothing changed only starts the stages; another folder of the same name made on the side changes nothing.
A smoke run (`debug=tiny`) writes its figures, index and lock to `outputs/debug/paper/` (conf/debug/tiny.yaml).
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import REPO_ROOT, stage_main
from pipeline.config import compose, settings
from pipeline.errors import ConfigError, PipelineError
from pipeline.experiments.report import write_index
from pipeline.lineage import (
    dataset_identity,
    debug_overrides,
    expected_errormap_id,
    map_identity,
    map_recipe,
    write_lock,
)
from pipeline.schema import NonEmpty, Option, Pattern


@dataclass(frozen=True)
class StageArgs:
    """Extra Hydra overrides of each stage's jobs."""

    data: list[str] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    errormap: list[str] = field(default_factory=list)
    experiments: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class PaperSettings:
    """The root keys of conf/paper.yaml (documented there); the cross-field rules in :func:`check`."""

    datasets: Annotated[list[Annotated[str, Option("data")]], NonEmpty()]
    maps: list[str]
    errormaps: list[str]
    experiments: list[Annotated[str, Option("experiment")]]
    args: StageArgs
    stop_on_error: bool
    lock: Annotated[str, Pattern(r"[^/]+\.yaml", "a file name ending in .yaml")]


def path_overrides() -> list[str]:
    """`paths.*` overrides given to the paper (or dagger) job are passed on to every stage."""
    try:
        return [o for o in HydraConfig.get().overrides.task if o.lstrip("+").startswith("paths.")]
    except Exception:  # noqa: BLE001 - not under @hydra.main
        return []


def _args(cfg) -> dict[str, list[str]]:
    return {k: list(v) for k, v in asdict(StageArgs(**(tracking.to_plain(cfg.args) or {}))).items()}


def check(cfg: DictConfig) -> None:
    s = settings(cfg, PaperSettings)
    datasets, maps = s.datasets, s.maps
    for name in maps:
        if map_recipe(name) is None:
            raise ConfigError("maps", f"unknown map {name!r}: a recipe of conf/data/, or <recipe>_<model> with a "
                                      "model of conf/model/ (e.g. clean_paper)")
    missing = {name for name in maps if map_recipe(name)[0] not in datasets}
    if missing:
        raise ConfigError("maps", f"{sorted(missing)} are trained on datasets not among {datasets}")
    if set(s.errormaps) - set(maps):
        raise ConfigError("errormaps", f"{sorted(set(s.errormaps) - set(maps))} are not among the maps {maps}")


def experiment_pins(experiments_cfg, map_refs: dict[str, str], em_refs: dict[str, str]) -> list[str]:
    """The experiments read maps by kind (`maps.<kind>: <map name>`, conf/experiments.yaml, e.g. `field_heavy:
    field_heavy_keypoint`): pin every kind whose map this run built (`map_refs`: map name -> `name-id`), and its
    error map (`em_refs`, by map name) where the experiments read one."""
    kinds = {str(kind): str(ref) for kind, ref in experiments_cfg.maps.items()}
    pins = [f"maps.{k}={map_refs[n]}" for k, n in kinds.items() if n in map_refs]
    return pins + [f"errormaps.{k}={em_refs[n]}" for k, n in kinds.items()
                   if n in em_refs and k in experiments_cfg.errormaps]


def run_stage(stage: str, argv: list[str], timings: dict, stop: bool, *, tag: str = "paper",
              label: str | None = None) -> bool:
    """Run `python -m pipeline.<stage> <argv>` as its own Hydra job; its time goes to `timings[label or stage]`.
    A failure raises (`stop`) or prints one line; `tag` names the orchestrator (`[paper]`, `make paper`)."""
    cmd = [sys.executable, "-m", f"pipeline.{stage}", *argv]
    print(f"\n[{tag}] === {label or stage}: {' '.join(cmd[1:])}", flush=True)
    ts = time.perf_counter()
    try:
        proc = subprocess.run(cmd, cwd=REPO_ROOT, check=False)
    except KeyboardInterrupt:  # Ctrl-C reached the stage too, which said so in its one line: say nothing more
        raise SystemExit(130) from None
    key = label or stage
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - ts
    if proc.returncode != 0:
        msg = f"stage {stage} failed (exit {proc.returncode}); fix it and re-run `make {tag}` (done stages are re-used)"
        if stop:
            raise PipelineError(msg)
        print(f"[{tag}] {msg}", flush=True)
        return False
    return True


def run(cfg) -> dict:
    check(cfg)
    t0 = time.perf_counter()
    # paths.* and debug=<level> go to every stage and to every config whose ids are computed here
    args, paths = _args(cfg), [*path_overrides(), *debug_overrides(cfg)]
    stop = bool(cfg.get("stop_on_error", True))
    timings: dict[str, float] = {}
    datasets, maps, errormaps, experiments = list(cfg.datasets), list(cfg.maps), list(cfg.errormaps), list(cfg.experiments)
    lock: dict[str, dict[str, Path]] = {"datasets": {}, "maps": {}, "errormaps": {}, "experiments": {}}
    ds_root, models_root = Path(cfg.paths.datasets_dir), Path(cfg.paths.models_dir)
    debug = debug_overrides(cfg)
    if debug:
        print(f"[paper] {debug[0]}: a smoke run at tiny sizes; its figures, tables and lock go to "
              f"{cfg.paths.paper_dir} (the paper's folder is left as it is)", flush=True)

    run_stage("data", ["-m", f"data={','.join(datasets)}", *paths, *args["data"]], timings, stop)
    for name in datasets:
        _, ds_id, _ = dataset_identity(compose("data", [f"data={name}", *paths, *args["data"]]))
        lock["datasets"][name] = ds_root / f"{name}-{ds_id}"
    map_refs = {}
    groups: dict[tuple[str, ...], list[str]] = {}  # maps of the same model overrides: one multirun each
    for name in maps:
        recipe, extra = map_recipe(name)
        groups.setdefault(tuple(extra), []).append(recipe)
    for extra, recipes in groups.items():
        run_stage("train", ["-m", f"data={','.join(recipes)}", *extra, *paths, *args["train"]], timings, stop)
    if maps:
        for name in maps:
            recipe, extra = map_recipe(name)
            mname, mid = map_identity(compose("train", [f"data={recipe}", *extra, *paths, *args["train"]]))
            map_refs[name] = f"{mname}-{mid}"
            lock["maps"][name] = models_root / map_refs[name]
    em_refs = {}
    if errormaps:
        run_stage("errormap", [f"maps=[{','.join(map_refs[m] for m in errormaps)}]", *paths, *args["errormap"]],
               timings, stop)
        for name in errormaps:
            ename, eid = expected_errormap_id(models_root / map_refs[name], [*paths, *args["errormap"]])
            em_refs[name] = f"{ename}-{eid}"
            lock["errormaps"][name] = Path(cfg.paths.errormaps_dir) / em_refs[name]
    if experiments:
        pins = experiment_pins(compose("experiments", paths), map_refs, em_refs)
        if not any(p.startswith("paths.paper_dir=") for p in paths):  # the folder this job indexes and locks
            pins.append(f"paths.paper_dir={cfg.paths.paper_dir}")
        run_stage("experiments", ["-m", f"experiment={','.join(experiments)}", *pins, *paths, "publish=true",
                                  *args["experiments"]],
               timings, stop)
        paper_dir = Path(cfg.paths.paper_dir)
        for exp in experiments:
            entry = paper_dir / "index" / f"{exp}.json"
            if entry.is_file():
                lock["experiments"][exp] = (paper_dir / json.loads(entry.read_text())["cache"]).resolve()
    lock = {k: {n: f for n, f in v.items() if tracking.is_complete(f)} for k, v in lock.items()}
    lock_path = write_lock(Path(cfg.paths.paper_dir) / cfg.lock, lock, debug=cfg.get("debug") or "none")
    if (Path(cfg.paths.paper_dir) / "index").is_dir():
        write_index(Path(cfg.paths.paper_dir))
    total = time.perf_counter() - t0
    line = ", ".join(f"{k} {v:.0f} s" for k, v in timings.items())
    print(f"\n[paper] done in {total / 60:.1f} min ({line}); see {cfg.paths.paper_dir}/index.md; inputs pinned in "
          f"{lock_path}")
    return {"timings": timings, "total": total, "lock": lock_path, "maps": map_refs, "errormaps": em_refs}


main = stage_main("paper", run="pipeline.paper:run", check="pipeline.paper:check")

if __name__ == "__main__":
    sys.exit(main())
