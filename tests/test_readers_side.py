"""The reader's side (issue 46): a sweep without `-m`, a misspelled `--config-name` and an override the selected
experiment bundle never reads are each one line on stderr and exit code 2, before any work (each test fails on the
code before the fix)."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
from shared import run_cli  # tests/shared.py

from pipeline.cli import CONF_DIR, REPO_ROOT, compose
from pipeline.errors import ConfigError


def _cli(module, *args, timeout=300):
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO_ROOT, env={**env, "MPLBACKEND": "Agg"},
                          capture_output=True, text=True, timeout=timeout)


def _entry(fresh: bool):
    """`python -m` in a fresh interpreter, or the same entry in this one (`run_cli`: a second of imports less)."""
    return _cli if fresh else run_cli


def _one_line(proc, field: str) -> str:
    msg = f"rc {proc.returncode}\n{proc.stderr[-2000:]}"
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}: "), msg
    assert "Traceback" not in proc.stderr + proc.stdout, msg
    return lines[0]


def _before_hydra(config_name: str, argv: list[str], check=None, reads=None) -> None:
    from pipeline.cli import before_hydra

    before_hydra(config_name, argv, check, reads)


# ------------------------------------------------------------------------------------ a sweep without -m
@pytest.mark.parametrize("module,override", [("pipeline.simulate", "controller=hybrid,smooth"),
                                             ("pipeline.data", "data=clean,occluded"),
                                             ("pipeline.experiments", "experiment=coverings,scheme"),
                                             ("pipeline.paper", "debug=none,tiny")])
def test_a_sweep_without_multirun_is_one_line_naming_the_key_in_every_stage(tmp_path, module, override):
    """Hydra's own answer was five lines and exit 1 (the simulator in a fresh interpreter, the others in this one)."""
    key, _, value = override.partition("=")
    line = _one_line(_entry(module == "pipeline.simulate")(module, override, f"paths.root_dir={tmp_path}"), key)
    assert f"'{value}' is a sweep" in line and "-m" in line, line


def test_a_sweep_with_multirun_or_a_multirun_config_passes_the_check(tmp_path):
    root = f"paths.root_dir={tmp_path}"
    with pytest.raises(ConfigError) as err:
        _before_hydra("simulate", ["plot=false", "sim.horizon=1,2", root])
    assert err.value.field == "sim.horizon" and "sim.horizon=[1,2]" in err.value.reason  # a key's list spelled out
    _before_hydra("simulate", ["-m", "controller=hybrid,smooth", root])
    _before_hydra("simulate", ["--multirun", "controller=hybrid,smooth", root])
    _before_hydra("simulate", ["hydra.mode=MULTIRUN", "controller=hybrid,smooth", root])  # Hydra sweeps it as is
    _before_hydra("simulate", ["plot=false", "controller=hybrid", root])  # no sweep


# ------------------------------------------------------------------------------------ a misspelled config name
@pytest.mark.parametrize("args", [["--config-name", "simulte"], ["--config-name=simulte"], ["-cn", "simulte"]])
def test_a_misspelled_config_name_is_one_line_listing_the_configs_closest_first(tmp_path, args):
    fresh = args[0] == "--config-name" and len(args) == 2  # the first spelling in a fresh interpreter
    line = _one_line(_entry(fresh)("pipeline.simulate", *args, f"paths.root_dir={tmp_path}"), "--config-name")
    names = sorted(p.stem for p in CONF_DIR.glob("*.yaml"))
    assert "'simulte'" in line and all(n in line for n in names), line
    listed = line.split(": ", 2)[2]
    assert listed.index("simulate") < min(listed.index(n) for n in names if n != "simulate"), line


# ------------------------------------------------------------------------------------ an override never read
def test_a_map_the_experiment_never_reads_is_one_line_naming_key_and_bundle(tmp_path):
    """`robustness_sweep` runs on the true state: `maps.clean` was silently ignored (exit 0)."""
    line = _one_line(run_cli("pipeline.experiments", "experiment=robustness_sweep", "maps.clean=clean_paper",
                             f"paths.root_dir={tmp_path}"), "maps.clean")
    assert "robustness_sweep" in line, line


def _exp(*argv, tmp_path):
    from pipeline.cli import resolve

    _before_hydra("experiments", [*argv, "perception=oracle", f"paths.root_dir={tmp_path}"],
                  resolve("pipeline.experiments.checks:check"), resolve("pipeline.experiments.checks:inputs_read"))


@pytest.mark.parametrize("argv,field", [
    (["experiment=robustness_sweep", "maps.clean=clean_paper"], "maps.clean"),
    (["experiment=noise_failure", "controllers.cbf.alpha=2"], "controllers.cbf.alpha"),
    (["experiment=noise_failure", "disturbances.adversarial.eps=0.3"], "disturbances.adversarial.eps"),
    (["experiment=noise_failure", "errormaps.clean=abc"], "errormaps.clean"),
    (["experiment=occlusion", "occlusions.light.seed=3"], "occlusions.light.seed"),
    (["experiment=occlusion", "occlusions.light.opacity=[0.1,0.2]"], "occlusions.light.opacity"),
    (["-m", "experiment=robustness_sweep,scheme", "maps.clean=clean_paper"], "maps.clean"),
])
def test_an_override_no_job_reads_is_rejected(tmp_path, argv, field):
    with pytest.raises(ConfigError) as err:
        _exp(*argv, tmp_path=tmp_path)
    assert err.value.field == field and "\n" not in str(err.value)
    if "robustness_sweep" in argv[-2]:
        assert "robustness_sweep" in err.value.reason


@pytest.mark.parametrize("argv", [
    ["experiment=noise_failure", "maps.clean=clean_paper", "disturbances.gaussian.sigma=0.5", "controller.chi=1.2"],
    ["experiment=robustness_sweep", "controllers.cbf.alpha=2", "disturbances.adversarial.eps=0.3"],
    ["experiment=occlusion", "maps.occluded=x", "occlusions.heavy.seed=3"],
    ["experiment=occlusion", "experiment.occlusion=heavy_mix", "occlusions.heavy.seed=3"],  # heavy_mix reads heavy's
    ["experiment=perception_closeness", "errormaps.clean=abc"],
    ["-m", "experiment=robustness_sweep,noise_failure", "maps.clean=clean_paper"],  # one job of the sweep reads it
    ["experiment=robustness_sweep", "paths.side_dir=side", "experiment.n_agents=3", "scale=0.5"],
])
def test_an_override_a_job_reads_passes(tmp_path, argv):
    _exp(*argv, tmp_path=tmp_path)


def test_make_paper_passes_each_experiment_only_the_inputs_it_reads(tmp_path):
    """The paper DAG pins every map kind it built: each experiment's job gets the pins it reads, no other."""
    from pipeline.paper import experiment_jobs

    paths = [f"paths.root_dir={tmp_path}"]
    pins = ["maps.clean=clean_keypoint-0123456789", "maps.occluded=occluded_keypoint-0123456789",
            "errormaps.clean=clean_keypoint-9876543210"]
    jobs = {j.label: j.argv for j in experiment_jobs(["robustness_sweep", "occlusion", "noise_failure"], pins, paths,
                                                   ["publish=true"])}
    assert not any(a.startswith(("maps.", "errormaps.")) for a in jobs["experiments robustness_sweep"])
    assert [a for a in jobs["experiments occlusion"] if a.startswith("maps.")] == pins[:2]
    assert [a for a in jobs["experiments noise_failure"] if a.startswith(("maps.", "errormaps."))] == pins[:1]
    assert all(j[0].startswith("experiment=") and j[-1] == "publish=true" and paths[0] in j for j in jobs.values())
    assert compose("experiments", jobs["experiments occlusion"])  # every job composes
