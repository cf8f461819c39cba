"""`make dagger`: the DAgger-style iterative recipe (issue 11) — train, run the closed loop with the learned map,
add the positions it visited where it was wrong, retrain, for `dagger.rounds` rounds.

Round 0 renders `dagger.recipe` and trains map_0 on it. Round k >= 1 renders the same recipe with
`data.sampling.parent=<dataset_{k-1}>` (its train split is kept: D_k = D_{k-1} ∪ new draws) and
`data.sampling.closed_loop.map=<map_{k-1}>` (the new draws come from that map's closed loop, camera and clouds in
it, weighted by its error with `dagger.collect.error_weighted`), then trains map_k on D_k. Every dataset and map
is a tracked output whose manifest names its parents by id.

Each stage runs as its own Hydra job (`pipeline.paper.run_stage`), given exact ids: the orchestrator computes the
id a stage's config produces before running it, and a stage whose output is already built is not started, so
a second `make dagger` only prints. The run's report folder `<paths.dagger_dir>/<recipe>-<id>/` (id: the hash
of every round's dataset and map ids) holds `rounds.csv`, `rounds.md` and `dagger.lock.yaml`.
"""

from __future__ import annotations

import json
import sys
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Annotated, Any

import pandas as pd
from omegaconf import DictConfig

from pipeline import identity, tracking
from pipeline.cli import stage_main
from pipeline.config import build, compose
from pipeline.data.plan import plan
from pipeline.errors import ConfigError, PipelineError
from pipeline.experiments.report import markdown_table
from pipeline.lineage import write_lock
from pipeline.paper import path_overrides, run_stage
from pipeline.schema import Node, Option, PositiveInt, check_value
from pipeline.train.checks import check_settings

LATER = ("error_weighted", "min_error", "error_floor")  # collect keys that need a map: rounds >= 1 only
CL = "data.sampling.closed_loop"


# ------------------------------------------------------------------------------------------ config
@dataclass(frozen=True)
class Collect:
    """`dagger.collect`: the `data.sampling.closed_loop.*` keys of every round (their types and ranges are that
    node's, checked when the rounds' data configs are composed, and named here, :func:`_renamed`)."""

    controller: Annotated[dict, Node()]
    disturbance: Annotated[dict, Node()]
    starts: Any
    horizon: Any
    error_weighted: Any
    min_error: Any
    error_floor: Any


@dataclass(frozen=True)
class Args:
    """`dagger.args`: extra Hydra overrides of every round's data job, of rounds >= 1's, of every train job."""

    data: list[str] = field(default_factory=list)
    data_later: list[str] = field(default_factory=list)
    train: list[str] = field(default_factory=list)


@dataclass(frozen=True)
class Dagger:
    """The `dagger` node (conf/dagger.yaml documents each key)."""

    rounds: PositiveInt
    recipe: Annotated[str, Option("data")]
    collect: Collect
    levels: list[str] = field(default_factory=list)
    args: Args = field(default_factory=Args)


COLLECT = tuple(Collect.__dataclass_fields__)


def _settings(cfg) -> dict:
    """`dagger` node, checked (types and names; the stage configs are checked by :func:`check`)."""
    d = tracking.to_plain(cfg.get("dagger"))
    check_value(d, Dagger, "dagger")
    return {**d, "args": asdict(Args(**(d.get("args") or {}))), "levels": list(d.get("levels") or [])}


def _collect(d: dict, later: bool) -> list[str]:
    """`data.sampling.closed_loop.*` overrides from `dagger.collect`. A controller/disturbance node replaces the
    recipe's (set to null first: an override merges dicts), so another `_target_` keeps none of the old keys."""
    c = d["collect"]
    out = []
    for key in ("controller", "disturbance"):
        out += [f"{CL}.{key}=null", f"{CL}.{key}={override_value(c[key])}"]
    out += [f"{CL}.{k}={override_value(c[k])}" for k in ("starts", "horizon")]
    if later:
        out += [f"{CL}.{k}={override_value(c[k])}" for k in LATER]
    return out


def _data_overrides(d: dict, k: int, prev: tuple[str, str] | None) -> list[str]:
    """The data job of round `k`: the recipe named `<recipe>_r<k>`, the collect settings, the user's overrides,
    and from round 1 the previous round's dataset and map (`prev`, `name-id`s; None: left out, for checks)."""
    out = [f"data={d['recipe']}", f"data.name={d['recipe']}_r{k}", *_collect(d, later=k > 0), *d["args"]["data"]]
    if k > 0:
        out += d["args"]["data_later"]
        if prev is not None:
            out += [f"data.sampling.parent={prev[0]}", f"{CL}.map={prev[1]}"]
    return out


def _renamed(err: ConfigError, where: str) -> ConfigError:
    """A data-stage error on a `dagger.collect` key names that key; others say which overrides they came from."""
    for key in COLLECT:
        if err.field == f"{CL}.{key}" or err.field.startswith(f"{CL}.{key}."):
            return ConfigError(f"dagger.collect.{err.field[len(CL) + 1:]}", err.reason)
    return err if f"(in {where}" in err.reason else ConfigError(err.field, f"{err.reason} (in {where})")


def _compose(config: str, overrides: list[str], where: str):
    """A stage config composed here; Hydra's errors become one `ConfigError` line."""
    try:
        return compose(config, overrides)
    except ConfigError as err:
        raise ConfigError(err.field, f"{err.reason} (in {where})") from None


def check(cfg: DictConfig) -> None:
    """Before any work: the dagger node, round 0's data and train configs (with the collect settings and every
    override), and the later rounds' recipe (as far as it can be checked before map_0 exists)."""
    d = _settings(cfg)
    paths = path_overrides()
    where = "dagger.collect / dagger.args.data"
    try:
        plan(_compose("data", [*_data_overrides(d, 0, None), *paths], where))
        later = tracking.to_plain(_compose("data", [*_data_overrides(d, 1, None), *paths],
                                           f"{where} / dagger.args.data_later").data)
        later["sampling"]["closed_loop"]["map"] = "map"  # a stand-in: map_0 does not exist yet
        build(later, "data")
    except ConfigError as err:
        raise _renamed(err, where) from None
    tcfg = _compose("train", [*paths, *d["args"]["train"]], "dagger.args.train")
    try:
        check_settings(tcfg)
    except ConfigError as err:
        raise ConfigError(err.field, f"{err.reason} (in dagger.args.train)") from None
    missing = [lv for lv in d["levels"] if lv not in list(tcfg.eval_levels or [])]
    if missing:
        raise ConfigError("dagger.levels", f"{missing} are not among the train eval_levels {list(tcfg.eval_levels)}")


# ------------------------------------------------------------------------------------------ rounds
def _round(d: dict, k: int, prev, paths: list[str], timings: dict) -> dict:
    """Round `k`: the data job, then the train job (each skipped when its output is built)."""
    data_args = [*_data_overrides(d, k, prev), *paths]
    dcfg = _compose("data", data_args, f"round {k}")
    for key in ("controller", "disturbance"):  # the node went through the command line intact
        if tracking.to_plain(dcfg.data.sampling.closed_loop[key]) != d["collect"][key]:
            raise PipelineError(f"dagger.collect.{key}: cannot be passed to the data job as an override")
    p = plan(dcfg)
    ds_ref = p.folder_name
    label = f"round {k}/{d['rounds'] - 1}"
    inputs = (f"parent {p.parents['dataset']} + new positions from {p.parents['map']}'s closed loop" if k
              else "the base recipe")
    print(f"\n[dagger] {label}: dataset {ds_ref} ({inputs})", flush=True)
    if tracking.is_complete(p.path):
        print(f"[dagger] {label}: {ds_ref} is built (nothing to do)")
    elif not run_stage("data", data_args, timings, True, tag="dagger", label=f"data r{k}") or not tracking.is_complete(p.path):
        raise PipelineError(f"round {k}: the data job did not produce {p.path}")
    train_args = [f"dataset={ds_ref}", *paths, *d["args"]["train"]]
    tcfg = _compose("train", train_args, "dagger.args.train")
    mname, mid = identity.map_identity(tracking.to_plain_lenient(tcfg), p.recipe.name, p.id)
    map_ref = f"{mname}-{mid}"
    map_path = Path(tcfg.paths.models_dir) / map_ref
    if tracking.is_complete(map_path):
        print(f"[dagger] {label}: map {map_ref} is built (nothing to do)")
    elif not run_stage("train", train_args, timings, True, tag="dagger", label=f"train r{k}") or not tracking.is_complete(map_path):
        raise PipelineError(f"round {k}: the train job did not produce {map_path}")
    return {"dataset": p.path, "map": map_path}


def _row(k: int, out: dict, levels: list[str]) -> dict:
    """One line of rounds.csv from the round's dataset and map manifests."""
    ds = tracking.read_manifest(out["dataset"])
    metrics = json.loads((out["map"] / "metrics.json").read_text())
    parents = ds.get("parents") or {}
    loop = ds.get("closed_loop_visits") or {}
    visits = loop.get("map_error") or {}
    row = {"round": k, "dataset": out["dataset"].name, "map": out["map"].name,
           "parent_dataset": parents.get("dataset") or "", "parent_map": parents.get("map") or "",
           "train_images": ds["counts"]["train"], "new_train_images": ds["recipe"]["splits"]["train"],
           "test_mae_px": metrics["test_split"]["mae_px"],
           "test_near_p95_px": metrics["test_split"]["near_target"]["p95"]}
    for lv in levels:
        row[f"{lv}_mae_px"] = metrics[lv]["mae_px"]
        row[f"{lv}_near_p95_px"] = metrics[lv]["near_target"]["p95"]
    row["parent_map_visit_err_mean"] = visits.get("mean", float("nan"))
    row["parent_map_visit_err_p95"] = visits.get("p95", float("nan"))
    row["parent_map_outside_view"] = loop.get("outside_view_share", float("nan"))
    return row


def _report(cfg, d: dict, outs: list[dict]) -> Path:
    """`<dagger_dir>/<recipe>-<id>/`: rounds.csv, rounds.md, dagger.lock.yaml (kept when already built)."""
    root = Path(cfg.paths.dagger_dir)
    chain = [(o["dataset"].name, o["map"].name) for o in outs]
    id_ = tracking.content_id({"rounds": chain, "levels": d["levels"]})
    folder = root / f"{d['recipe']}-{id_}"
    if tracking.is_complete(folder):
        print(f"\n[dagger] report {folder} is up to date (nothing to do):\n{(folder / 'rounds.md').read_text()}")
        return folder
    df = pd.DataFrame([_row(k, o, d["levels"]) for k, o in enumerate(outs)])
    meta = {"kind": "dagger", "recipe": d["recipe"], "rounds": [{"dataset": a, "map": b} for a, b in chain],
            "settings": d}
    with tracking.tracked_output(root, d["recipe"], id_, meta) as tmp:
        df.to_csv(tmp / "rounds.csv", index=False, float_format="%.6g", lineterminator="\n")
        (tmp / "rounds.md").write_text(f"**DAgger rounds of `{d['recipe']}`** (errors in px; the parent map's visit "
                                       "errors in world units)\n\n" + markdown_table(df))
        write_lock(tmp / "dagger.lock.yaml", {"datasets": {f"round{k}": o["dataset"] for k, o in enumerate(outs)},
                                              "maps": {f"round{k}": o["map"] for k, o in enumerate(outs)}},
                   generated_by="make dagger (pipeline.dagger)")
    print(f"\n[dagger] rounds ({folder / 'rounds.md'}):\n{(folder / 'rounds.md').read_text()}")
    return folder


def run(cfg) -> dict:
    check(cfg)
    d = _settings(cfg)
    t0 = time.perf_counter()
    paths, timings = path_overrides(), {}
    outs, prev = [], None
    for k in range(d["rounds"]):
        outs.append(_round(d, k, prev, paths, timings))
        prev = (outs[-1]["dataset"].name, outs[-1]["map"].name)
    folder = _report(cfg, d, outs)
    line = ", ".join(f"{k} {v:.0f} s" for k, v in timings.items()) or "every output was built"
    print(f"[dagger] done in {(time.perf_counter() - t0) / 60:.1f} min ({line}) -> {folder}")
    return {"rounds": outs, "report": folder, "timings": timings}


main = stage_main("dagger", run="pipeline.dagger:run", check="pipeline.dagger:check")


def override_value(value) -> str:
    """A plain value (from a composed node) in Hydra's override syntax, for passing a node to another job:
    `null`, `true`, numbers, quoted strings, `[...]`, `{key:value,...}`."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int | float):
        return repr(value)
    if isinstance(value, str):
        return "'" + value.replace("'", "\\'") + "'"  # the caller checks the round trip (backslashes)
    if isinstance(value, list | tuple):
        return "[" + ",".join(override_value(v) for v in value) + "]"
    if isinstance(value, dict):
        return "{" + ",".join(f"{k}:{override_value(v)}" for k, v in value.items()) + "}"
    raise TypeError(f"override_value: cannot write {type(value).__name__} {value!r}")


if __name__ == "__main__":
    sys.exit(main())
