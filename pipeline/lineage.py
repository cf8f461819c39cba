"""Lineage: which tracked output a reference means, and the lock file of a whole run.

A reference to a dataset, perception map or error map is a path, a `name-id`, an id, or a name. A name
means the output that the upstream stage's **current config** produces for it (its id recomputed, as a lock
file would), never "the newest folder": a quick experiment on the side (another `clean-<id>`) changes
nothing downstream. A name that no config produces (e.g. a map trained with `name=...`) resolves only when
exactly one output has it. `make paper` passes exact ids from stage to stage and writes
`outputs/paper/paper.lock.yaml` (:func:`write_lock`).
"""

from __future__ import annotations

from pathlib import Path

from pipeline import tracking
from pipeline.cli import CONF_DIR

COMMANDS = {
    "dataset": "python -m pipeline.data data={name}",
    "error map": "python -m pipeline.errormap maps=[{name}]",
}


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


def expected_dataset_id(name: str, overrides=()) -> str | None:
    """Id of the dataset `python -m pipeline.data data=<name> [overrides]` renders (None: not a recipe)."""
    if not _recipe(name):
        return None
    from pipeline.config import compose
    from pipeline.data.stage import plan

    return plan(compose("data", [f"data={name}", *overrides])).id


def train_dataset_id(cfg) -> tuple[str, str]:
    """(name, id) of the dataset a composed train config trains on: `dataset` if set (resolved), else the
    dataset its `data` recipe renders with this very config."""
    from pipeline.data.stage import plan

    if cfg.get("dataset"):
        folder = resolve_dataset(cfg.dataset, cfg.paths.datasets_dir)
        name, _, id_ = folder.name.rpartition("-")
        return name, id_
    p = plan(cfg)
    return p.recipe.name, p.id


def expected_map_id(name: str, overrides=()) -> str | None:
    """Id of the map `map_command(name) [overrides]` trains (None: no config makes `name`)."""
    made_by = map_recipe(name)
    if made_by is None:
        return None
    from pipeline.config import compose
    from pipeline.train.stage import model_identity

    recipe, extra = made_by
    cfg = compose("train", [f"data={recipe}", *extra, *overrides])
    ds_name, ds_id = train_dataset_id(cfg)
    model_name, id_ = model_identity(cfg, ds_name, ds_id)
    return id_ if model_name == name else None


def resolve_dataset(ref, datasets_dir) -> Path:
    return tracking.resolve(Path(datasets_dir), ref, kind="dataset", expected=expected_dataset_id,
                            command=COMMANDS["dataset"], field="dataset")


def resolve_map(ref, models_dir, field: str = "maps") -> Path:
    return tracking.resolve(Path(models_dir), ref, kind="perception map", expected=expected_map_id,
                            command=map_command, field=field)


def expected_errormap_id(pmap, overrides=()) -> tuple[str, str]:
    """(name, id) of the error map `python -m pipeline.errormap maps=[<map name-id>]` computes for `pmap`."""
    from pipeline.config import compose
    from pipeline.errormap.stage import errormap_identity

    cfg = compose("errormap", [f"maps={pmap.name}-{pmap.id}", *overrides])
    return errormap_identity(cfg, pmap)


def resolve_errormap(ref, errormaps_dir, pmap=None) -> Path:
    """An error map by path, `name-id` or id; `None` means the current config's error map of `pmap`."""
    if ref is None:
        if pmap is None:
            raise ValueError("resolve_errormap: a reference or a perception map is needed")
        name, id_ = expected_errormap_id(pmap)
        ref = f"{name}-{id_}"
        folder = Path(errormaps_dir) / ref
        if not tracking.is_complete(folder):
            from pipeline.errors import DatasetError

            raise DatasetError(f"error map of {pmap.name}-{pmap.id}: the current errormap config makes {ref}, which "
                               f"is not built under {errormaps_dir}; run `python -m pipeline.errormap "
                               f"maps=[{pmap.name}-{pmap.id}]`")
        return folder
    return tracking.resolve(Path(errormaps_dir), ref, kind="error map", command=COMMANDS["error map"],
                            field="errormaps")


# ------------------------------------------------------------------------------------------- lock
def lock_entry(folder: Path) -> dict:
    """Id, config hash and code version of a tracked output (from its manifest)."""
    m = tracking.read_manifest(folder)
    config = {k: v for k, v in m.items() if k not in ("files", "created", "git_commit", "package_version", "id",
                                                       "name", "metrics")}
    return {"id": m.get("id"), "folder": folder.name, "config_hash": tracking.content_id(config),
            "code_version": m.get("code_version") or (m.get("code") if isinstance(m.get("code"), str) else None),
            "git_commit": m.get("git_commit"), "package_version": m.get("package_version")}


def write_lock(path: Path, sections: dict[str, dict[str, Path]],
               generated_by: str = "make paper (pipeline.paper)") -> Path:
    """`paper.lock.yaml`: for every dataset, map, error map and experiment result its id, config hash and
    code version (sections: kind -> {name: folder})."""
    import yaml

    lock = {kind: {name: lock_entry(folder) for name, folder in items.items()} for kind, items in sections.items()}
    lock = {"generated_by": generated_by, "git_commit": tracking.git_commit(), **lock}
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp")
    tmp.write_text(yaml.safe_dump(lock, sort_keys=False))
    tmp.replace(path)
    return path


def pinned_folders(paper_dir: Path, kind: str) -> dict[str, str]:
    """`{name: folder}` of the `kind` section (e.g. "experiments") of every lock in `paper_dir` (`*.lock.yaml`,
    written by :func:`write_lock`); empty when there is none."""
    import yaml

    out: dict[str, str] = {}
    for path in sorted(Path(paper_dir).glob("*.lock.yaml")):
        section = (yaml.safe_load(path.read_text()) or {}).get(kind) or {}
        out.update({name: entry.get("folder") for name, entry in section.items() if isinstance(entry, dict)})
    return out
