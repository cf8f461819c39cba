"""The DAgger-style recipe (issue 11, item 1): a map in the closed loop that collects positions, error-weighted
draws, aggregation with a parent dataset, the `pipeline.dagger` orchestrator, bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pandas as pd
import pytest
import yaml
from shared import run_cli  # tests/shared.py

from pipeline import tracking
from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError

TINY = ["data.splits.train=300", "data.splits.val=40", "data.splits.test=40"]
LOOP = ["data.sampling.closed_loop.starts=8", "data.sampling.closed_loop.horizon=3"]
TRAIN = ["trainer=debug", "model.filters=[4,8]", "eval_levels=[none]", "trainer.enable_progress_bar=false"]


def _cli(*args, timeout=300):
    env = {**os.environ, "HYDRA_FULL_ERROR": "0", "OMP_NUM_THREADS": "1"}  # tiny batches: one thread is fastest
    return subprocess.run([sys.executable, "-m", *args], cwd=REPO_ROOT, capture_output=True, text=True, env=env,
                          timeout=timeout)


@pytest.fixture
def one_thread():
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


# ------------------------------------------------------------------------------ (a) error-weighted draws
class LeftHalfWrong:
    """A stub perception map: reads the leader off a clean image (centroid of the bright blue channel: only the
    white leader is bright there) and is 6 units off, only in the left half of the arena (x < 0)."""

    def __init__(self, camera):
        self.camera = camera

    def predict(self, images):
        w = np.clip(np.asarray(images, dtype=float)[..., 2] - 120.0, 0.0, None)  # (N, H, W)
        rows, cols = np.indices(w.shape[1:]) + 0.5
        s = w.sum(axis=(1, 2))
        uv = np.stack([(w * cols).sum(axis=(1, 2)) / s, (w * rows).sum(axis=(1, 2)) / s], axis=1)
        p = self.camera.pixel_to_world(uv)
        p[p[:, 0] < 0, 1] += 6.0
        return p


def _stub_recipe(tmp_path, *extra):
    from pipeline.config import build
    from pipeline.render import load_occlusion

    cfg = compose("data", ["data=closed_loop", "data.splits.train=2000", f"paths.datasets_dir={tmp_path}",
                           "data.sampling.closed_loop.map=stub-0123456789", "data.sampling.closed_loop.starts=16",
                           "data.sampling.closed_loop.horizon=10", "data.sampling.closed_loop.share=1.0",
                           "data.sampling.closed_loop.jitter=0.0", "data.sampling.closed_loop.min_error=1.0",
                           "data.sampling.closed_loop.error_floor=0.01", *extra])
    recipe = build(tracking.to_plain(cfg.data), "data")
    camera = build(tracking.to_plain(cfg.render), "render", scene=build(cfg.scene, "scene"))
    return recipe, camera, load_occlusion(recipe.occlusion, cfg.occlusions)


def test_error_weighted_pool_over_represents_where_the_map_is_wrong(tmp_path):
    from pipeline.data.closed_loop import map_visitation_pool
    from pipeline.data.sampling import plan_split

    recipe, camera, occ = _stub_recipe(tmp_path, "data.sampling.closed_loop.error_weighted=true")
    stub = LeftHalfWrong(camera)
    pool = map_visitation_pool(recipe, camera, stub, occ)
    left = pool.positions[:, 0] < 0
    assert len(pool) > 1000 and 0.02 < left.mean() < 0.6  # the loop lives mostly on the right (target at x = 40)
    assert np.all(np.abs(pool.errors[left] - 6.0) < 0.5) and np.all(pool.errors[~left] < 0.5)  # the stub's errors
    new = plan_split(recipe, "train", camera, occ, perception_map=stub).leader
    assert len(new) == 2000 and (new[:, 0] < 0).mean() > 0.9  # "add the positions it visited where it was wrong"
    # not weighted: the draws follow the visitation (the same pool), within binomial noise
    plain, *_ = _stub_recipe(tmp_path, "data.sampling.closed_loop.error_weighted=false")
    share = (plan_split(plain, "train", camera, occ, perception_map=stub).leader[:, 0] < 0).mean()
    assert abs(share - left.mean()) < 4 * np.sqrt(left.mean() * (1 - left.mean()) / 2000) + 0.01
    # val and test never depend on the map: the true-state visitation, as without one
    val = plan_split(recipe, "val", camera, occ).leader
    no_map, *_ = _stub_recipe(tmp_path, "data.sampling.closed_loop.map=null")
    np.testing.assert_array_equal(val, plan_split(no_map, "val", camera, occ).leader)


# ------------------------------------------------------------------------ (b) aggregation with a parent
@pytest.fixture(scope="module")
def round0(tmp_path_factory):
    """A tiny `dagger` dataset (heavy clouds, closed-loop share) and a fast_dev_run map trained on it."""
    import torch

    from pipeline.data.stage import run as data_run
    from pipeline.train.stage import run as train_run

    root = tmp_path_factory.mktemp("dagger")
    paths = [f"paths.datasets_dir={root / 'datasets'}", f"paths.models_dir={root / 'models'}"]
    ds = data_run(compose("data", ["data=dagger", *TINY, *LOOP, *paths]))
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        pm = train_run(compose("train", [f"dataset={ds['path'].name}", *TRAIN, *paths]))
    finally:
        torch.set_num_threads(threads)
    return {"paths": paths, "root": root, "dataset": ds["path"].name, "map": f"{pm['name']}-{pm['id']}"}


def _child(round0, *extra):
    return compose("data", ["data=dagger", "data.name=child", *TINY, "data.splits.train=100", *LOOP, *round0["paths"],
                            f"data.sampling.parent={round0['dataset']}", f"data.sampling.closed_loop.map={round0['map']}",
                            "data.sampling.closed_loop.error_weighted=true", *extra])


def test_aggregated_dataset_keeps_every_parent_position_and_names_its_parents(round0, one_thread):
    from pipeline.data import open_dataset
    from pipeline.data.plan import plan
    from pipeline.data.stage import run as data_run

    out = data_run(_child(round0))
    child = open_dataset(out["path"], verify=True)
    parent = open_dataset(round0["root"] / "datasets" / round0["dataset"])
    n = parent.counts["train"]
    assert child.counts == {"train": n + 100, "val": 40, "test": 40}
    np.testing.assert_array_equal(child.positions("train")[:n], parent.positions("train"))
    np.testing.assert_array_equal(child.follower("train")[:n], parent.follower("train"))
    np.testing.assert_array_equal(child.images("train")[:n], parent.images("train"))
    new = child.positions("train")[n:]  # the new draws are not the parent's
    assert len(np.unique(np.concatenate([new, parent.positions("train")]), axis=0)) == n + 100
    for split in ("val", "test"):  # val/test do not depend on the parent or the map
        np.testing.assert_array_equal(child.images(split), parent.images(split))
    m = child.manifest
    assert m["parents"] == {"dataset": round0["dataset"], "map": round0["map"]}
    assert m["aggregation"] == {"parent_train": n, "new_train": 100}
    visits = m["closed_loop_visits"]
    assert 0 < visits["positions"] <= visits["frames"] and 0 <= visits["outside_view_share"] < 1
    assert visits["map_error"]["mean"] > 0
    assert m["recipe"]["sampling"]["closed_loop"]["map"] == round0["map"]
    # the inputs are in the id: by id or name-id the same dataset; another parent or map, another dataset
    assert plan(_child(round0, f"data.sampling.parent={round0['dataset'].rsplit('-', 1)[1]}")).id == out["id"]
    other = data_run(compose("data", ["data=dagger", *TINY, *LOOP, *round0["paths"], "data.seed=3"]))
    assert plan(_child(round0, f"data.sampling.parent={other['path'].name}")).id != out["id"]
    assert plan(_child(round0, "data.sampling.closed_loop.map=null",
                       "data.sampling.closed_loop.error_weighted=false")).id != out["id"]
    # same config -> same bytes (the map's closed loop simulated again, not taken from the process cache)
    from pipeline.data import closed_loop

    hashes = {k: v["sha256"] for k, v in m["files"].items()}
    closed_loop._POOLS.clear()
    again = data_run(_child(round0, "force=true"))
    assert {k: v["sha256"] for k, v in tracking.read_manifest(again["path"])["files"].items()} == hashes


@pytest.mark.parametrize("override, field", [
    ("data.sampling.parent=nope", "data.sampling.parent"),
    ("data.sampling.closed_loop.map=nope", "data.sampling.closed_loop.map"),
    ("data.occlusion=none", "data.sampling.parent"),  # the parent was rendered with heavy clouds
    ("data.sampling.closed_loop.min_error=-1", "data.sampling.closed_loop.min_error"),
    ("data.sampling.closed_loop.error_floor=0", "data.sampling.closed_loop.error_floor"),
    ("data.sampling.closed_loop.device=tpu", "data.sampling.closed_loop.device"),
    ("data.sampling.closed_loop.map=null", "data.sampling.closed_loop.error_weighted"),  # weighs by a map's error
])
def test_bad_inputs_name_the_field(round0, override, field):
    from pipeline.data.plan import plan

    with pytest.raises(ConfigError) as err:
        plan(_child(round0, override))
    assert err.value.field == field


# ------------------------------------------------------------------------------ (c) the orchestrator
def _dagger_args(root, run_dir):
    q = lambda xs: "[" + ",".join(f"'{x}'" for x in xs) + "]"  # noqa: E731 - quoted override list
    return ["pipeline.dagger", "dagger.rounds=2", f"paths.root_dir={root}", f"hydra.run.dir={run_dir}",
            f"dagger.args.data={q(TINY)}", f"dagger.args.data_later={q(['data.splits.train=100'])}",
            f"dagger.args.train={q(TRAIN)}", "dagger.levels=[none]", "dagger.collect.starts=8",
            "dagger.collect.horizon=3"]


def test_dagger_two_rounds_parent_chain_and_rerun_is_a_no_op(tmp_path, monkeypatch):
    root = tmp_path / "root"
    # the orchestrator in this process (its data and train jobs are fresh processes either way, `pipeline.jobs`),
    # with `_cli`'s environment for them; `pipeline.dagger` in a fresh interpreter: test_bad_keys_are_one_line_exit_2
    monkeypatch.setenv("HYDRA_FULL_ERROR", "0")
    monkeypatch.setenv("OMP_NUM_THREADS", "1")
    first = run_cli(*_dagger_args(root, tmp_path / "run1"))
    assert first.returncode == 0, first.stderr[-3000:]
    reports = list((root / "outputs" / "dagger").iterdir())
    assert len(reports) == 1
    rounds = pd.read_csv(reports[0] / "rounds.csv")
    assert list(rounds["round"]) == [0, 1]
    ds = [tracking.read_manifest(root / "data" / "datasets" / name) for name in rounds["dataset"]]
    maps = [tracking.read_manifest(root / "outputs" / "models" / name) for name in rounds["map"]]
    assert ds[0]["parents"] == {"dataset": None, "map": None}
    assert ds[1]["parents"] == {"dataset": rounds["dataset"][0], "map": rounds["map"][0]}
    assert [m["dataset_name"] + "-" + m["dataset_id"] for m in maps] == list(rounds["dataset"])
    assert list(rounds["train_images"]) == [300, 400] and list(rounds["new_train_images"]) == [300, 100]
    assert rounds["test_mae_px"].notna().all() and rounds["none_near_p95_px"].notna().all()
    for col in ("parent_map_visit_err_mean", "parent_map_outside_view"):
        assert rounds[col].isna().tolist() == [True, False]
    lock = yaml.safe_load((reports[0] / "dagger.lock.yaml").read_text())
    assert lock["maps"]["round1"]["folder"] == rounds["map"][1] and "rounds.md" in json.dumps(
        tracking.read_manifest(reports[0])["files"])
    stamps = {p: p.stat().st_mtime_ns for p in (root / "data" / "datasets").iterdir()}
    again = run_cli(*_dagger_args(root, tmp_path / "run2"))  # nothing to run: in this process
    assert again.returncode == 0, again.stderr[-3000:]
    assert "===" not in again.stdout and again.stdout.count("nothing to do") == 5  # 2 datasets, 2 maps, report
    assert {p: p.stat().st_mtime_ns for p in (root / "data" / "datasets").iterdir()} == stamps


# ----------------------------------------------------------------------------------- (d) bad input
@pytest.mark.parametrize("args, field", [
    (["pipeline.dagger", "dagger.rounds=0"], "dagger.rounds"),
    (["pipeline.dagger", "dagger.collect.starts=0"], "dagger.collect.starts"),
    (["pipeline.dagger", "dagger.args.data=['+data.sampling.closed_loop.mapp=1']"], "data.sampling.closed_loop.mapp"),
    (["pipeline.data", "data=dagger", "+data.sampling.closed_loop.mapp=x"], "data.sampling.closed_loop.mapp"),
    (["pipeline.data", "data=dagger", "data.sampling.closed_loop.mapp=x"], "data.sampling.closed_loop.mapp"),
])
def test_bad_keys_are_one_line_exit_2(tmp_path, args, field):
    rest = (*args[1:], f"paths.root_dir={tmp_path / 'root'}", f"hydra.run.dir={tmp_path / 'run'}")
    # each stage's first case in a fresh interpreter, the others through the same entry in this process
    fresh = args in (["pipeline.dagger", "dagger.rounds=0"],
                     ["pipeline.data", "data=dagger", "+data.sampling.closed_loop.mapp=x"])
    res = _cli(args[0], *rest, timeout=120) if fresh else run_cli(args[0], *rest)
    assert res.returncode == 2, res.stderr
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(f"error: {field}:"), res.stderr
    assert not (tmp_path / "root").exists()


def test_collect_nodes_reach_the_data_job_intact():
    """`dagger.collect.controller` (another option and a changed gain) is exactly the data job's node."""
    from pipeline.dagger import _data_overrides, _settings

    cfg = compose("dagger", ["controller@dagger.collect.controller=smooth", "dagger.collect.controller.k=2.5",
                             "dagger.collect.disturbance.sigma=0.25"])
    d = _settings(cfg)
    dcfg = compose("data", _data_overrides(d, 1, ("a-0123456789", "b-0123456789")))
    cl = tracking.to_plain(dcfg.data.sampling.closed_loop)
    assert cl["controller"] == d["collect"]["controller"] and cl["controller"]["_target_"].endswith("SmoothController")
    assert cl["controller"]["k"] == 2.5 and "chi" not in cl["controller"] and cl["disturbance"]["sigma"] == 0.25
    assert cl["error_weighted"] is True and cl["map"] == "b-0123456789" and dcfg.data.sampling.parent == "a-0123456789"
    assert dcfg.data.name == "dagger_r1"
