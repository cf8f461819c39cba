"""The data stage: tracked, content-addressed datasets, the reading API and verify (issue 3 §2-§4)."""

import hashlib
from pathlib import Path

import numpy as np
import pytest
from shared import run_cli  # tests/shared.py

from pipeline import tracking
from pipeline.cli import compose
from pipeline.data import open_dataset, resolve_dataset
from pipeline.data.stage import run
from pipeline.data.verify import verify_datasets
from pipeline.errors import ConfigError, DatasetError

TINY = ["data.splits.train=50", "data.splits.val=10", "data.splits.test=10"]


def cfg_for(root: Path, recipe="clean", *extra):
    return compose("data", [f"data={recipe}", *TINY, f"paths.datasets_dir={root}", *extra])


def file_hashes(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in sorted(folder.iterdir()) if p.name != "manifest.json"}


def cli(module, *args):
    """`python -m module args` in this process (tests/shared.py: the same entry; a Hydra `-m` multirun runs its jobs
    in the launching process too); the data stage's fresh-interpreter case is in tests/test_config_truth.py."""
    return run_cli(module, *args)


@pytest.fixture(scope="module")
def occluded(tmp_path_factory):
    root = tmp_path_factory.mktemp("datasets")
    return root, run(cfg_for(root, "occluded"))


# -------------------------------------------------------------------------------------------- stage
def test_dataset_folder_and_api(tmp_path):
    out = run(cfg_for(tmp_path, "clean"))
    assert not out["skipped"] and out["path"] == tmp_path / f"clean-{out['id']}"
    ds = open_dataset(f"clean-{out['id']}", datasets_dir=tmp_path, verify=True)
    assert ds.id == out["id"] and ds.name == "clean" and ds.counts == {"train": 50, "val": 10, "test": 10}
    assert set(ds.manifest["files"]) == {"images_train.npy", "images_val.npy", "images_test.npy", "labels.csv", "preview.png"}
    assert ds.recipe["occlusion"] == "none" and ds.manifest["seed"] == 0
    for ref in (out["id"], f"clean-{out['id']}", str(out["path"])):
        assert resolve_dataset(ref, tmp_path) == out["path"]
    imgs = ds.images("train")
    assert isinstance(imgs, np.memmap) and imgs.shape == (50, 60, 100, 3) and imgs.dtype == np.uint8
    assert {"split", "x", "y", "follower_x", "follower_y", "occluded_frac"} <= set(ds.labels.columns)
    assert len(ds.labels) == 70
    # the stored images are exactly what the dataset's camera renders from the stored labels
    pos, fol = ds.positions("val"), ds.follower("val")
    assert pos.dtype == np.float32 and pos.shape == (10, 2)
    np.testing.assert_array_equal(ds.camera().render(pos, fol), ds.images("val"))
    # positions stay inside the arena by half the robot; followers keep their distance or are absent
    allpos = ds.positions("train")
    assert np.all(np.abs(allpos[:, 0]) <= 48.5) and np.all(np.abs(allpos[:, 1]) <= 28.5)
    f = ds.follower("train")
    present = ~np.isnan(f[:, 0])
    assert 0 < present.sum() < 50
    d = np.hypot(*(f[present] - allpos[present]).T)  # min_distance 5, but near_share of them within 5 (below)
    assert np.all((d >= 5.0) | (d <= ds.recipe["follower"]["near_distance"]))
    assert ds.recipe["follower"]["near_share"] > 0 and (d < 5.0).any()
    assert np.all(ds.occluded_frac("train") == 0)
    with pytest.raises(DatasetError):
        ds.images("holdout")
    with pytest.raises(DatasetError, match="unknown dataset"):
        open_dataset("nope", datasets_dir=tmp_path)


def test_same_recipe_same_bytes_and_id_seed_changes_id(tmp_path, occluded):
    root, first = occluded
    again = run(cfg_for(tmp_path / "a", "occluded", "data.chunk_size=7"))  # chunking is volatile
    assert again["id"] == first["id"]
    assert file_hashes(again["path"]) == file_hashes(first["path"])
    other = run(cfg_for(tmp_path / "b", "occluded", "data.seed=5"))
    assert other["id"] != first["id"]
    assert file_hashes(other["path"])["images_train.npy"] != file_hashes(first["path"])["images_train.npy"]
    # other things that change the bytes change the id; barrier settings (not in the image) do not
    assert run(cfg_for(tmp_path / "c", "occluded", "render.robot_size=2.0"))["id"] != first["id"]
    assert run(cfg_for(tmp_path / "d", "occluded", "scene.barrier.rho=0.25"))["id"] == first["id"]


def test_occluded_dataset_has_clouds(occluded):
    root, out = occluded
    ds = open_dataset(out["id"], datasets_dir=root)
    frac = ds.occluded_frac("train")  # heavy_mix: clouds on 90% of the images
    assert 0.7 < (frac > 0).mean() < 1.0 and 0.1 < frac.mean() < 0.6
    assert ds.occlusion().name == "heavy_mix" and ds.occlusion().probability == 0.9


def test_second_run_is_a_no_op_and_force_rerenders(tmp_path, capsys):
    cfg = cfg_for(tmp_path, "leader_follower")
    first = run(cfg)
    shard = first["path"] / "images_train.npy"
    stamp = (first["path"].stat().st_mtime_ns, shard.stat().st_mtime_ns)
    second = run(cfg)
    assert second["skipped"] and second["id"] == first["id"]
    assert (first["path"].stat().st_mtime_ns, shard.stat().st_mtime_ns) == stamp
    assert "nothing to do" in capsys.readouterr().out
    forced = run(cfg_for(tmp_path, "leader_follower", "force=true"))
    assert not forced["skipped"] and forced["path"] == first["path"]
    assert (first["path"] / "images_train.npy").stat().st_mtime_ns != stamp[1]
    assert not tracking.verify(forced["path"])
    assert not np.isnan(open_dataset(first["path"]).follower("train")).any()  # every image has the follower


def test_interrupted_render_leaves_nothing(tmp_path, monkeypatch):
    from pipeline.render import Camera

    real = Camera.render
    calls = {"n": 0}

    def flaky(self, *args, **kwargs):
        calls["n"] += 1
        if calls["n"] == 3:
            raise KeyboardInterrupt("simulated interruption mid-write")
        return real(self, *args, **kwargs)

    monkeypatch.setattr(Camera, "render", flaky)
    with pytest.raises(KeyboardInterrupt):
        run(cfg_for(tmp_path, "clean", "data.chunk_size=20"))
    assert calls["n"] == 3
    assert list(tmp_path.iterdir()) == []  # neither the dataset folder nor a temporary one


def test_verify_catches_flipped_byte_and_missing_shard(tmp_path, monkeypatch):
    from pipeline import tracking

    out = run(cfg_for(tmp_path, "clean"))
    folder = out["path"]
    assert verify_datasets(tmp_path, echo=lambda s: None) == {str(folder): []}
    shard = folder / "images_val.npy"
    data = bytearray(shard.read_bytes())
    data[1000] ^= 0xFF
    shard.write_bytes(bytes(data))
    problems = verify_datasets(tmp_path, echo=lambda s: None)[str(folder)]
    assert problems == [f"{shard}: sha256 mismatch (altered)"]
    with pytest.raises(DatasetError, match="images_val.npy"):
        open_dataset(out["id"], datasets_dir=tmp_path, verify=True)
    with pytest.raises(DatasetError, match="images_val.npy: sha256"):  # a small dataset is re-hashed before use
        open_dataset(out["id"], datasets_dir=tmp_path)
    monkeypatch.setattr(tracking, "HASH_LIMIT", 0)  # a big one: the cheap check (sizes) does not re-hash
    open_dataset(out["id"], datasets_dir=tmp_path)
    (folder / "images_test.npy").unlink()
    problems = verify_datasets(tmp_path, echo=lambda s: None)[str(folder)]
    assert f"{folder / 'images_test.npy'}: missing" in problems and len(problems) == 2
    with pytest.raises(DatasetError, match="missing"):
        open_dataset(out["id"], datasets_dir=tmp_path)
    # the stage refuses to skip over (or silently replace) a folder that does not match its manifest
    with pytest.raises(DatasetError, match="damaged dataset .*missing.*force=true"):
        run(cfg_for(tmp_path, "clean"))
    # the CLI lists each problem with its path and exits non-zero
    res = cli("pipeline.data.verify", f"paths.datasets_dir={tmp_path}", f"hydra.run.dir={tmp_path / 'hydra'}")
    assert res.returncode != 0
    assert f"{shard}: sha256 mismatch" in res.stdout and f"{folder / 'images_test.npy'}: missing" in res.stdout
    assert "Traceback" not in res.stderr


@pytest.mark.parametrize(
    "override, field",
    [
        ("data.splits.val=-3", "data.splits.val"),
        ("data.occlusion=fog", "data.occlusion"),
        ("render.px_per_unit=0.33", "render.px_per_unit"),  # no whole number of pixels (was render.height=50)
        ("render.px_per_unit=-1", "render.px_per_unit"),
        ("data.sampling.mode=spiral", "data.sampling.mode"),
        ("data.follower.probability=2", "data.follower.probability"),
    ],
)
def test_bad_config_names_field_and_writes_nothing(tmp_path, override, field):
    with pytest.raises(ConfigError) as err:
        run(cfg_for(tmp_path, "clean", override))
    assert err.value.field == field and "\n" not in str(err.value)  # one line naming the field
    assert not tmp_path.exists() or list(tmp_path.iterdir()) == []


def test_sampling_options(tmp_path):
    grid = run(cfg_for(tmp_path, "clean", "data.sampling.mode=grid", "data.sampling.exclude_obstacle=true"))
    ds = open_dataset(grid["path"])
    p = ds.positions("train").astype(float)
    assert len(np.unique(p, axis=0)) == 50
    assert np.all(np.hypot(p[:, 0], p[:, 1]) > 4.0)
    xs = np.unique(np.round(p[:, 0], 4))
    assert len(xs) < 20  # on a lattice: few distinct columns
    assert not np.array_equal(ds.positions("val")[:5], ds.positions("test")[:5])


# -------------------------------------------------------------------------------------------- CLI
def test_cli_bad_input_is_one_line(tmp_path):
    res = cli("pipeline.data", "data=clean", "data.splits.train=0", f"paths.datasets_dir={tmp_path / 'ds'}",
              f"hydra.run.dir={tmp_path / 'run'}")
    assert res.returncode == 2
    lines = res.stderr.strip().splitlines()
    assert len(lines) == 1 and "data.splits.train" in lines[0] and lines[0].startswith("error:")
    assert "Traceback" not in res.stderr + res.stdout
    assert not (tmp_path / "ds").exists()
    res = cli("pipeline.data", "data=foggy", f"paths.datasets_dir={tmp_path / 'ds'}", f"hydra.run.dir={tmp_path / 'run'}")
    assert res.returncode != 0 and len(res.stderr.strip().splitlines()) == 1
    assert "foggy" in res.stderr and "clean" in res.stderr


def test_cli_multirun_renders_each_recipe(tmp_path):
    res = cli("pipeline.data", "-m", "data=clean,occluded", *TINY, f"paths.datasets_dir={tmp_path / 'ds'}",
              f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert res.returncode == 0, res.stderr
    names = sorted(d.name.rsplit("-", 1)[0] for d in (tmp_path / "ds").iterdir())
    assert names == ["clean", "occluded"]
    assert res.stdout.count("data: ") == 2
    report = verify_datasets(tmp_path / "ds", echo=lambda s: None)
    assert len(report) == 2 and not any(report.values())


def test_closed_loop_sampling_over_represents_visited_positions_by_the_share(tmp_path):
    """`sampling.mode=closed_loop`: the share of images near the target is share * (the visitation pool's
    share there) + (1 - share) * (the uniform share there), within binomial noise; the pool is what the
    composed controller and disturbance visit."""
    from pipeline.data.closed_loop import visitation_pool
    from pipeline.data.plan import plan
    from pipeline.data.recipe import Recipe

    fractions = {}
    for share in (0.0, 0.6):
        cfg = cfg_for(tmp_path / str(share), "closed_loop", "data.splits.train=4000", f"data.sampling.closed_loop.share={share}",
                      "data.sampling.closed_loop.jitter=0.0")
        out = run(cfg)
        ds = open_dataset(out["id"], datasets_dir=out["path"].parent)
        p = ds.positions("train")
        fractions[share] = float((np.hypot(p[:, 0] - 40.0, p[:, 1]) <= 5.0).mean())
        if share:
            pl = plan(cfg)
            pool = visitation_pool(pl.recipe, pl.camera)
            f_pool = float((np.hypot(pool[:, 0] - 40.0, pool[:, 1]) <= 5.0).mean())
            assert f_pool > 0.3  # the closed loop spends its time at the target
            (x0, x1), (y0, y1) = pl.camera.arena
            m = pl.camera.robot_size / 2 / pl.camera.scale
            f_uniform = np.pi * 25.0 / ((x1 - x0 - 2 * m) * (y1 - y0 - 2 * m))
            want = share * f_pool + (1 - share) * f_uniform
            assert abs(fractions[share] - want) < 4 * np.sqrt(want * (1 - want) / 4000) + 1e-3
            assert isinstance(pl.recipe, Recipe) and pl.recipe.closed_loop.controller["_target_"].endswith("HybridController")
    assert fractions[0.6] > 10 * fractions[0.0]
    # the composed controller is part of the dataset id: a different gain is a different dataset
    a = plan(cfg_for(tmp_path, "closed_loop"))
    b = plan(cfg_for(tmp_path, "closed_loop", "data.sampling.closed_loop.controller.k=2"))
    assert a.id != b.id


def test_near_followers_take_their_share_and_share_zero_draws_nothing(tmp_path):
    """`data.follower.near_share` moves that share of the followers within `near_distance` of the leader
    (overlapping squares included); at 0 the plan is byte for byte the one without the keys."""
    from pipeline.data.plan import plan
    from pipeline.data.sampling import plan_split

    def followers(*extra):
        p = plan(cfg_for(tmp_path, "clean", "data.splits.train=4000", "data.sampling.mode=uniform",
                         "data.follower.probability=1.0", *extra))
        sp = plan_split(p.recipe, "train", p.camera, p.occlusion)
        return sp.leader.astype(float), sp.follower.astype(float)

    lead, fol = followers("data.follower.near_share=0.3", "data.follower.near_distance=2.0")
    d = np.hypot(*(fol - lead).T)
    assert abs((d <= 2.0).mean() - 0.3) < 0.03            # the share, within ~4 sigma of binomial noise
    assert not ((d > 2.0) & (d < 5.0)).any()              # the others keep min_distance = 5
    assert (d < 0.5).mean() > 0.01                         # overlapping squares do occur
    base = followers("data.follower.near_share=0.0")
    for a, b in zip(base, followers("~data.follower.near_share", "~data.follower.near_distance"), strict=True):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(ConfigError, match="data.follower.near_share"):
        followers("data.follower.near_share=1.5")


def test_the_gate_stream_draws_fresh_positions_and_leaves_every_split_alone(tmp_path):
    """The `gate` stream (fresh positions for a map's flag gate, `pipeline.train.evaluate.gate_frames`) takes the next
    child of the recipe's seed sequence: every split keeps the stream it had before the stream existed (the first
    three children of `SeedSequence(seed)`), the gate's positions are none of a split's, follow the recipe's
    distribution (the closed-loop share near the target), and an unknown stream or a missing size is refused."""
    from pipeline.data.plan import plan
    from pipeline.data.sampling import SPLITS, plan_split, split_seed

    p = plan(cfg_for(tmp_path, "closed_loop", "data.splits.val=3000"))
    before = np.random.SeedSequence(p.recipe.seed).spawn(3)
    for i, split in enumerate(SPLITS):
        assert np.array_equal(split_seed(p.recipe, split).generate_state(4), before[i].generate_state(4))
    val = plan_split(p.recipe, "val", p.camera, p.occlusion)
    gate = plan_split(p.recipe, "gate", p.camera, p.occlusion, n=3000)
    assert np.array_equal(gate.leader, plan_split(p.recipe, "gate", p.camera, p.occlusion, n=3000).leader)  # deterministic
    assert not (gate.leader[:, None, :] == val.leader[None, :, :]).all(-1).any()
    near = [float((np.hypot(s.leader[:, 0] - 40.0, s.leader[:, 1]) <= 5.0).mean()) for s in (val, gate)]
    assert near[0] > 0.1 and abs(near[0] - near[1]) < 4 * np.sqrt(near[0] * (1 - near[0]) / 1500)
    with pytest.raises(ValueError, match="needs n"):
        plan_split(p.recipe, "gate", p.camera, p.occlusion)
    with pytest.raises(ValueError, match="unknown split"):
        split_seed(p.recipe, "calibration")
