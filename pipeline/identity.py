"""What determines each stage's output: the id of a dataset, a perception map and an error map (pure functions).

A tracked output's folder is `<name>-<id>` with `id` a short hash of exactly what determines its bytes: the
resolved config that matters (minus volatile keys), the ids of its inputs, and the code that computes it
(`tracking.code_version`). Nothing here reads a tracked output or resolves a reference: callers pass plain configs
and resolved ids (:mod:`pipeline.lineage` composes and resolves, the stages compute).
"""

from __future__ import annotations

from collections.abc import Mapping

from pipeline import tracking

# ------------------------------------------------------------------------------------------- datasets
# recipe keys left out of a dataset's id: the chunk size does not change the bytes; `closed_loop.device` is where a
# map runs in the loop (as the train stage leaves the accelerator out of a model's id; docs/dagger.md)
DATASET_VOLATILE = ("chunk_size", "device")
DATASET_CODE = ("render", "data/recipe", "data/sampling", "data/render")


def dataset_code(recipe: Mapping) -> tuple[str, ...]:
    """The code that determines a dataset's bytes: closed-loop sampling also runs the simulator, and with a map in
    the loop the camera measurement and the map's inference."""
    sampling = recipe.get("sampling") or {}
    if sampling.get("mode") != "closed_loop":
        return DATASET_CODE
    with_map = ("perception/measure", "perception/maps", "perception/network", "perception/spec", "perception/heading",
                "perception/keypoint") \
        if (sampling.get("closed_loop") or {}).get("map") else ()
    return DATASET_CODE + ("data/closed_loop", "sim", "hybrid", "control", "plants", *with_map)


def visible_scene(scene: Mapping) -> dict:
    """The parts of the scene that appear in the image (barrier settings do not change the bytes)."""
    return {"target": scene.get("target"), "arena": scene.get("arena"),
            "obstacles": [{k: o.get(k) for k in ("center", "radius")} for o in scene.get("obstacles") or []]}


def dataset_id(recipe: Mapping, scene: Mapping, render: Mapping, occlusion: Mapping) -> str:
    """Id of the dataset a recipe renders (`recipe` with its parents' references resolved to `name-id`s)."""
    return tracking.content_id({
        "recipe": tracking.strip_keys(recipe, DATASET_VOLATILE), "scene": visible_scene(scene), "render": render,
        "occlusion": occlusion, "code": tracking.code_version(*dataset_code(recipe)),
    })


# ------------------------------------------------------------------------------------- perception maps
# Trainer arguments that say where/how visibly a run happens, not what it learns: left out of the model id.
PLACEMENT_KEYS = ("_target_", "accelerator", "strategy", "devices", "num_nodes", "enable_progress_bar",
                  "enable_model_summary", "log_every_n_steps", "default_root_dir", "num_sanity_val_steps",
                  "use_distributed_sampler", "sync_batchnorm", "profiler", "logger", "callbacks",
                  "enable_checkpointing", "benchmark", "barebones", "detect_anomaly", "inference_mode",
                  "plugins", "enable_autolog_hparams", "model_registry")
# DataModule arguments that change speed only.
DATAMODULE_SPEED_KEYS = ("_target_", "eval_batch_size", "num_workers", "pin_memory")
# Callbacks that change the saved weights, and which of their arguments do (None = all).
WEIGHT_CALLBACKS = {"ModelCheckpoint": ("monitor", "mode"), "EarlyStopping": None}
MAP_CODE = ("train", "perception/network", "perception/spec", "perception/heading", "perception/keypoint")


def map_name(dataset_name: str, model_cfg: Mapping, override: str | None) -> str:
    """`<dataset>` or `<dataset>_<model name>` (e.g. clean, clean_paper), or the `name` given."""
    if override:
        return str(override)
    parts = [dataset_name]
    if model_cfg.get("name") not in (None, "default"):
        parts.append(str(model_cfg["name"]))
    return "_".join(dict.fromkeys(parts))


def _weight_callbacks(callbacks: Mapping) -> dict:
    out = {}
    for key, node in sorted((callbacks or {}).items()):
        cls = str(node.get("_target_", "")).rsplit(".", 1)[-1]
        if cls in WEIGHT_CALLBACKS:
            keep = WEIGHT_CALLBACKS[cls]
            out[key] = {k: v for k, v in node.items() if k != "verbose" and (keep is None or k in keep or
                                                                          k == "_target_")}
    return out


def map_identity(cfg: Mapping, dataset_name: str, dataset_id_: str) -> tuple[str, str]:
    """(model folder name, id) of the map a train config (plain) trains on dataset `dataset_id_`.

    In the id: the model config (but its `name`), the DataModule's batch and sample limits, the Trainer arguments
    but `PLACEMENT_KEYS`, the callbacks that change the saved weights, the dataset id, the seed, the evaluation
    levels and settings, and the training code. Not in it: accelerator, devices, strategy, logger, workers.
    """
    model = dict(cfg["model"])
    name = map_name(dataset_name, model, cfg.get("name"))
    trainer = {k: v for k, v in cfg["trainer"].items() if k not in PLACEMENT_KEYS}
    datamodule = {k: v for k, v in cfg["datamodule"].items() if k not in DATAMODULE_SPEED_KEYS}
    id_ = tracking.content_id(
        {k: v for k, v in model.items() if k not in ("name", "image_shape")},
        trainer, datamodule, _weight_callbacks(cfg.get("callbacks") or {}),
        dataset_id_, int(cfg["seed"]), list(cfg.get("eval_levels") or []), tracking.code_version(*MAP_CODE),
        *([cfg["uncertainty_eval"]] if cfg.get("uncertainty_eval") is not None else []),
        *([{"certified": cfg["certified"], "code": tracking.code_version("certify")}] if cfg.get("certified") is not None else []),
    )
    return name, id_


# ------------------------------------------------------------------------------------------ error maps
ERRORMAP_VOLATILE = ("force", "progress", "paths", "hydra", "maps", "occlusions", "device", "debug")
ERRORMAP_CODE = ("errormap", "render")


def errormap_id(settings: Mapping, occlusions: Mapping, map_id: str, scene: Mapping, arena, pose: bool = False) -> str:
    """Id of the error map of perception map `map_id` (its scene and arena, from its manifest) under the errormap
    settings (plain, minus volatile keys; `headings` only for a pose map, the only one that reads it) and the
    cloud levels' parameters."""
    volatile = ERRORMAP_VOLATILE if pose else (*ERRORMAP_VOLATILE, "headings")
    return tracking.content_id(tracking.strip_keys(settings, volatile), dict(occlusions), str(map_id),
                               dict(scene), [float(v) for pair in arena for v in pair],
                               tracking.code_version(*ERRORMAP_CODE))


# --------------------------------------------------------------------------------------- certified maps
CERTIFY_VOLATILE = ("force", "progress", "paths", "hydra", "maps", "debug", "threads", "shards", "shard")
CERTIFY_CODE = ("certify", "render", "perception/network", "perception/spec", "perception/maps", "errormap/analysis",
                "errormap/estimates", "control")


def clouds_id(recipe: Mapping, map_id: str, scene: Mapping, arena) -> str:
    """Id of the clouds app's certified table (`pipeline.certify.clouds_run`) of perception map `map_id` (its scene and
    arena) under the settings `recipe` (`CloudsSettings.recipe()`: volatile keys already out)."""
    return tracking.content_id(dict(recipe), str(map_id), dict(scene), [float(v) for pair in arena for v in pair],
                               tracking.code_version(*CERTIFY_CODE))


def certify_id(settings: Mapping, map_id: str, scene: Mapping, arena) -> str:
    """Id of the certified error map of perception map `map_id` (its scene and arena) under the certify settings
    (plain, minus volatile keys)."""
    return tracking.content_id(tracking.strip_keys(settings, CERTIFY_VOLATILE), str(map_id), dict(scene),
                               [float(v) for pair in arena for v in pair], tracking.code_version(*CERTIFY_CODE))
