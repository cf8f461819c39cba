"""`make paper`: the DAG data -> train -> errormap -> experiments, each stage as its own Hydra job.

Inputs are pinned by id from stage to stage: the paper job computes the id each stage's config produces (with the
`args` overrides), passes `maps.clean=clean-<id>` etc. to the next stage, and writes
`outputs/paper/paper.lock.yaml` listing every dataset, map, error map and experiment result with its config hash
and code version, and the run's debug level. The data come first; every later job (maps, error maps, certify,
experiments, brackets, learned policies) runs in one pool, each started once the jobs making the folders its
command line names are done (the ids are known before anything is trained: `expected_map_manifest`). Stages skip
work whose tracked output is up to date (checked against its manifest first), and figures whose inputs did not
change are not redrawn, so a second `make paper` with nothing changed only starts the stages; another folder of the
same name made on the side changes nothing.
A smoke run (`debug=tiny`) writes its figures, index and lock to `outputs/debug/paper/` (conf/debug/tiny.yaml).
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated

from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from pipeline import paper_stages, tracking
from pipeline.cli import CONF_DIR, stage_main
from pipeline.config import compose, settings
from pipeline.errors import ConfigError, PipelineError
from pipeline.experiments import checks as experiment_checks  # not `inputs_read` here: stage_main reads it
from pipeline.experiments.report import write_index
from pipeline.jobs import Job, run_jobs
from pipeline.lineage import (
    dataset_identity,
    debug_overrides,
    expected_errormap_id,
    expected_map_manifest,
    map_recipe,
    write_lock,
)
from pipeline.paper_profile import Runner
from pipeline.paper_stages import up_to_date
from pipeline.schema import NonEmpty, Option, Pattern, PositiveInt, checked


@dataclass(frozen=True)
class StageArgs:
    """Extra Hydra overrides of each stage's jobs."""

    data: list[str] = field(default_factory=list)
    train: list[str] = field(default_factory=list)
    errormap: list[str] = field(default_factory=list)
    certify: list[str] = field(default_factory=list)
    bracket: list[str] = field(default_factory=list)
    experiments: list[str] = field(default_factory=list)
    imitate: list[str] = field(default_factory=list)
    ppo: list[str] = field(default_factory=list)
    learned: list[str] = field(default_factory=list)


@checked("")
@dataclass(frozen=True)
class PaperSettings:
    """The root keys of conf/paper.yaml (documented there); the cross-field rules in :func:`check`."""

    datasets: Annotated[list[Annotated[str, Option("data")]], NonEmpty()]
    maps: list[str]
    errormaps: list[str]
    certify: list[str]
    bracket: list[Annotated[str, Option("tuning")]]
    bracket_map: str | None
    experiments: list[Annotated[str, Option("experiment")]]
    learned: list[Annotated[str, Pattern(r"imitate(_\w+)?|ppo", "the name of an imitation config (imitate, "
                                                                  "imitate_<x>) or ppo")]]
    args: StageArgs
    stop_on_error: bool
    workers: PositiveInt | None
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
    for key in ("errormaps", "certify"):
        if set(getattr(s, key)) - set(maps):
            raise ConfigError(key, f"{sorted(set(getattr(s, key)) - set(maps))} are not among the maps {maps}")
    if s.bracket_map is not None and s.bracket_map not in s.certify:
        raise ConfigError("bracket_map", f"{s.bracket_map!r} is not among the certified maps {s.certify} (certify)")
    missing = [c for c in s.learned if c != "ppo" and not (CONF_DIR / f"{c}.yaml").is_file()]
    if missing:
        raise ConfigError("learned", f"no imitation config conf/{missing[0]}.yaml")


def experiment_pins(experiments_cfg, map_refs: dict[str, str], em_refs: dict[str, str]) -> list[str]:
    """The experiments read maps by kind (`maps.<kind>: <map name>`, conf/experiments.yaml, e.g. `field_heavy:
    field_heavy_keypoint`): pin every kind whose map this run built (`map_refs`: map name -> `name-id`), and its
    error map (`em_refs`, by map name) where the experiments read one."""
    kinds = {str(kind): str(ref) for kind, ref in experiments_cfg.maps.items()}
    pins = [f"maps.{k}={map_refs[n]}" for k, n in kinds.items() if n in map_refs]
    return pins + [f"errormaps.{k}={em_refs[n]}" for k, n in kinds.items()
                   if n in em_refs and k in experiments_cfg.errormaps]


def experiment_jobs(experiments: list[str], pins: list[str], paths: list[str], rest: list[str]) -> list[Job]:
    """One experiments job per experiment, with the pins of the inputs it reads only (the stage rejects an
    override that its experiment never reads: :func:`pipeline.experiments.checks.inputs_read`)."""
    jobs = []
    for exp in experiments:
        try:
            read = experiment_checks.inputs_read(compose("experiments", [f"experiment={exp}", *paths, *rest], check=False))[1]
        except PipelineError:  # the job says what is wrong
            read = {}
        kept = [p for p in pins if (k := p.split("=", 1)[0].split("."))[0] not in read or k[1] in read[k[0]]]
        jobs.append(Job("experiments", [f"experiment={exp}", *kept, *paths, *rest], f"experiments {exp}"))
    return jobs


def run_stage(stage: str, argv: list[str], timings: dict, stop: bool, *, tag: str = "paper",
              label: str | None = None) -> bool:
    """Run `python -m pipeline.<stage> <argv>` alone, its output on the terminal (`make dagger`'s rounds); its time
    goes to `timings[label or stage]`. A failure raises (`stop`) or prints one line (:func:`pipeline.jobs.run_jobs`)."""
    key = label or stage
    ts = time.perf_counter()
    done = run_jobs([Job(stage, argv, key)], workers=1, tag=tag, stop=stop)
    timings[key] = timings.get(key, 0.0) + time.perf_counter() - ts
    return all(d.rc == 0 for d in done)


def experiments_stamp(argv: list[str], lock: dict) -> str:
    """What the experiments stage's outputs follow from: its command line (inputs pinned by id), the inputs' ids
    (datasets, maps, error maps: the experiments read nothing else of the lock), every module of the package and
    every config file."""
    conf = sorted(p for p in CONF_DIR.rglob("*.yaml"))
    read = ("datasets", "maps", "errormaps")
    return tracking.content_id(argv, {k: {n: f.name for n, f in v.items()} for k, v in lock.items() if k in read},
                               tracking.code_version(*(p.name for p in Path(tracking.__file__).parent.iterdir()
                                                       if p.suffix == ".py" or (p / "__init__.py").is_file())),
                               [(str(p.relative_to(CONF_DIR)), p.read_text()) for p in conf])


def experiments_up_to_date(stamp: Path, argv: list[str], experiments: list[str], lock: dict,
                           said: set | None = None) -> bool:
    """The experiments stage started with the same stamp before and every figure, table and cached result it
    indexed is still there (results checked against their manifests): nothing to compute or draw."""
    try:
        if json.loads(stamp.read_text()).get("stamp") != experiments_stamp(argv, lock):
            return False
        paper_dir = stamp.parent
        for exp in experiments:
            entry = json.loads((paper_dir / "index" / f"{exp}.json").read_text())
            files = [paper_dir / f for it in entry["items"] for f in it["files"]]
            if not all(f.is_file() for f in files) or tracking.verify(paper_dir / entry["cache"], full=None):
                return False
    except (OSError, ValueError, KeyError, PipelineError):
        return False
    if said is None or "experiments" not in said:
        print(f"\n[paper] === experiments: up to date ({len(experiments)} results, figures and tables in {paper_dir}); "
              "not started", flush=True)
    if said is not None:
        said.add("experiments")
    return True


def run(cfg) -> dict:
    check(cfg)
    t0 = time.perf_counter()
    # paths.* and debug=<level> go to every stage and to every config whose ids are computed here
    args, paths = _args(cfg), [*path_overrides(), *debug_overrides(cfg)]
    stop = bool(cfg.get("stop_on_error", True))
    timings: dict[str, float] = {}
    datasets, maps, errormaps = list(cfg.datasets), list(cfg.maps), list(cfg.errormaps)
    ds_root, models_root = Path(cfg.paths.datasets_dir), Path(cfg.paths.models_dir)
    if debug_overrides(cfg):
        print(f"[paper] {debug_overrides(cfg)[0]}: a smoke run at tiny sizes; its figures, tables and lock go to "
              f"{cfg.paths.paper_dir} (the paper's folder is left as it is)", flush=True)

    def dataset_folders():
        return {n: ds_root / f"{n}-{dataset_identity(compose('data', [f'data={n}', *paths, *args['data']]))[1]}"
                for n in datasets}

    lock: dict[str, dict[str, Path]] = {"datasets": {}, "maps": {}, "errormaps": {}, "certified": {}, "bracket": {},
                                        "experiments": {}, "learned": {}}
    runner = Runner(cfg, timings, stop)
    if datasets:  # every later job reads a dataset: alone first (one job, seconds)
        found = up_to_date("data", dataset_folders)
        if found is None:
            runner.stage("data", [Job("data", ["-m", f"data={','.join(datasets)}", *paths, *args["data"]], "data")])
        lock["datasets"] = found or dataset_folders()
    train_argv = {n: [f"data={map_recipe(n)[0]}", *map_recipe(n)[1], *paths, *args["train"]] for n in maps}
    # the ids of the maps and of what reads them, before any is trained: every later stage joins one pool, each job
    # waiting for the jobs that make what its command line names (Runner._waiting)
    manifests = {n: expected_map_manifest(compose("train", a)) for n, a in train_argv.items()}
    lock["maps"] = {n: models_root / f"{m['name']}-{m['id']}" for n, m in manifests.items()}
    lock["errormaps"] = {n: Path(cfg.paths.errormaps_dir) / "-".join(expected_errormap_id(
        manifests[n], [*paths, *args["errormap"]])) for n in errormaps}
    runner.made_by.update({f.name: f"train {n}" for n, f in lock["maps"].items()})
    runner.made_by.update({f.name: f"errormap {n}" for n, f in lock["errormaps"].items()})
    map_refs = {n: f.name for n, f in lock["maps"].items()}
    em_refs = {n: f.name for n, f in lock["errormaps"].items()}
    after = {  # the stages after the data, in one pool: a job starts once the jobs that make its inputs are done
        "train": lambda: _built("train", maps, lock["maps"], runner, lambda n: Job("train", train_argv[n], f"train {n}")),
        "errormap": lambda: _built("errormap", errormaps, lock["errormaps"], runner, lambda n: Job(
            "errormap", [f"maps=[{map_refs[n]}]", *paths, *args["errormap"]], f"errormap {n}")),
        "certified": lambda: paper_stages.certified(cfg, list(cfg.certify), paths, args, lock, runner, manifests)
        if cfg.get("certify") else {},
        "experiments": lambda: _experiments(cfg, list(cfg.experiments), paths, args, map_refs, em_refs, lock, runner)
        if cfg.experiments else {},
        "bracket": lambda: paper_stages.bracket(cfg, list(cfg.bracket), paths, args, lock, runner)
        if cfg.get("bracket") else {},
        "learned": lambda: paper_stages.learned(cfg, list(cfg.learned), paths, args, map_refs, runner)
        if cfg.get("learned") else {},
    }
    with runner.together():  # their jobs side by side in one pool (the 1-core jobs beside each other)
        for key in after:  # learned holds its policies' jobs too
            made = after[key]()  # the folders it will make (bracket's pin reads lock["certified"])
            if key in lock:
                lock[key] = made
    runner.closed = True  # every job ran: the stages are called once more to read and publish what they made
    for key in ("certified", "bracket", "experiments", "learned"):
        lock[key] = after[key]()
    lock = {k: {n: f for n, f in v.items() if tracking.is_complete(f)} for k, v in lock.items()}
    lock_path = write_lock(Path(cfg.paths.paper_dir) / cfg.lock, lock, debug=cfg.get("debug") or "none")
    total = time.perf_counter() - t0
    runner.write_profile(total)
    write_index(Path(cfg.paths.paper_dir))  # after the profile and the copied files: it links every file there
    line = ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()) or "every stage up to date"
    print(f"\n[paper] done in {total / 60:.1f} min ({line}); see {cfg.paths.paper_dir}/index.md; inputs pinned in "
          f"{lock_path}")
    return {"timings": timings, "total": total, "lock": lock_path, "maps": map_refs, "errormaps": em_refs}


def _built(stage: str, names: list[str], folders: dict[str, Path], runner, job) -> dict[str, Path]:
    """The train or errormap stage: `job(name)` for each of `names`, unless every folder of `folders` is built."""
    if names and up_to_date(stage, lambda: folders, runner.said) is None:
        runner.stage(stage, [job(n) for n in names])
    return folders


def _experiments(cfg, experiments, paths, args, map_refs, em_refs, lock, runner) -> dict[str, Path]:
    """The experiments stage with every input pinned, unless the same command ran before and everything it wrote is
    still there; `{experiment: results folder}` from the paper folder's index."""
    pins = experiment_pins(compose("experiments", paths), map_refs, em_refs)
    if not any(p.startswith("paths.paper_dir=") for p in paths):  # the folder this job indexes and locks
        pins.append(f"paths.paper_dir={cfg.paths.paper_dir}")
    argv = ["-m", f"experiment={','.join(experiments)}", *pins, *paths, "publish=true", *args["experiments"]]
    paper_dir = Path(cfg.paths.paper_dir)
    stamp = paper_dir / f".{Path(cfg.lock).stem}.experiments.json"  # what the last run was started with
    if not experiments_up_to_date(stamp, argv, experiments, lock, runner.said):
        stamp.unlink(missing_ok=True)
        one = experiment_jobs(experiments, pins, paths, ["publish=true", *args["experiments"]])
        runner.stage("experiments", one,  # the stamp once every job succeeded (after the pool, when held)
                     then=lambda: stamp.write_text(json.dumps({"stamp": experiments_stamp(argv, lock)}) + "\n"))
    out = {}
    for exp in experiments:
        entry = paper_dir / "index" / f"{exp}.json"
        if entry.is_file():
            out[exp] = (paper_dir / json.loads(entry.read_text())["cache"]).resolve()
    return out


main = stage_main("paper", run="pipeline.paper:run", check="pipeline.paper:check")

if __name__ == "__main__":
    sys.exit(main())
