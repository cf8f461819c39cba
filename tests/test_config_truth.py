"""One source of truth (issue 9): every run is exactly its composed config, inputs are pinned by id, nothing
is silently ignored, and every bad input is one line and exit code 2 before any work."""

from __future__ import annotations

import os
import subprocess
import sys

import numpy as np
import pytest
import yaml

from pipeline.cli import REPO_ROOT, compose
from pipeline.errors import ConfigError


def _env():
    env = {k: v for k, v in os.environ.items() if k != "HYDRA_FULL_ERROR"}
    env["MPLBACKEND"] = "Agg"
    return env


def _cli(module, *args, timeout=300):
    return subprocess.run([sys.executable, "-m", module, *args], cwd=REPO_ROOT, env=_env(), capture_output=True,
                          text=True, timeout=timeout)


def _exp_cfg(tmp_path, *extra):
    return compose("experiments", [f"paths.paper_dir={tmp_path / 'paper'}", f"paths.outputs_dir={tmp_path / 'out'}",
                                   "perception=oracle", *extra])


# ------------------------------------------------------------------------------ shared controller gains
def test_u_max_and_k_reach_every_controller_of_a_comparison(tmp_path):
    from pipeline.experiments.context import Context

    cfg = _exp_cfg(tmp_path, "experiment=robustness_sweep", "controller.u_max=5", "controller.k=2",
                   "controllers.cbf.alpha=3")
    ctx = Context(cfg)
    ctrls = {n: ctx.controller(n) for n in ("hybrid", "smooth", "cbf")}
    assert {n: c.u_max for n, c in ctrls.items()} == {"hybrid": 5.0, "smooth": 5.0, "cbf": 5.0}
    assert {n: c.k for n, c in ctrls.items()} == {"hybrid": 2.0, "smooth": 2.0, "cbf": 2.0}
    assert ctrls["cbf"].alpha == 3.0  # a key per controller changes one
    resolved = yaml.safe_load(compose_yaml(cfg))
    assert {resolved["controllers"][n]["u_max"] for n in ("hybrid", "smooth", "cbf")} == {5.0}
    # and in the results: far from the target every controller is saturated at the shared limit
    x0 = np.array([[-45.0, 20.0], [-40.0, -25.0]])
    for name, c in ctrls.items():
        res = ctx.simulate(c, x0, horizon=1.0)
        speed = np.hypot(res.u[..., 0], res.u[..., 1])
        assert speed.max() == pytest.approx(5.0, rel=1e-6), name
    default = Context(_exp_cfg(tmp_path, "experiment=robustness_sweep"))
    res = default.simulate(default.controller("smooth"), x0, horizon=1.0)
    assert np.hypot(res.u[..., 0], res.u[..., 1]).max() > 5.0 + 1e-6


def compose_yaml(cfg) -> str:
    from omegaconf import OmegaConf

    return OmegaConf.to_yaml({k: cfg[k] for k in ("controller", "controllers")}, resolve=True)


# ---------------------------------------------------------------------------------------- cache keys
def test_baseline_parameter_recomputes_and_a_title_only_redraws(tmp_path):
    from pipeline.experiments.stage import COMPUTE_CODE, run

    small = ["experiment=robustness_sweep", "scale=0.05", "experiment.eps=[0.5]", "experiment.disturbances=[adversarial]"]
    first = run(_exp_cfg(tmp_path, *small))
    assert not first["cached"]
    retitled = run(_exp_cfg(tmp_path, *small, "experiment.title=Another title", "experiment.paper=nothing"))
    assert retitled["cached"] and retitled["cache"] == first["cache"]
    baseline = run(_exp_cfg(tmp_path, *small, "controllers.smooth.k=2"))
    assert not baseline["cached"] and baseline["cache"] != first["cache"]
    unused = run(_exp_cfg(tmp_path, *small, "occlusions.heavy.seed=9", "disturbances.gaussian.sigma=2"))
    assert unused["cached"]  # parameters the sweep does not read do not invalidate it
    disturbance = run(_exp_cfg(tmp_path, *small, "disturbances.alternating.eps=0.3", "experiment.disturbances=[alternating]"))
    assert not disturbance["cached"]
    assert not any(m.endswith(("figures", "report")) for m in COMPUTE_CODE)


def test_hybrid_only_override_is_in_the_cache_key_of_the_hybrid_rows(tmp_path):
    from pipeline.experiments.stage import run

    small = ["experiment=robustness_sweep", "scale=0.05", "experiment.eps=[0.5]", "experiment.disturbances=[adversarial]"]
    a = run(_exp_cfg(tmp_path, *small))
    b = run(_exp_cfg(tmp_path, *small, "controller.chi=1.3", "controller.lam=0.2"))
    assert a["cache"] != b["cache"]


# ------------------------------------------------------------------------------------- unknown keys
@pytest.mark.parametrize("override", ["+controller.lamda=0.05", "controller.chii=2", "+disturbance.epsilon=0.3",
                                      "++controller.lamda=0.05", "+sim.dtt=0.1", "+camera.rate=10"])
def test_unknown_keys_with_and_without_plus_are_one_line(override):
    proc = _cli("pipeline.simulate", override, "plot=false", "hydra.run.dir=/tmp/never-used-run-dir")
    key = override.lstrip("+").split("=")[0]
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and proc.stderr.startswith(f"error: {key}: ")
    assert "unknown key" in proc.stderr and "Traceback" not in proc.stderr


# ------------------------------------------------------------------------------- bad input, every stage
def _bad_cases(tmp_path):
    afile = tmp_path / "a_file"
    afile.write_text("x")
    return [
        ("pipeline.simulate", ["camera.p_fail=abc"], "camera.p_fail"),
        ("pipeline.simulate", ["init=grid", "init.nx=abc"], "init.nx"),
        ("pipeline.simulate", ["init=near_k", "init.a_range=[-10.0,-40.0]"], "init.a_range"),
        ("pipeline.simulate", ["init.points=[[0.5,0.5]]"], "init.points"),
        ("pipeline.simulate", ["scene.target=[80.0,0.0]"], "scene.target"),
        ("pipeline.simulate", ["scene.obstacle.center=[0.0,45.0]"], "scene.obstacle.center"),
        ("pipeline.simulate", ["sim.seed=-1"], "sim.seed"),
        ("pipeline.simulate", [f"paths.outputs_dir={afile}"], "paths.outputs_dir"),
        ("pipeline.simulate", [f"paths.outputs_dir={afile}/sub"], "paths.outputs_dir"),
        ("pipeline.data", ["data.seed=-1"], "data.seed"),
        ("pipeline.data", ["data.splits.train=abc"], "data.splits"),
        ("pipeline.data", ["data=nope"], "data"),
        ("pipeline.data", [f"paths.datasets_dir={afile}"], "paths.datasets_dir"),
        ("pipeline.data", ["-m", "data=clean,occluded", "occlusions.heavy.opacity=[0.9,0.1]"], "occlusions.heavy.opacity"),
        ("pipeline.errormap", ["grid.step=abc"], "grid.step"),
        ("pipeline.errormap", [f"paths.errormaps_dir={afile}"], "paths.errormaps_dir"),
        ("pipeline.experiments", ["experiment=robustness_sweep", "experiment.n_agents=-5"], "experiment.n_agents"),
        ("pipeline.experiments", ["experiment=robustness_sweep", "experiment.a_range=[-10.0,-40.0]"], "experiment.a_range"),
        ("pipeline.experiments", ["experiment=robustness_sweep", "+experiment.nagents=5"], "experiment.nagents"),
        ("pipeline.experiments", ["experiment=robustness_sweep", "controllers.cbf.alpha=-1"], "controllers.cbf.alpha"),
        ("pipeline.experiments", ["experiment=robustness_sweep", "scale=abc"], "scale"),
        ("pipeline.experiments", ["experiment=noise_failure", "experiment.initial_conditions=[[1.0,1.0]]"],
         "experiment.initial_conditions"),
        ("pipeline.experiments", ["-m", "experiment=coverings,robustness_sweep", "experiment.eps=[-1.0]"], "experiment.eps"),
        ("pipeline.experiments", ["experiment=nope"], "experiment"),
        ("pipeline.paper", ["datasets=[nope]"], "datasets"),
        ("pipeline.paper", ["+args.render=[x]"], "args.render"),
    ]


def test_bad_input_is_one_line_and_exit_2_before_any_work(tmp_path):
    out = tmp_path / "out"
    for module, args, field in _bad_cases(tmp_path):
        extra = [] if any(a.startswith("paths.") for a in args) else [f"paths.root_dir={out}"]
        extra += {"pipeline.experiments": ["perception=oracle"], "pipeline.simulate": ["plot=false"]}.get(module, [])
        proc = _cli(module, *args, *extra, f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'sweep'}")
        msg = f"{module} {args}: rc {proc.returncode}\n{proc.stderr[-2000:]}"
        assert proc.returncode == 2, msg
        lines = proc.stderr.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"error: {field}"), msg
        assert "Traceback" not in proc.stderr + proc.stdout, msg
        assert not out.exists() or not any(out.rglob("*.npy")), msg  # no work was done


def test_missing_input_names_the_command_that_makes_it(tmp_path):
    proc = _cli("pipeline.experiments", "experiment=noise_failure", f"paths.root_dir={tmp_path}",
                f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert "python -m pipeline.train data=clean" in proc.stderr and len(proc.stderr.strip().splitlines()) == 1


# ------------------------------------------------------------------------------------ faults
def test_stale_temporaries_are_removed_and_verify_fails_without_manifest(tmp_path):
    from pipeline.data import run as data_run
    from pipeline.data.verify import verify_datasets

    root = tmp_path / "datasets"
    stale = root / ".tmp-clean-0123456789-999999999"  # a pid that does not run
    stale.mkdir(parents=True)
    (stale / "images_train.npy").write_bytes(b"0" * 1000)
    live = root / f".tmp-clean-0123456789-{os.getpid()}"
    live.mkdir()
    small = ["data=clean", "data.splits.train=16", "data.splits.val=4", "data.splits.test=4", f"paths.datasets_dir={root}"]
    out = data_run(compose("data", small))
    assert not stale.exists() and live.exists()
    broken = root / "clean-abcdef0123"
    broken.mkdir()
    lines = []
    report = verify_datasets(root, echo=lines.append)
    assert report[str(out["path"])] == [] and report[str(broken)] and any("FAIL clean-abcdef0123" in s for s in lines)
    proc = _cli("pipeline.data.verify", f"paths.datasets_dir={root}", f"hydra.run.dir={tmp_path / 'run'}")
    assert proc.returncode == 2 and "manifest" in proc.stdout + proc.stderr


# ----------------------------------------------------------------------- lineage: never the newest folder
def test_a_name_means_the_current_config_never_the_newest_folder(tmp_path):
    from pipeline.data import open_dataset
    from pipeline.data import run as data_run
    from pipeline.errors import DatasetError

    root = tmp_path / "datasets"
    small = ["data.splits.train=16", "data.splits.val=4", "data.splits.test=4", f"paths.datasets_dir={root}"]
    default = data_run(compose("data", ["data=clean", *small]))
    side = data_run(compose("data", ["data=clean", *small, "data.seed=7"]))  # a quick experiment on the side
    assert side["id"] != default["id"]
    # the name resolves to what conf/data/clean.yaml makes now (full size here: not built), never to `side`
    with pytest.raises(DatasetError, match="current config makes clean-") as err:
        open_dataset("clean", datasets_dir=root)
    assert "python -m pipeline.data data=clean" in str(err.value) and side["path"].name in str(err.value)
    assert open_dataset(default["id"], datasets_dir=root).id == default["id"]
    # a name no config makes resolves only when unambiguous
    from pipeline import tracking

    (root / "mine-aaaaaaaaaa").mkdir()
    (root / "mine-aaaaaaaaaa" / "manifest.json").write_text('{"id": "aaaaaaaaaa", "created": "1"}')
    assert tracking.resolve(root, "mine").name == "mine-aaaaaaaaaa"
    (root / "mine-bbbbbbbbbb").mkdir()
    (root / "mine-bbbbbbbbbb" / "manifest.json").write_text('{"id": "bbbbbbbbbb", "created": "2"}')
    with pytest.raises(DatasetError, match="ambiguous"):
        tracking.resolve(root, "mine")


def test_paper_keeps_its_maps_when_a_quick_experiment_trains_another(tmp_path):
    """Issue 9, item 1, end to end on a tiny config: `make paper`, a quick 1-epoch training on the side, then
    `make paper` again: every figure and the lock file keep the paper's own map id."""
    root = tmp_path / "root"
    data = ["data.splits.train=256", "data.splits.val=32", "data.splits.test=32"]
    q = lambda xs: "[" + ",".join(f"'{x}'" for x in xs) + "]"  # noqa: E731 - quoted override list
    args = [f"paths.root_dir={root}", "datasets=[clean,leader_follower]", "maps=[clean]", "errormaps=[clean]",
            "experiments=[perception_closeness,noise_failure]", f"args.data={q(data)}",
            f"args.train={q(['trainer=debug', 'eval_levels=[none]', *data])}",
            f"args.errormap={q(['grid.step=4.0', 'occlusion_levels=[none]', 'train_samples=64'])}",
            f"args.experiments={q(['debug=tiny'])}", f"hydra.run.dir={tmp_path / 'run1'}"]
    first = _cli("pipeline.paper", *args, timeout=900)
    assert first.returncode == 0, first.stderr[-3000:]
    lock = yaml.safe_load((root / "outputs" / "paper" / "paper.lock.yaml").read_text())
    map_folder = lock["maps"]["clean"]["folder"]
    side = _cli("pipeline.train", "data=clean", "trainer=debug", "datamodule.limit_train_samples=64", "eval_levels=[none]",
                *data, f"paths.root_dir={root}", f"hydra.run.dir={tmp_path / 'side'}", timeout=600)
    assert side.returncode == 0, side.stderr[-2000:]
    assert len(list((root / "outputs" / "models").glob(f"{map_folder.rsplit('-', 1)[0]}-*"))) == 2
    again = _cli("pipeline.paper", *args[:-1], f"hydra.run.dir={tmp_path / 'run2'}", timeout=900)
    assert again.returncode == 0, again.stderr[-3000:]
    lock2 = yaml.safe_load((root / "outputs" / "paper" / "paper.lock.yaml").read_text())
    assert lock2["maps"]["clean"]["folder"] == map_folder
    assert lock2["experiments"] == lock["experiments"]  # nothing recomputed with the side map
    index = (root / "outputs" / "paper" / "index.md").read_text()
    assert map_folder in index and "paper.lock.yaml" in index


def test_schema_rejects_wrong_types_in_instantiated_scenarios():
    from pipeline.experiments.scenarios import RobustnessSweep

    with pytest.raises(ConfigError, match="experiment.eps"):
        RobustnessSweep(id="x", title="x", eps="big")
    with pytest.raises(TypeError):
        RobustnessSweep(id="x", title="x", epsilon=[0.1])  # no **kwargs: a typo is not a default
