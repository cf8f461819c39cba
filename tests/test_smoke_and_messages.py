"""Smoke runs never touch the paper, one figure sequence for make paper and make multi, figures redrawn only when
their inputs change, and the smaller messages of issue 32 (each test fails on the code before the fix)."""

from __future__ import annotations

import json
import re
import shutil

import pytest
import yaml

from pipeline import tracking
from pipeline.cli import CONF_DIR, REPO_ROOT, compose
from pipeline.errors import ConfigError, DatasetError, PipelineError


# ---------------------------------------------------------------------------------- smoke runs and the paper
def test_a_debug_run_writes_its_paper_folder_elsewhere_and_its_lock_records_debug(tmp_path):
    from pipeline.lineage import write_lock

    full, tiny = compose("paper", [f"paths.root_dir={tmp_path}"]), compose("paper", ["debug=tiny",
                                                                                   f"paths.root_dir={tmp_path}"])
    assert full.paths.paper_dir != tiny.paths.paper_dir
    assert not tiny.paths.paper_dir.startswith(full.paths.paper_dir + "/")
    for stage in ("experiments", "data", "train", "errormap"):  # every stage a debug run passes it to agrees
        assert compose(stage, ["debug=tiny", f"paths.root_dir={tmp_path}"]).paths.paper_dir == tiny.paths.paper_dir
    lock = write_lock(tmp_path / "x.lock.yaml", {"datasets": {}}, debug=tiny.debug)
    assert yaml.safe_load(lock.read_text())["debug"] == "tiny"


def test_make_paper_and_make_multi_number_their_figures_in_one_sequence():
    """Every `figN_` / `animN_` stem the drawing code writes (not the registry's keys): one figure per number, an
    animation under its figure's number, each figure in the index's order (report.FIGURES)."""
    from pipeline.experiments.report import FIGURES

    stems: dict[tuple[str, int], set[str]] = {}
    for path in sorted((REPO_ROOT / "pipeline" / "experiments").rglob("*.py")):
        for kind, num, rest in re.findall(r'f?"(fig|anim)(\d+)_(\{scen\.id\}|[a-z_]+)(?:\.gif)?"(?!:)', path.read_text()):
            stems.setdefault((kind, int(num)), set()).add(rest)
    clash = {k: v for k, v in stems.items() if len(v) > 1}
    assert not clash, f"one number, several figures: {clash}"
    for (kind, num), rest in stems.items():
        if kind == "anim":
            fig = stems.get(("fig", num), set())
            assert any(f.endswith(a) for f in fig for a in rest), f"anim{num}_{rest}: fig{num} is {fig or 'missing'}"
    numbers = {int(re.match(r"fig(\d+)_", s).group(1)) for s in FIGURES}
    assert {n for k, n in stems if k == "fig"} <= numbers, "a figure the index does not order"
    assert sorted(numbers) == list(range(1, max(numbers) + 1))


def test_figures_are_redrawn_only_when_their_inputs_change(tmp_path, monkeypatch):
    from pipeline.experiments import stage

    args = ["experiment=coverings", "debug=tiny", f"paths.root_dir={tmp_path}"]
    first = stage.run(compose("experiments", args))
    png = next(f for f in first["files"] if f.suffix == ".png")
    stamp = png.stat().st_mtime_ns
    calls = []
    monkeypatch.setattr(stage, "resolve", lambda name: lambda *a: calls.append(name))
    again = stage.run(compose("experiments", args))
    assert calls == [] and again["files"] == first["files"] and png.stat().st_mtime_ns == stamp
    png.unlink()  # a file gone: drawn again
    stage.run(compose("experiments", args))
    assert len(calls) == 1
    calls.clear()
    stage.run(compose("experiments", [*args, "experiment.title=another title"]))  # what is drawn changed
    assert len(calls) == 1


# ---------------------------------------------------------------------------------------- smaller items
def test_verify_data_resolves_a_name_by_the_current_config_s_id(tmp_path):
    """Not "the newest" or "the only one": another `clean-<id>` made on the side is not what `clean` means."""
    from pipeline.data.verify import verify_datasets
    from pipeline.lineage import expected_dataset_id

    root = tmp_path / "datasets"
    with tracking.tracked_output(root, "clean", "0123456789", {"kind": "dataset", "counts": {}}) as tmp:
        (tmp / "labels.csv").write_text("x\n")
    with pytest.raises(DatasetError, match=f"clean-{expected_dataset_id('clean', ['debug=tiny'])}"):
        verify_datasets(root, "clean", echo=lambda s: None, overrides=["debug=tiny"])
    assert list(verify_datasets(root, "clean-0123456789", echo=lambda s: None)) == [str(root / "clean-0123456789")]


def test_train_s_missing_dataset_hint_keeps_debug_tiny(tmp_path):
    from pipeline.train.stage import run

    with pytest.raises(DatasetError, match=r"`python -m pipeline.data data=clean debug=tiny`"):
        run(compose("train", ["data=clean", "debug=tiny", f"paths.root_dir={tmp_path}"]))


def test_errormap_says_a_missing_dataset_is_the_map_s_training_data(tmp_path):
    from pipeline.errormap.stage import run

    folder = tmp_path / "outputs" / "models" / "clean-0123456789"
    data = compose("data")
    with tracking.tracked_output(folder.parent, "clean", "0123456789",
                                 {"kind": "perception_map", "dataset_id": "abcdefabcd", "dataset_name": "clean",
                                  "scene": tracking.to_plain(data.scene), "arena": [[-50, 50], [-30, 30]],
                                  "render": tracking.to_plain(data.render)}) as tmp:
        (tmp / "model.pt").write_bytes(b"x")

    class Map:  # what run_one reads of a map (injected: no torch needed for this message)
        id, name, manifest = "0123456789", "clean", json.loads((folder / "manifest.json").read_text())

        def camera(self):
            from pipeline.config import build

            return build(compose("data").render, "render", scene=build(compose("data").scene, "scene"))

    with pytest.raises(DatasetError, match="training data of perception map clean-0123456789.*clean-abcdefabcd"):
        run(compose("errormap", ["maps=clean-0123456789", "debug=tiny", "occlusion_levels=[none]",
                                 f"paths.root_dir={tmp_path}"]), perception_map=Map())


def test_a_key_unknown_to_one_job_of_a_sweep_names_the_job():
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("experiments", ["-m", "experiment=camera_attack,coverings", "experiment.attack=pixel_attack"])
    assert err.value.field == "experiment.attack" and "experiment=coverings" in err.value.reason
    assert "\n" not in str(err.value)


def test_a_pixel_attack_of_zero_steps_is_rejected():
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("experiments", ["experiment=camera_attack", "disturbances.pixel_attack.steps=0"])
    assert err.value.field == "disturbances.pixel_attack.steps"


@pytest.mark.parametrize("bad", [{"n_obstacles": 0}, {"radius_range": [3.0, 2.0]}, {"apex_factor": 1.0},
                                 {"barrier": {"rho": -1.0}}, {"barrier_scale_factor": -1.0},
                                 {"radius_range": [40.0, 41.0]}, {"n_obstacles": 40, "radius_range": [4.0, 5.0]}])
def test_a_random_field_s_errors_name_keys_the_config_has(bad):
    """`scene=field`: the message's field is a key of the composed config, so `<field>=<value>` is an override."""
    from omegaconf import OmegaConf

    from pipeline.config import build

    cfg = compose("experiments", ["experiment=multi_monte_carlo", "scene=field"])
    node = OmegaConf.to_container(cfg.scene, resolve=True)
    node = {**node, **{k: ({**node[k], **v} if isinstance(v, dict) else v) for k, v in bad.items()}}
    with pytest.raises(ConfigError) as err:
        build(node, "scene")
    assert OmegaConf.select(cfg, err.value.field, default="__none__") != "__none__", err.value


def test_the_docs_give_the_default_of_publish_the_config_has():
    text = (REPO_ROOT / "docs" / "experiments.md").read_text()
    said = re.search(r"`publish` picks:[^.]*?`(\w+)` \((?:the )?default\)", text, re.S)
    assert said, "docs/experiments.md no longer says publish's default"
    assert said.group(1) == str(compose("experiments").publish).lower()
    assert yaml.safe_load((CONF_DIR / "experiments.yaml").read_text())["publish"] is False


def test_a_damaged_dataset_under_verify_data_is_reported_not_refused(tmp_path):
    """verify-data reports every damaged file (it does not stop at the first like a stage does)."""
    from pipeline.data.verify import verify_datasets

    root = tmp_path / "datasets"
    with tracking.tracked_output(root, "clean", "0123456789", {"kind": "dataset", "counts": {}}) as tmp:
        (tmp / "labels.csv").write_text("abc\n")
    (root / "clean-0123456789" / "labels.csv").write_text("abd\n")
    report = verify_datasets(root, "clean-0123456789", echo=lambda s: None)
    assert any("sha256" in p for p in report[str(root / "clean-0123456789")])


def test_a_damaged_map_folder_is_one_line_through_every_resolver(tmp_path):
    from pipeline.lineage import resolve_map

    with tracking.tracked_output(tmp_path, "clean", "0123456789", {"kind": "perception_map"}) as tmp:
        (tmp / "model.pt").write_bytes(b"0" * 100)
    (tmp_path / "clean-0123456789" / "model.pt").write_bytes(b"0" * 50)
    for ref in ("clean-0123456789", "0123456789", str(tmp_path / "clean-0123456789")):
        with pytest.raises(PipelineError, match=r"model.pt: size 50 != 100.*pipeline.train data=clean.*force=true"):
            resolve_map(ref, tmp_path)
    shutil.rmtree(tmp_path / "clean-0123456789")
    (tmp_path / "clean-0123456789").write_text("x")
    with pytest.raises(PipelineError, match="a file where"):
        resolve_map("clean-0123456789", tmp_path)
