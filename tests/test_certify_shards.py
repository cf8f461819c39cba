"""The certify stage in shards (pipeline.certify.shards): shards computed apart and merged give the map computed in one
process, array for array, under the same id; a saved shard is read, not recomputed; bad shard settings are one line."""

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from shared import run_cli  # tests/shared.py

from pipeline.certify import shards
from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import PipelineError
from pipeline.preflight import preflight


def _cfg(tiny_maps, certified, *extra):
    root, ids = tiny_maps
    return compose("certify", ["debug=tiny", f"maps={ids['clean']}", f"paths.models_dir={root / 'models'}",
                               f"paths.certified_dir={certified}", "progress=false", "batch=8", *extra])


@given(n=st.integers(0, 200), batch=st.integers(1, 50), k=st.integers(1, 12))
def test_shards_cut_the_chunks_into_contiguous_runs_that_cover_each_once(n, batch, k):
    ranges = shards.chunk_ranges(n, batch)
    assert [a for a, _ in ranges] == list(range(0, n, batch)) and (not ranges or ranges[-1][1] == n)
    runs = [list(shards.shard_chunks(len(ranges), k, i)) for i in range(k)]
    assert sum(runs, []) == list(range(len(ranges)))  # in order, each chunk once
    assert max(map(len, runs)) - min(map(len, runs)) <= 1


@given(sizes=st.lists(st.integers(0, 6), min_size=1, max_size=5), seed=st.integers(0, 99))
def test_merging_parts_concatenates_rows_and_reduces_scalars(sizes, seed):
    rng = np.random.default_rng(seed)
    parts = [({"x": rng.normal(size=(k, 2))} if k else {},
              {"n": k, "worst": [float(rng.normal()), {"at": i}]} if k else {}) for i, k in enumerate(sizes)]
    arrays, scalars = shards.merge(parts, {"n": "sum", "worst": "max"})
    rows = [a["x"] for a, _ in parts if a]
    if rows:
        np.testing.assert_array_equal(arrays["x"], np.concatenate(rows))
        assert scalars["worst"] == max((s["worst"] for _, s in parts if s), key=lambda w: w[0])
    assert scalars["n"] == sum(sizes)
    nested = shards.merge([shards.merge(parts[:1], {"n": "sum", "worst": "max"}),
                           shards.merge(parts[1:], {"n": "sum", "worst": "max"})], {"n": "sum", "worst": "max"})
    assert nested[1] == scalars and nested[0].keys() == arrays.keys()  # shards of chunks merge as the chunks do


def _arrays(folder):
    with np.load(folder / "cells.npz") as z:
        return {k: z[k] for k in z.files}


def test_shards_merge_to_the_map_computed_in_one_process(tiny_maps, tmp_path):
    from pipeline.certify.stage import run

    whole = run(_cfg(tiny_maps, tmp_path / "one"))
    for i in (2, 0):  # out of order; shard 1 is left to the merge
        out = run(_cfg(tiny_maps, tmp_path / "sharded", "shards=3", f"shard={i}"))
        assert out["summary"] is None and out["shard"] == i
        assert shards.shard_path(out["path"], "kappa0", i, 3).is_file()
    merged = run(_cfg(tiny_maps, tmp_path / "sharded", "shards=3"))
    assert merged["path"].name == whole["path"].name  # one id: shards and shard are not in it
    a, b = _arrays(whole["path"]), _arrays(merged["path"])
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k], err_msg=k)
    for k in whole["summary"]["kappas"]:
        assert (whole["path"] / f"error_map_kappa{k}.csv").read_bytes() == \
               (merged["path"] / f"error_map_kappa{k}.csv").read_bytes()
        s, t = whole["summary"]["kappas"][k], merged["summary"]["kappas"][k]
        assert s["eps_bar"] == t["eps_bar"] and s.get("soundness") == t.get("soundness") and s["pgd"]["share_max"] == \
            pytest.approx(t["pgd"]["share_max"])
    assert not (tmp_path / "sharded" / shards.SHARDS_DIR / merged["path"].name).exists()  # merged: removed


def test_a_saved_shard_is_read_not_recomputed(tiny_maps, tmp_path):
    from pipeline.certify.stage import run

    out = run(_cfg(tiny_maps, tmp_path, "shards=2", "shard=0", "kappas=[0.0]", "pgd_cells=0"))
    path = shards.shard_path(out["path"], "kappa0", 0, 2)
    arrays, scalars = shards.load(path)
    arrays["upper"] = arrays["upper"] + 1e4  # a marked shard: the merge must carry the mark
    shards.save(path, (arrays, scalars))
    merged = run(_cfg(tiny_maps, tmp_path, "shards=2", "kappas=[0.0]", "pgd_cells=0"))
    eps = _arrays(merged["path"])["eps_0"][_arrays(merged["path"])["operational"]]
    n = len(arrays["upper"])
    assert 0 < n < len(eps) and np.all(eps[:n] > 1e4) and np.all(eps[n:] < 1e4)


@pytest.mark.parametrize("override, field", [("shard=2", "shard"), ("shards=0", "shards"), ("shard=-1", "shard")])
def test_bad_shard_settings_are_one_line(override, field, tmp_path):
    from pipeline.certify.checks import check

    with pytest.raises(PipelineError) as err:
        preflight("certify", ["shards=2", override, f"paths.outputs_dir={tmp_path}"], check)
    assert err.value.field == field and "\n" not in str(err.value), str(err.value)


def test_a_multirun_over_shards_then_the_merge_from_the_command_line(tiny_maps, tmp_path):
    root, ids = tiny_maps
    common = ["debug=tiny", f"maps={ids['clean']}", f"paths.models_dir={root / 'models'}",
              f"paths.certified_dir={tmp_path / 'certified'}", "progress=false", "batch=8", "kappas=[0.0]",
              "shards=2", f"hydra.sweep.dir={tmp_path / 'multi'}", f"hydra.run.dir={tmp_path / 'run'}"]
    # in this process (tests/shared.py:run_cli, as `python -m` runs it): Hydra's multirun launches its jobs in the
    # process that parses the command line either way
    sweep = run_cli("pipeline.certify", "-m", *common, "shard=0,1")
    assert sweep.returncode == 0, sweep.stderr[-2000:]
    assert sweep.stdout.count("certify: shard ") == 2, sweep.stdout
    merge = run_cli("pipeline.certify", *common)
    assert merge.returncode == 0 and "certify: wrote" in merge.stdout, merge.stderr[-2000:]
    assert "are not saved; computing them here" not in merge.stdout, merge.stdout  # both shards read, none computed


def test_the_clouds_app_in_shards_gives_the_table_of_one_process(tiny_maps, tmp_path):
    from omegaconf import open_dict

    from pipeline.certify.clouds_run import run

    root, ids = tiny_maps

    def clouds(certified, *extra):
        cfg = compose("certify_clouds", [f"paths.models_dir={root / 'models'}", f"clouds.maps={ids['occluded']}",
                                         f"paths.certified_dir={certified}", "clouds.progress=false",
                                         "clouds.limit=6", "clouds.layouts=3", "clouds.samples=1", "clouds.fresh=4",
                                         "clouds.chunk=2", "clouds.gate=0.5", *extra])
        with open_dict(cfg):
            cfg.paths.output_dir = str(tmp_path / "run")
        return run(cfg)

    whole = clouds(tmp_path / "one")
    for i in (2, 0):
        assert clouds(tmp_path / "sharded", "clouds.shards=3", f"clouds.shard={i}")["shard"] == i
    merged = clouds(tmp_path / "sharded", "clouds.shards=3")
    assert merged["path"].name == whole["path"].name and not merged["skipped"]
    assert (whole["path"] / "table.csv").read_bytes() == (merged["path"] / "table.csv").read_bytes()
    for key in ("sampled", "fresh", "eps_bar_delta", "cells_eps_delta_below_c_minus_r"):
        assert whole[key] == merged[key], key
    assert {k: v for k, v in whole["gated"].items() if k != "seconds"} == \
           {k: v for k, v in merged["gated"].items() if k != "seconds"}
    assert whole["sampled"]["frames"] == 6 * 3 * 1 and whole["fresh"]["frames"] == 6 * 4  # every chunk counted
    again = clouds(tmp_path / "one")
    assert again["skipped"] and again["path"] == whole["path"]


def test_the_clouds_settings_defaults_are_the_yaml():
    from dataclasses import asdict

    from omegaconf import OmegaConf

    from pipeline.certify.clouds_cli import CloudsSettings

    yaml = OmegaConf.to_container(OmegaConf.load(REPO_ROOT / "conf" / "certify_clouds.yaml").clouds)
    assert asdict(CloudsSettings()) == yaml


def test_a_merge_that_finds_no_saved_shards_says_so_and_names_the_others(tiny_maps, tmp_path, capsys):
    """Shards of another id (other settings, another code version) are not this map's: the merge computes them and
    says so in one line, naming the others, instead of silently redoing hours of work."""
    from pipeline.certify.stage import run

    run(_cfg(tiny_maps, tmp_path, "shards=2", "shard=0", "kappas=[0.0]", "pgd_cells=0", "seed=1"))
    capsys.readouterr()
    merged = run(_cfg(tiny_maps, tmp_path, "shards=2", "kappas=[0.0]", "pgd_cells=0"))  # seed 0: another id
    lines = [ln for ln in capsys.readouterr().out.splitlines() if ln.startswith("shards:")]
    assert len(lines) == 1 and "2 of 2 shards" in lines[0] and merged["path"].name in lines[0], lines
    others = [d.name for d in (tmp_path / shards.SHARDS_DIR).iterdir()]
    assert len(others) == 1 and others[0] in lines[0] and others[0] != merged["path"].name


def test_the_clouds_app_bounds_in_float64_on_request(tiny_maps, tmp_path):
    """`clouds.dtype=float64`: the bound's arithmetic without float32 rounding (a new id); the same cells and
    layouts, bounds within float32 rounding of the float32 ones, no sampled error past them."""
    from omegaconf import open_dict

    from pipeline.certify.clouds_run import run

    root, ids = tiny_maps
    out = {}
    for dtype in ("float32", "float64"):
        cfg = compose("certify_clouds", [f"paths.models_dir={root / 'models'}", f"clouds.maps={ids['occluded']}",
                                         f"paths.certified_dir={tmp_path}", "clouds.progress=false", "clouds.limit=2",
                                         "clouds.layouts=3", "clouds.samples=2", "clouds.fresh=4",
                                         "clouds.delta=0.9", "clouds.confidence=0.5", f"clouds.dtype={dtype}"])
        with open_dict(cfg):
            cfg.paths.output_dir = str(tmp_path / "run")
        out[dtype] = run(cfg)
    assert out["float32"]["path"] != out["float64"]["path"] and out["float64"]["sampled"]["violations"] == 0
    t32, t64 = (np.loadtxt(out[d]["path"] / "table.csv", delimiter=",", skiprows=1) for d in ("float32", "float64"))
    assert np.isfinite(t32[:, 4]).all()  # delta 0.9 at confidence 0.5: a finite order statistic of 3 layouts
    np.testing.assert_allclose(t64[:, 4], t32[:, 4], rtol=1e-4)
    assert not np.array_equal(t64[:, 4], t32[:, 4])  # the float64 arithmetic reached the bound
