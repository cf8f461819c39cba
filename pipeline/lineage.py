"""Lineage: which tracked output a reference means, the ids the current configs produce, and the lock of a run.

A reference to a dataset, perception map or error map is a path, a `name-id`, an id, or a name. A name means the
output that the upstream stage's **current config** produces for it (its id recomputed from `conf/`, as a lock
file would: :mod:`pipeline.identity`), never "the newest folder": a quick experiment on the side (another
`clean-<id>`) changes nothing downstream. A name that no config produces (a map trained with `name=...`)
resolves only when exactly one output has it. `make paper` passes exact ids from stage to stage and writes
`outputs/paper/paper.lock.yaml` (:func:`write_lock`).
"""

from __future__ import annotations

from pathlib import Path

import yaml

from pipeline import identity, tracking
from pipeline.config import build, compose
from pipeline.errors import ConfigError, DatasetError
from pipeline.render import Occlusion, load_occlusion
from pipeline.repo import CONF_DIR, write_atomic

COMMANDS = {
    "dataset": "python -m pipeline.data data={name}",
    "error map": "python -m pipeline.errormap maps=[{name}]",
}


def debug_overrides(cfg) -> list[str]:
    """`[debug=<level>]` of a composed config (conf/debug/; none: `[]`): what a stage passes on when it resolves its
    inputs by name, so that a `debug=tiny` run finds the tiny upstream outputs (and its hints say `debug=tiny`)."""
    level = cfg.get("debug") if cfg is not None else None
    return [] if level in (None, "none") else [f"debug={level}"]


def rerun_command(stage: str, fallback=(), cfg=None) -> str:
    """This job's command line, `python -m pipeline.<stage> <its overrides>` without `force=` (outside a Hydra app:
    `fallback` and the config's `debug=<level>`): what a message tells the user to run again."""
    try:
        from hydra.core.hydra_config import HydraConfig

        overrides = list(HydraConfig.get().overrides.task)
    except Exception:  # noqa: BLE001 - not under @hydra.main (tests, a stage called from Python)
        overrides = [*fallback, *debug_overrides(cfg)]
    return " ".join([f"python -m pipeline.{stage}", *(o for o in overrides if not o.startswith("force="))])


def _with(command: str | None, overrides) -> str | None:
    return " ".join([command, *overrides]) if command and overrides else command


def _recipe(name: str) -> bool:
    return (CONF_DIR / "data" / f"{name}.yaml").is_file()


def map_recipe(name: str) -> tuple[str, list[str]] | None:
    """(data recipe, train overrides) of the map a name means: `<recipe>` is what `python -m pipeline.train
    data=<recipe>` trains, `<recipe>_<model>` (e.g. `clean_paper`) what `... data=<recipe> model=<model>` trains
    (`model` an option of conf/model/); None when no config makes `name`."""
    if _recipe(name):
        return name, []
    for i, ch in enumerate(name):
        if ch == "_" and _recipe(name[:i]) and (CONF_DIR / "model" / f"{name[i + 1:]}.yaml").is_file():
            return name[:i], [f"model={name[i + 1:]}"]
    return None


def map_command(name: str) -> str:
    """The command that trains the map `name` means (see :func:`map_recipe`)."""
    recipe, extra = map_recipe(name) or (name, [])
    return " ".join(["python -m pipeline.train", f"data={recipe}", *extra])


# ------------------------------------------------------------------------------------------ datasets
def dataset_identity(cfg) -> tuple[str, str, dict, Occlusion]:
    """(name, id, recipe, cloud level) of the dataset a composed config's `data` recipe renders: its parent dataset
    and its map in the loop resolved to `name-id`s (which the recipe then holds, so they are in the id); the level
    built from `occlusions` (once: the data stage renders with it)."""
    recipe = tracking.to_plain(cfg.data)
    sampling = recipe.get("sampling") or {}
    debug = debug_overrides(cfg)
    if sampling.get("parent") is not None:
        try:
            sampling["parent"] = resolve_dataset(sampling["parent"], cfg.paths.datasets_dir, debug).name
        except DatasetError as err:
            raise ConfigError("data.sampling.parent", str(err)) from None
    cl = sampling.get("closed_loop") or {}
    if cl.get("map") is not None:
        try:
            cl["map"] = resolve_map(cl["map"], cfg.paths.models_dir, field="data.sampling.closed_loop.map",
                                    overrides=debug).name
        except DatasetError as err:
            raise ConfigError("data.sampling.closed_loop.map", str(err)) from None
    occlusion = load_occlusion(recipe.get("occlusion", "none"), cfg.occlusions, field="data.occlusion")
    id_ = identity.dataset_id(recipe, tracking.to_plain(cfg.scene), tracking.to_plain(cfg.render), occlusion.config())
    return recipe["name"], id_, recipe, occlusion


def expected_dataset_id(name: str, overrides=()) -> str | None:
    """Id of the dataset `python -m pipeline.data data=<name> [overrides]` renders (None: not a recipe)."""
    if not _recipe(name):
        return None
    return dataset_identity(compose("data", [f"data={name}", *overrides]))[1]


def train_dataset_id(cfg) -> tuple[str, str]:
    """(name, id) of the dataset a composed train config trains on: `dataset` if set (resolved), else the
    dataset its `data` recipe renders with this very config."""
    if cfg.get("dataset"):
        folder = resolve_dataset(cfg.dataset, cfg.paths.datasets_dir, debug_overrides(cfg))
        name, _, id_ = folder.name.rpartition("-")
        return name, id_
    name, id_, _, _ = dataset_identity(cfg)
    return name, id_


def resolve_dataset(ref, datasets_dir, overrides=(), check: bool = True) -> Path:
    """A dataset by path, `name-id`, id or name (`overrides`, e.g. `debug=tiny`, join the config a name means),
    checked against its manifest (`check`; :func:`pipeline.tracking.resolve`)."""
    return tracking.resolve(Path(datasets_dir), ref, kind="dataset",
                            expected=lambda name: expected_dataset_id(name, overrides),
                            command=lambda name: _with(COMMANDS["dataset"].format(name=name), overrides),
                            field="dataset", check=check)


# ------------------------------------------------------------------------------------- perception maps
def expected_map_id(name: str, overrides=()) -> str | None:
    """Id of the map `map_command(name) [overrides]` trains (None: no config makes `name`)."""
    made_by = map_recipe(name)
    if made_by is None:
        return None
    recipe, extra = made_by
    cfg = compose("train", [f"data={recipe}", *extra, *overrides])
    model_name, id_ = identity.map_identity(tracking.to_plain_lenient(cfg), *train_dataset_id(cfg))
    return id_ if model_name == name else None


def expected_map_manifest(cfg) -> dict:
    """The fields of a map's manifest that the ids downstream of it read (name, id, scene, arena, the model's
    `outputs`), for the map a composed train config trains, before it is trained: from the config and its dataset
    (rendered: read from the dataset's manifest). `make paper` pins the error maps and certified maps of the maps it
    trains in the same pool with them (:func:`expected_errormap_id`); the train stage writes the same values."""
    ds_name, ds_id = train_dataset_id(cfg)
    name, id_ = identity.map_identity(tracking.to_plain_lenient(cfg), ds_name, ds_id)
    ds = tracking.read_manifest(resolve_dataset(f"{ds_name}-{ds_id}", cfg.paths.datasets_dir, debug_overrides(cfg)))
    camera = build(ds["render"], "render", scene=build(ds["scene"], "scene"))  # the train stage's `ds.camera()`
    return {"name": name, "id": id_, "scene": ds["scene"], "arena": [list(a) for a in camera.arena],
            "model": {"outputs": cfg.model.get("outputs")}}


def resolve_map(ref, models_dir, field: str = "maps", overrides=()) -> Path:
    """A perception map by path, `name-id`, id or name (`overrides`, e.g. `debug=tiny`, join the train config a
    name means)."""
    return tracking.resolve(Path(models_dir), ref, kind="perception map",
                            expected=lambda name: expected_map_id(name, overrides),
                            command=lambda name: _with(map_command(name), overrides), field=field)


# ------------------------------------------------------------------------------------------ error maps
def errormap_settings(cfg) -> dict:
    """The settings of a composed errormap config that an error map's id hashes (plain; `occlusion_levels` a list)."""
    out = {k: tracking.to_plain(cfg[k]) for k in cfg.keys() if k not in ("paths", "hydra")}
    if isinstance(out.get("occlusion_levels"), str):
        out["occlusion_levels"] = [out["occlusion_levels"]]
    return out


def errormap_identity(cfg, map_manifest: dict) -> tuple[str, str]:
    """(folder name, id) of the error map a composed errormap config computes for the perception map whose
    manifest is `map_manifest` (its id, name, scene and arena)."""
    settings = errormap_settings(cfg)
    occ = {lv: load_occlusion(lv, cfg.occlusions, field="occlusion_levels").config()
           for lv in settings["occlusion_levels"]}
    pose = (map_manifest.get("model") or {}).get("outputs") == "pose"
    id_ = identity.errormap_id(settings, occ, map_manifest["id"], map_manifest["scene"], map_manifest["arena"], pose)
    return map_manifest["name"], id_


def expected_errormap_id(map_folder: Path | dict, overrides=()) -> tuple[str, str]:
    """(name, id) of the error map `python -m pipeline.errormap maps=[<map name-id>]` computes for a map folder (or
    the manifest of a map not trained yet: :func:`expected_map_manifest`)."""
    m = map_folder if isinstance(map_folder, dict) else tracking.read_manifest(map_folder)
    return errormap_identity(compose("errormap", [f"maps={m['name']}-{m['id']}", *overrides]), m)


def resolve_errormap(ref, errormaps_dir, map_folder: Path | None = None, overrides=()) -> Path:
    """An error map by path, `name-id` or id; `None` means the current config's error map of the map folder (with
    `overrides`, e.g. `debug=tiny`)."""
    if ref is None:
        if map_folder is None:
            raise ValueError("resolve_errormap: a reference or a perception map is needed")
        name, id_ = expected_errormap_id(map_folder, overrides)
        folder = Path(errormaps_dir) / f"{name}-{id_}"
        command = _with(f"python -m pipeline.errormap maps=[{map_folder.name}]", overrides)
        if not tracking.is_complete(folder, "error map"):
            raise DatasetError(f"error map of {map_folder.name}: the current errormap config makes {folder.name}, "
                               f"which is not built under {errormaps_dir}; run `{command}`")
        return tracking.check_intact(folder, "error map", f"{command} force=true")
    return tracking.resolve(Path(errormaps_dir), ref, kind="error map", command=COMMANDS["error map"],
                            field="errormaps")


# ------------------------------------------------------------------------------------------- PPO models
# Here, not in pipeline.learned.ppo (torch and stable-baselines3 at import): the paper job and the learned stage's
# preflight compute a PPO model's id without them.
PPO_CODE = ("envs", "learned/ppo", "learned/spec")


def ppo_identity(cfg) -> str:
    """Id of the PPO model a composed ppo config trains (`python -m pipeline.learned.ppo`): its settings, the scene,
    the reward, the clouds and the code."""
    return tracking.content_id(tracking.to_plain(cfg.ppo), tracking.to_plain(cfg.scene), tracking.to_plain(cfg.env),
                               tracking.to_plain(cfg.occlusion), tracking.code_version(*PPO_CODE))


def ppo_folder(ref, models_dir, field: str = "policies.ppo") -> Path:
    """A trained PPO model's folder (outputs/models/ppo-<id>: path, name-id, id; `ppo`: the one the current
    conf/ppo.yaml makes)."""
    def expected(name: str) -> str | None:
        return ppo_identity(compose("ppo", [f"paths.models_dir={Path(models_dir).resolve()}"])) if name == "ppo" else None

    return tracking.resolve(Path(models_dir), ref, kind="PPO policy", field=field,
                            command="python -m pipeline.learned.ppo", expected=expected)


# ------------------------------------------------------------------------------------------------ lock
def lock_entry(folder: Path) -> dict:
    """Id, config hash and code version of a tracked output (from its manifest)."""
    m = tracking.read_manifest(folder)
    config = {k: v for k, v in m.items() if k not in ("files", "created", "git_commit", "package_version", "id",
                                                       "name", "metrics")}
    return {"id": m.get("id"), "folder": folder.name, "config_hash": tracking.content_id(config),
            "code_version": m.get("code_version") or (m.get("code") if isinstance(m.get("code"), str) else None),
            "git_commit": m.get("git_commit"), "package_version": m.get("package_version")}


def write_lock(path: Path, sections: dict[str, dict[str, Path]],
               generated_by: str = "make paper (pipeline.paper)", debug: str = "none") -> Path:
    """`paper.lock.yaml`: the run's debug level (`none`: full size) and, for every dataset, map, error map and
    experiment result, its id, config hash and code version (sections: kind -> {name: folder})."""
    lock = {kind: {name: lock_entry(folder) for name, folder in items.items()} for kind, items in sections.items()}
    lock = {"generated_by": generated_by, "git_commit": tracking.git_commit(), "debug": str(debug), **lock}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    return write_atomic(path, yaml.safe_dump(lock, sort_keys=False))


def pinned_folders(paper_dir: Path, kind: str) -> dict[str, str]:
    """`{name: folder}` of the `kind` section (e.g. "experiments") of every lock in `paper_dir` (`*.lock.yaml`,
    written by :func:`write_lock`); empty when there is none."""
    out: dict[str, str] = {}
    for path in sorted(Path(paper_dir).glob("*.lock.yaml")):
        section = (yaml.safe_load(path.read_text()) or {}).get(kind) or {}
        out.update({name: entry.get("folder") for name, entry in section.items() if isinstance(entry, dict)})
    return out
