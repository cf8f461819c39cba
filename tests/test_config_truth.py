"""One source of truth (issue 9): every run is exactly its composed config, inputs are pinned by id, nothing
is silently ignored, and every bad input is one line and exit code 2 before any work.

Every config node names its `_target_`, whose typed signature is its schema: its keys and value types are
checked at composition (`pipeline.config.compose` / `pipeline.preflight`), and the code's defaults are the YAML's of
the default option (the YAML is what runs)."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
import yaml
from shared import index_links, run_cli  # tests/shared.py

from pipeline.cli import CONF_DIR, REPO_ROOT, compose
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
                                   "perception=oracle", "publish=true", *extra])


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
# one cell of the sweep per controller, the sampled loop (what a run reads, not how long it takes, is tested here)
SMALL_SWEEP = ["experiment=robustness_sweep", "scale=0.05", "experiment.eps=[0.5]",
               "experiment.disturbances=[adversarial]", "experiment.time_model=sampled", "sim.horizon=20"]


def _cache_id(cfg) -> str:
    """The id of the folder `run(cfg)` computes into, from the key alone (no simulation)."""
    from pipeline import tracking
    from pipeline.experiments.checks import build_scenario
    from pipeline.experiments.context import Context
    from pipeline.experiments.stage import cache_key
    from pipeline.perception.maps import load_perception_map

    scen = build_scenario(cfg)
    return tracking.content_id(cache_key(cfg, scen, Context(cfg, load_map=load_perception_map)))


def test_baseline_parameter_recomputes_and_a_title_only_redraws(tmp_path):
    from pipeline.experiments.stage import COMPUTE_CODE, run

    small = SMALL_SWEEP
    first = run(_exp_cfg(tmp_path, *small))
    assert not first["cached"]
    assert first["cache"].name == f"robustness_sweep-{_cache_id(_exp_cfg(tmp_path, *small))}"
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
    """The key `run` names its folder by (tied to it above) changes with a hybrid-only parameter."""
    a = _cache_id(_exp_cfg(tmp_path, *SMALL_SWEEP))
    b = _cache_id(_exp_cfg(tmp_path, *SMALL_SWEEP, "controller.chi=1.3", "controller.lam=0.2"))
    c = _cache_id(_exp_cfg(tmp_path, *SMALL_SWEEP, "experiment.title=Another title"))
    assert a != b and a == c


# ------------------------------------------------------------------------------------- unknown keys
@pytest.mark.parametrize("override", ["+controller.lamda=0.05", "controller.chii=2", "+disturbance.epsilon=0.3",
                                      "++controller.lamda=0.05", "+sim.dtt=0.1", "+camera.rate=10",
                                      "+scene.obstacles.0.height=3", "scene.obstacles.0.height=3", "+init.mode=points"])
def test_unknown_keys_with_and_without_plus_are_one_line(override):
    proc = run_cli("pipeline.simulate", override, "plot=false", "hydra.run.dir=/tmp/never-used-run-dir")
    key = override.lstrip("+").split("=")[0]
    key = key.replace("obstacles.0", "obstacles[0]")  # a list element is named by its index
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines() == [proc.stderr.strip()] and proc.stderr.startswith(f"error: {key}: ")
    assert "unknown key" in proc.stderr and "Traceback" not in proc.stderr


# --------------------------------------------------------------- every `_target_` node is its schema
# (config, overrides, the field named): a wrong type, a wrong choice, an unknown key with `+`/`++` (composition
# adds it, the schema rejects it) and without (Hydra rejects it, the preflight names it), in nested nodes too
SCHEMA_CASES = [
    ("simulate", ["sim.dt=abc"], "sim.dt", "must be a number"),
    ("simulate", ["sim.record_every=2.5"], "sim.record_every", "must be an integer"),
    ("simulate", ["sim.stop_on_success=maybe"], "sim.stop_on_success", "must be true or false"),
    ("simulate", ["sim.model=hourly"], "sim.model", "must be one of sampled, continuous"),
    ("simulate", ["sim.method=euler"], "sim.method", "must be one of rosenbrock23, dopri5"),
    ("simulate", ["camera.period=fast"], "camera.period", "must be a number > 0 (or null)"),
    ("simulate", ["controller.chi=[1.1,1.2]"], "controller.chi", "must be a number"),
    ("simulate", ["+controller.lamda=0.05"], "controller.lamda", "unknown key"),
    ("simulate", ["++controller.lamda=0.05"], "controller.lamda", "unknown key"),
    ("simulate", ["controller.chii=2"], "controller.chii", "unknown key"),
    ("simulate", ["controller=cbf", "controller.alpha=abc"], "controller.alpha", "must be a number"),
    ("simulate", ["disturbance=gaussian", "disturbance.sigma=abc"], "disturbance.sigma", "must be a number"),
    ("simulate", ["+disturbance.epsilon=0.3"], "disturbance.epsilon", "unknown key"),
    ("simulate", ["init=grid", "init.nx=abc"], "init.nx", "must be an integer"),
    ("simulate", ["init=grid", "init.exclude_diamond=sometimes"], "init.exclude_diamond", "must be true or false"),
    ("simulate", ["init=grid", "+init.mode=grid"], "init.mode", "unknown key"),  # the key the options lost
    ("simulate", ["init=near_k", "init.obstacle=first"], "init.obstacle", "must be an integer (or null)"),
    ("simulate", ["init.points=[1.0,2.0]"], "init.points[0]", "must be a list"),
    ("simulate", ["scene.target=far"], "scene.target", "must be a list"),
    ("simulate", ["scene.obstacles.0.radius=big"], "scene.obstacles[0].radius", "must be a number"),
    ("simulate", ["scene.obstacles.0.apex=high"], "scene.obstacles[0].apex", "must be a number (or null)"),
    ("simulate", ["+scene.obstacles.0.height=3"], "scene.obstacles[0].height", "unknown key"),
    ("simulate", ["scene.obstacles.0.height=3"], "scene.obstacles[0].height", "unknown key"),
    ("simulate", ["scene.barrier.kind=cubic"], "scene.barrier.kind", "must be one of squared, authors_code"),
    ("simulate", ["+scene.barrier.rho_b=0.3"], "scene.barrier.rho_b", "unknown key"),
    ("simulate", ["scene.arena.x=wide"], "scene.arena.x", "must be a list"),
    ("simulate", ["+scene.obstacle={center:[0,0],radius:4}"], "scene.obstacle", "unknown key"),  # the old key
    ("data", ["data=clean", "data.splits.train=abc"], "data.splits.train", "must be an integer"),
    ("data", ["data=clean", "data.sampling.mode=random"], "data.sampling.mode", "must be one of uniform, grid"),
    ("data", ["data=clean", "+data.sampling.closed_loop.shares=0.3"], "data.sampling.closed_loop.shares", "unknown key"),
    ("data", ["data=clean", "data.sampling.closed_loop.controller.chi=abc"],
     "data.sampling.closed_loop.controller.chi", "must be a number"),
    ("data", ["data=clean", "data.follower.probability=half"], "data.follower.probability", "must be a number"),
    ("data", ["render.px_per_unit=abc"], "render.px_per_unit", "must be a number"),
    ("data", ["render.colors.leader=white"], "render.colors.leader", "must be a list"),
    ("data", ["+render.height=60"], "render.height", "unknown key"),  # the image size is the arena's
    ("data", ["occlusions.heavy.blobs=many"], "occlusions.heavy.blobs", "must be a list"),
    ("data", ["+occlusions.heavy.density=2"], "occlusions.heavy.density", "unknown key"),
    ("train", ["data=clean", "model.lr=fast"], "model.lr", "must be a number"),  # a target read from its source
    ("train", ["data=clean", "model.filters=wide"], "model.filters", "non-empty list of integers"),
    ("train", ["data=clean", "+model.nll_weight=1"], "model.nll_weight", "unknown key"),
    ("train", ["data=clean", "datamodule.batch_size=1.5"], "datamodule.batch_size", "must be an integer"),
    ("train", ["data=clean", "+trainer.max_epoch=3"], "trainer.max_epoch", "unknown key"),
    ("train", ["data=clean", "uncertainty_eval.gate_px=abc"], "uncertainty_eval.gate_px", "must be a number"),
    ("train", ["data=clean", "+uncertainty_eval.gate=3"], "uncertainty_eval.gate", "unknown key"),
    ("experiments", ["experiment=robustness_sweep", "experiment.eps=big"], "experiment.eps", "must be a list"),
    ("experiments", ["experiment=robustness_sweep", "+experiment.nagents=5"], "experiment.nagents", "unknown key"),
    ("experiments", ["experiment=robustness_sweep", "controllers.cbf.alpha=abc"], "controllers.cbf.alpha",
     "must be a number"),
    ("experiments", ["+controllers.smooth.alpha=1"], "controllers.smooth.alpha", "unknown key"),
    ("experiments", ["disturbances.adversarial.eps=abc"], "disturbances.adversarial.eps", "must be a number"),
    ("dagger", ["dagger.collect.controller.chi=abc"], "dagger.collect.controller.chi", "must be a number"),
]


@pytest.mark.parametrize("config,overrides,field,reason", SCHEMA_CASES,
                         ids=[" ".join(c[1]) for c in SCHEMA_CASES])
def test_every_node_is_checked_at_composition(config, overrides, field, reason):
    from pipeline.preflight import preflight

    hydra_rejects = not overrides[-1].startswith("+") and "unknown key" in reason  # no such key to override
    if not hydra_rejects:
        with pytest.raises(ConfigError) as err:
            compose(config, overrides)
        assert err.value.field == field and reason in err.value.reason, str(err.value)
        assert "\n" not in str(err.value)
    with pytest.raises(ConfigError) as err:  # what every stage's command line runs first
        preflight(config, overrides)
    assert err.value.field == field and reason in err.value.reason and "\n" not in str(err.value), str(err.value)


WRONG = ("§not-a-value§", 12345, [["x"]], {"not_a_key": ["x"]})


def _leaves(value, tp, path):
    """(path, annotation) of every value under a node's keyword: into nested dataclasses and lists of them."""
    import dataclasses
    import types
    import typing

    union = typing.get_origin(tp) in (typing.Union, types.UnionType)
    opts = [a for a in typing.get_args(tp) if a is not type(None)] if union else [tp]
    dc = next((o for o in opts if dataclasses.is_dataclass(o)), None)
    if dc is not None and isinstance(value, dict):
        hints = typing.get_type_hints(dc)
        for k, v in value.items():
            yield from _leaves(v, hints[k], f"{path}.{k}")
        return
    item = typing.get_args(tp)[0] if typing.get_origin(tp) is list and typing.get_args(tp) else None
    if item is not None and dataclasses.is_dataclass(item) and isinstance(value, list):
        for i, v in enumerate(value):
            yield from _leaves(v, item, f"{path}[{i}]")
        return
    yield path, tp


def _set(cfg, path, value):
    from omegaconf import OmegaConf, open_dict

    key = path.replace("[", ".").replace("]", "")
    with open_dict(cfg):
        OmegaConf.update(cfg, key, value, merge=False, force_add=True)


SCHEMA_CONFIGS = [("simulate", []), ("simulate", ["init=grid", "disturbance=adversarial", "controller=cbf"]),
                  ("simulate", ["init=random", "disturbance=alternating", "controller=smooth"]),
                  ("simulate", ["init=near_k", "disturbance=gaussian", "scene=authors_code"]),
                  ("data", ["data=closed_loop", "render=authors_code"]), ("train", ["data=clean"]),
                  ("dagger", [])] + [("experiments", [f"experiment={e}"])
                                     for e in sorted(p.stem for p in (CONF_DIR / "experiment").glob("*.yaml"))]


@pytest.mark.parametrize("config,overrides", SCHEMA_CONFIGS, ids=[" ".join([c, *o]) for c, o in SCHEMA_CONFIGS])
def test_every_key_of_every_target_node_is_checked(config, overrides):
    """In every composed config, every `_target_` node rejects a key its target does not take, and every
    annotated keyword (nested dataclass fields included) rejects a value of the wrong type: one line naming it.
    (Targets outside the project, read from their source, are checked by key; their values by the target.)"""
    import pickle

    from omegaconf import OmegaConf

    from pipeline.config import META_KEYS, _walk, check_schema, plain_value, signature
    from pipeline.schema import check_value

    cfg = compose(config, overrides)
    frozen = pickle.dumps(cfg)  # each mutation on its own copy (unpickled: 7x faster than a deep copy)
    nodes = [(p, n) for p, n in _walk(cfg) if isinstance(n.get("_target_"), str)]
    assert nodes
    n_values = 0
    for path, node in nodes:
        parent, _, leaf = path.rpartition(".")
        if OmegaConf.is_interpolation(OmegaConf.select(cfg, parent) if parent else cfg, leaf):
            continue  # `controllers.hybrid: ${controller}`: checked as the node it points to
        seen = (path, repr({k: plain_value(node, k) for k in node.keys()}))
        if seen in _NODES_CHECKED:  # the same node at the same place in an earlier config of this process
            n_values += _NODES_CHECKED[seen]
            continue
        checked_before = n_values
        params = signature(node["_target_"])
        assert params is not None, path  # neither `**kwargs` nor unreadable: every key is checked
        bad = pickle.loads(frozen)
        _set(bad, f"{path}.not_a_keyword", 1)
        with pytest.raises(ConfigError) as err:
            check_schema(bad)
        assert err.value.field == f"{path}.not_a_keyword" and "unknown key" in err.value.reason, str(err.value)
        for key in node.keys():
            value = plain_value(node, key)  # `...`: a `${hydra:...}` value, resolved in a run only
            if key in META_KEYS or params.get(key) is None or value is ... or (
                    isinstance(value, dict) and "_target_" in value):
                continue
            for where, tp in _leaves(value, params[key], f"{path}.{key}"):
                wrong = next((w for w in WRONG if _rejects(check_value, w, tp)), None)
                if wrong is None:
                    continue  # the annotation accepts anything
                bad = pickle.loads(frozen)
                _set(bad, where, wrong)
                with pytest.raises(ConfigError) as err:
                    check_schema(bad)
                assert err.value.field.startswith(where) and "\n" not in str(err.value), (where, str(err.value))
                n_values += 1
        _NODES_CHECKED[seen] = n_values - checked_before
    assert n_values >= len(nodes)


# (path, resolved values) -> values checked: most nodes (controller, scene, sim, camera ...) are the same in many
# composed configs; each distinct one is checked once per test process, in whichever config meets it first
_NODES_CHECKED: dict[tuple[str, str], int] = {}


def _conf_targets() -> list[str]:
    import re

    return sorted({m for f in CONF_DIR.rglob("*.yaml") for m in re.findall(r"_target_:\s*([\w.]+)", f.read_text())})


def test_every_project_target_imports_without_torch():
    """Every target of this project is imported to read its signature (no source parsing): none may import torch.
    A torch class takes a typed spec instead (`MapSpec`, `DataModuleSpec`, `PolicySpec`), so its node is checked
    like any other before torch loads. Before, six torch modules were named targets, read from their source text."""
    modules = sorted({t.rpartition(".")[0] for t in _conf_targets() if t.startswith("pipeline.")})
    code = f"import importlib, sys; [importlib.import_module(m) for m in {modules!r}]; print('torch' in sys.modules)"
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert proc.stdout.strip() == "False", proc.stderr[-2000:]


def test_a_torch_class_takes_its_spec_and_saves_its_fields():
    """The network of a spec keeps the spec's fields as its hyperparameters, so a saved map (or policy) is rebuilt
    from them with the same layers; a bad value is one error naming the key, checked by the spec."""
    import dataclasses

    import torch

    from pipeline.learned.network import VelocityPolicy
    from pipeline.learned.spec import PolicySpec
    from pipeline.perception.spec import MapSpec
    from pipeline.train.module import PerceptionMap

    for cls, spec in ((PerceptionMap, MapSpec(filters=(4, 8), position_head="keypoint")),
                      (VelocityPolicy, PolicySpec(filters=(4, 8), hidden=8))):
        torch.manual_seed(0)
        net = cls(spec)
        assert dict(net.hparams) == dataclasses.asdict(spec)
        torch.manual_seed(0)
        again = cls.of(**net.hparams)
        assert all(torch.equal(a, b) for a, b in zip(net.state_dict().values(), again.state_dict().values()))
    with pytest.raises(ConfigError, match="model.position_head"):  # checked by the spec
        PerceptionMap.of(position_head="grid")


def test_another_packages_keys_are_read_without_importing_it():
    """Lightning's targets: their keys from source (its import loads torch), followed through re-exports."""
    code = ("import sys; from pipeline.config import signature; s = signature('lightning.Trainer'); "
            "print('max_epochs' in s, 'dirpath' in signature('lightning.pytorch.callbacks.ModelCheckpoint'), "
            "'torch' in sys.modules)")
    proc = subprocess.run([sys.executable, "-c", code], cwd=REPO_ROOT, capture_output=True, text=True, timeout=300)
    assert proc.stdout.split() == ["True", "True", "False"], proc.stderr[-2000:]


def _rejects(check_value, value, tp) -> bool:
    try:
        check_value(value, tp, "x")
    except ConfigError:
        return True
    return False


# ------------------------------------------------------------------ the code's defaults are the YAML's
def _plain(x):
    import dataclasses

    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return {f.name: _plain(getattr(x, f.name)) for f in dataclasses.fields(x)}
    if isinstance(x, list | tuple):
        return [_plain(v) for v in x]
    if isinstance(x, dict):
        return {k: _plain(v) for k, v in x.items()}
    return x


def _code_defaults(cls) -> dict:
    """Keyword -> default of a dataclass (its fields) or a class / function (its signature)."""
    import dataclasses
    import inspect

    if dataclasses.is_dataclass(cls):
        out = {}
        for f in dataclasses.fields(cls):
            if f.default is not dataclasses.MISSING:
                out[f.name] = f.default
            elif f.default_factory is not dataclasses.MISSING:
                out[f.name] = f.default_factory()
        return out
    return {n: p.default for n, p in inspect.signature(cls).parameters.items() if p.default is not p.empty}


def _yaml(rel: str) -> dict:
    return yaml.safe_load((REPO_ROOT / "conf" / rel).read_text())


def _differences(node: dict, cls, *, skip=()) -> list[str]:
    """Keys of a YAML node whose value is not the code's default (`name`: the target's keyword, else its label
    `cls.name`)."""
    from pipeline.render.camera import DEFAULT_COLORS

    defaults = _code_defaults(cls)
    if cls.__name__ == "Camera":  # colors=None draws DEFAULT_COLORS
        defaults["colors"] = DEFAULT_COLORS
    out = []
    for key, value in node.items():
        if key in ("_target_", "defaults", "hydra", *skip):  # hydra: Hydra's own settings (run dirs)
            continue
        if key == "name" and key not in defaults:
            want = getattr(cls, "name", None)
        else:
            assert key in defaults, f"{cls.__name__} has no default for {key}"
            want = defaults[key]
        if _plain(want) != _plain(value):
            out.append(f"{key}: YAML {value!r}, code {_plain(want)!r}")
    return out


def _target(node: dict):
    from pipeline.config import resolve

    module, _, name = node["_target_"].rpartition(".")
    return resolve(f"{module}:{name}")


DEFAULT_NODES = ["sim/default.yaml", "camera/default.yaml", "controller/hybrid.yaml", "controller/smooth.yaml",
                 "controller/cbf.yaml", "disturbance/none.yaml", "disturbance/gaussian.yaml",
                 "disturbance/alternating.yaml", "disturbance/adversarial.yaml", "disturbance/pixel_attack.yaml",
                 "disturbance/worst_cloud.yaml", "init/points.yaml", "init/grid.yaml",
                 "init/random.yaml", "init/near_k.yaml", "scene/default.yaml", "render/default.yaml",
                 "occlusion/none.yaml", "model/default.yaml", "datamodule/default.yaml"]


@pytest.mark.parametrize("rel", DEFAULT_NODES)
def test_code_defaults_are_the_yaml_of_the_default_option(rel):
    """What runs is the YAML: a target built without that key (a test, a notebook, `Scene()`) gets the same value."""
    node = _yaml(rel)
    assert _differences(node, _target(node)) == []


def test_nested_and_stage_defaults_are_the_yaml():
    from pipeline.control import Barrier, Obstacle, Scene
    from pipeline.data.recipe import ClosedLoopSampling, Sampling
    from pipeline.errormap.settings import ErrorMapSettings
    from pipeline.train.settings import UncertaintyEval

    scene = _yaml("scene/default.yaml")  # the nested nodes, key for key
    assert _differences(scene["barrier"], Barrier) == []
    assert _plain(Scene().obstacles) == scene["obstacles"]
    assert _differences(scene["obstacles"][0], Obstacle, skip=("center", "radius")) == []  # those two: required
    assert _plain(Scene().arena) == scene["arena"] and _plain(Scene().barrier) == scene["barrier"]
    sampling = _yaml("sampling/closed_loop.yaml")
    # controller: the composed controller node, its guard set off (the datasets sample the literal rule)
    assert _differences(sampling["closed_loop"], ClosedLoopSampling, skip=("controller",)) == []
    assert sampling["closed_loop"]["controller"] == {"guard": False}
    assert _differences(sampling, Sampling, skip=("mode", "closed_loop")) == []  # mode: what this option picks
    uncertainty = _yaml("train.yaml")["uncertainty_eval"]
    assert _target(uncertainty) is UncertaintyEval and _differences(uncertainty, UncertaintyEval) == []
    errormap = _yaml("errormap.yaml")
    assert _differences(errormap, ErrorMapSettings) == []
    assert set(errormap) - {"defaults", "hydra"} == set(_code_defaults(ErrorMapSettings))  # every setting in the YAML


def test_experiment_settings_and_simulate_defaults_are_the_yaml():
    """The experiments stage's root keys, and `simulate()`'s settings: those of conf/sim and conf/camera."""
    import inspect

    from pipeline.experiments.settings import ExperimentSettings
    from pipeline.sim import CameraSettings, SimSettings, simulate

    experiments = _yaml("experiments.yaml")
    assert _differences(experiments, ExperimentSettings) == []
    assert set(experiments) - {"defaults", "hydra"} == set(_code_defaults(ExperimentSettings))
    sim, camera = _yaml("sim/default.yaml"), _yaml("camera/default.yaml")
    assert _differences(sim, SimSettings) == [] and _differences(camera, CameraSettings) == []
    defaults = inspect.signature(simulate).parameters
    assert defaults["sim"].default == SimSettings() and defaults["camera"].default == CameraSettings()


# ------------------------------------------------------------------------------- bad input, every stage
AFILE = "<a_file>"  # replaced by a path to a plain file of the test's own tmp_path


def _bad_cases():
    afile = AFILE
    return [
        ("pipeline.simulate", ["camera.p_fail=abc"], "camera.p_fail"),
        ("pipeline.simulate", ["init=grid", "init.nx=abc"], "init.nx"),
        ("pipeline.simulate", ["init=near_k", "init.a_range=[-10.0,-40.0]"], "init.a_range"),
        ("pipeline.simulate", ["init.points=[[0.5,0.5]]"], "init.points"),
        ("pipeline.simulate", ["scene.target=[80.0,0.0]"], "scene.target"),
        ("pipeline.simulate", ["scene.obstacles.0.center=[0.0,45.0]"], "scene.obstacles[0].center"),
        ("pipeline.simulate", ["scene.obstacles.0.radius=big"], "scene.obstacles[0].radius"),
        ("pipeline.simulate", ["scene.barrier.kind=cubic"], "scene.barrier.kind"),
        ("pipeline.simulate", ["sim.model=hourly"], "sim.model"),
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
        ("pipeline.paper", ["bracket=[nope]"], "bracket[0]"),
        ("pipeline.paper", ["bracket=[paper]", "bracket_map=clean_keypoint"], "bracket_map"),  # not among certify's maps
        ("pipeline.bracket", ["tuning=nope"], "tuning"),
    ]


def _fresh_process(module, args) -> bool:
    """The first case of each stage runs in a fresh interpreter (`python -m`), the others in this one (`run_cli`:
    the same entry, a second of start-up less each)."""
    return next(a for m, a, _ in _bad_cases() if m == module) == args


@pytest.mark.parametrize("module,args,field", _bad_cases(), ids=[f"{m.split('.')[1]} {' '.join(a)}"
                                                                  for m, a, _ in _bad_cases()])
def test_bad_input_is_one_line_and_exit_2_before_any_work(tmp_path, module, args, field):
    cli = _cli if _fresh_process(module, args) else run_cli
    out = tmp_path / "out"
    afile = tmp_path / "a_file"
    afile.write_text("x")
    args = [a.replace(AFILE, str(afile)) for a in args]
    extra = [] if any(a.startswith("paths.") for a in args) else [f"paths.root_dir={out}"]
    extra += {"pipeline.experiments": ["perception=oracle"], "pipeline.simulate": ["plot=false"]}.get(module, [])
    proc = cli(module, *args, *extra, f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path / 'sweep'}")
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
    from pipeline.data.stage import run as data_run
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
    from pipeline.data.stage import run as data_run
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
    `make paper` again: every figure and the lock file keep the paper's own map id. (And issue 46: the paper
    folder's index.md links every file the run wrote.)"""
    root = tmp_path / "root"
    data = ["data.splits.train=256", "data.splits.val=32", "data.splits.test=32"]
    q = lambda xs: "[" + ",".join(f"'{x}'" for x in xs) + "]"  # noqa: E731 - quoted override list
    args = [f"paths.root_dir={root}", "datasets=[clean]", "maps=[clean_keypoint]", "errormaps=[clean_keypoint]",
            "experiments=[perception_closeness]", f"args.data={q(data)}",
            f"args.train={q(['trainer=debug', 'eval_levels=[none]', *data])}",
            f"args.errormap={q(['grid.step=4.0', 'occlusion_levels=[none]', 'train_samples=64'])}",
            "certify=[clean_keypoint]",
            f"args.certify={q(['cell=2.0', 'region=[[30.0,46.0],[-6.0,6.0]]', 'kappas=[0.0]', 'samples=2', 'pgd_cells=2', 'pgd_steps=2'])}",
            "bracket=[wide_barrier]", "bracket_map=clean_keypoint",
            f"args.bracket={q(['bracket.controllers=[hybrid]', 'bracket.cell=4.0', 'bracket.start_cell=20', 'bracket.eps=[0.1]', 'bracket.n_bisect=0', 'bracket.n_dirs=8', 'bracket.tail=4', 'bracket.lookahead=4', 'bracket.commit=4', 'sim.horizon=8', 'bracket.refine=0', 'bracket.funnel_split=0'])}",
            f"args.experiments={q(['debug=tiny'])}", "learned=[imitate]",
            f"args.imitate={q(['imitation.agents=2', 'imitation.rounds=0', 'imitation.epochs=1', 'imitation.max_frames=4', 'model.hidden=8'])}",
            f"args.learned={q(['learned.agents=2', 'learned.near_k=2', 'learned.agents_list=[hybrid,imitated]', 'learned.attack_list=[imitated]', 'learned.clouds_list=[]', 'learned.cloud_attack_list=[]', 'learned.attack_steps=1', 'sim.horizon=1', 'learned.grid=[5,4]'])}",
            f"hydra.run.dir={tmp_path / 'run1'}"]
    first = _cli("pipeline.paper", *args, timeout=900)
    assert first.returncode == 0, first.stderr[-3000:]
    lock = yaml.safe_load((root / "outputs" / "paper" / "paper.lock.yaml").read_text())
    map_folder = lock["maps"]["clean_keypoint"]["folder"]
    side = run_cli("pipeline.train", "data=clean", "model=keypoint", "trainer=debug",  # in this process: no imports
                   "datamodule.limit_train_samples=64", "eval_levels=[none]", *data, f"paths.root_dir={root}",
                   f"hydra.run.dir={tmp_path / 'side'}")
    assert side.returncode == 0, side.stderr[-2000:]
    assert len(list((root / "outputs" / "models").glob(f"{map_folder.rsplit('-', 1)[0]}-*"))) == 2
    figure = next((root / "outputs" / "paper").glob("fig*.png"))
    drawn = figure.stat().st_mtime_ns
    # nothing to run: the orchestrator in this process (run_cli; a stage it started would be a fresh process)
    again = run_cli("pipeline.paper", *args[:-1], f"hydra.run.dir={tmp_path / 'run2'}")
    assert again.returncode == 0, again.stderr[-3000:]
    # nothing changed for the paper (issue 32): no stage is started, no figure redrawn
    assert again.stdout.count("; not started") == 8, again.stdout[-3000:]  # the learned stage's two too
    assert "certify: up to date" in again.stdout  # the certified error map the paper computed is the one expected
    assert figure.stat().st_mtime_ns == drawn
    lock2 = yaml.safe_load((root / "outputs" / "paper" / "paper.lock.yaml").read_text())
    assert lock2["maps"]["clean_keypoint"]["folder"] == map_folder
    assert lock2["experiments"] == lock["experiments"]  # nothing recomputed with the side map
    assert lock2["certified"] == lock["certified"] and lock["certified"]["clean_keypoint"]["folder"]
    assert lock2["bracket"] == lock["bracket"]  # the bracket with the tuning, certified with the paper's own bound
    bracket = json.loads((root / "outputs" / "bracket" / lock["bracket"]["wide_barrier"]["folder"] /
                          "manifest.json").read_text())
    assert bracket["recipe"]["error_map_ref"] == lock["certified"]["clean_keypoint"]["folder"]
    assert bracket["recipe"]["scene"]["barrier"]["gain"] == 300  # conf/tuning/wide_barrier.yaml reached the run
    assert "map ε̄: certified" in (root / "outputs" / "paper" / "tab_bracket_wide_barrier.md").read_text()
    assert lock2["learned"] == lock["learned"] and set(lock["learned"]) == {"policy imitate", "comparison"}
    learned = yaml.safe_load((root / "outputs" / "models" / lock["learned"]["policy imitate"]["folder"] /
                              "manifest.json").read_text())  # its trunk: the paper's own map
    assert learned["config"]["imitation"]["trunk_from"] == map_folder
    table = (root / "outputs" / "paper" / "tab_learned.md").read_text()
    assert "| imitated | near K, pixel attack κ=1 | 2 |" in table
    index = (root / "outputs" / "paper" / "index.md").read_text()
    assert map_folder in index and "paper.lock.yaml" in index
    # index.md is written last and links every file of the folder (the profile used to be written after it)
    paper = root / "outputs" / "paper"
    files = {str(p.relative_to(paper)) for p in paper.rglob("*") if p.is_file()} - {"index.md"}
    assert {"paper.profile.md", "paper.profile.json", "tab_learned.md", "tab_bracket_wide_barrier.md"} <= files
    links = index_links(paper / "index.md")
    assert files <= links, sorted(files - links)


def test_schema_rejects_wrong_types_in_instantiated_scenarios():
    """A scenario is built from its node (`experiment._target_`): its typed signature is the node's schema."""
    from pipeline.config import build
    from pipeline.experiments.paper.theory import RobustnessSweep

    node = {"_target_": "pipeline.experiments.paper.theory.RobustnessSweep", "id": "x", "title": "x"}
    assert isinstance(build(node, "experiment"), RobustnessSweep)
    with pytest.raises(ConfigError, match="experiment.eps") as err:
        build({**node, "eps": "big"}, "experiment")
    assert err.value.field == "experiment.eps" and "\n" not in str(err.value)
    with pytest.raises(ConfigError, match="experiment.epsilon: unknown key"):
        build({**node, "epsilon": [0.1]}, "experiment")
    with pytest.raises(TypeError):
        RobustnessSweep(id="x", title="x", epsilon=[0.1])  # no **kwargs: a typo is not a default


def test_the_code_hashed_into_each_id_covers_the_modules_that_compute_it():
    """Lineage: an output's id hashes the code that computes its bytes. Every experiment bundle's scenario module is
    in the experiments' code (`experiments/multi/unicycle` was missing: a change to the unicycle runs kept their cached
    results), and every `pipeline.perception` module the network imports is in the maps' code (the keypoint head)."""
    import ast

    from pipeline import identity
    from pipeline.experiments.stage import COMPUTE_CODE

    def covered(module: str, code) -> bool:
        path = module.removeprefix("pipeline.").replace(".", "/")
        return any(path == c or path.startswith(c + "/") for c in code)

    for f in sorted((CONF_DIR / "experiment").glob("*.yaml")):
        target = yaml.safe_load(f.read_text())["experiment"].get("_target_")
        if target is None:  # a bundle that extends another (its defaults): the other's target
            continue
        assert covered(target.rsplit(".", 1)[0], COMPUTE_CODE), (f.name, target)
    tree = ast.parse((REPO_ROOT / "pipeline" / "perception" / "network.py").read_text())
    imported = {n.module for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module
                and n.module.startswith("pipeline.perception")}
    assert imported and all(covered(m, identity.MAP_CODE) for m in imported), imported
    assert all(covered(m, identity.dataset_code({"sampling": {"mode": "closed_loop", "closed_loop": {"map": "x"}}}))
               for m in imported), imported


@pytest.mark.parametrize("override, field", [("certify=[occluded_keypoint]", "certify"),
                                             ("errormaps=[unicycle_pose]", "errormaps"), ("args.certify=3", "args.certify")])
def test_paper_lists_only_maps_it_builds(override, field):
    """The certify and errormap stages of make paper take maps of its `maps` list: one line naming the key."""
    from pipeline.paper import check
    from pipeline.preflight import preflight

    with pytest.raises(ConfigError) as err:
        preflight("paper", ["maps=[clean_keypoint]", "datasets=[clean]", "errormaps=[clean_keypoint]", override], check)
    assert err.value.field == field and "\n" not in str(err.value)


@pytest.mark.parametrize("overrides,field,reason", [
    (["model=nope"], "model", "unknown option 'nope'"),
    (["model.lrr=0.1"], "model.lrr", "unknown key"),
    (["trainer.max_epochs=[1"], "overrides", ""),
])
def test_compose_turns_hydras_errors_into_one_config_error(overrides, field, reason):
    """`compose` from Python (the paper DAG, the environment, dagger) gives Hydra's composition errors as one
    `ConfigError` line; before, each caller turned them into one (three copies) or let Hydra's exception through."""
    with pytest.raises(ConfigError) as err:
        compose("train", overrides)
    assert err.value.field == field and reason in err.value.reason and "\n" not in str(err.value)


def test_compose_composes_once_and_every_caller_gets_its_own_copy(monkeypatch):
    """`pipeline.config.compose` runs Hydra once per name and group choices in a process; values (`key=value`) are set
    on a deep copy by Hydra's own last step, so every call equals Hydra's composition of the same overrides byte for
    byte, a caller's edit never reaches the next call, and an error is raised every time, never kept."""
    import hydra
    from omegaconf import OmegaConf, open_dict

    from pipeline import config

    calls = []
    real = hydra.compose
    monkeypatch.setattr(hydra, "compose", lambda **kw: calls.append(kw) or real(**kw))
    config._composed.cache_clear()

    def theirs(overrides):
        with hydra.initialize_config_dir(version_base="1.3", config_dir=str(CONF_DIR)):
            return OmegaConf.to_yaml(real(config_name="simulate", overrides=overrides))

    a = config.compose("simulate", ["sim.horizon=7.0"])
    with open_dict(a):  # edits, a new key among them, stay in this copy
        a.sim.horizon, a.controller.extra = 99.0, None
    b = config.compose("simulate", ["sim.horizon=7.0"])
    assert len(calls) == 1 and b.sim.horizon == 7.0 and "extra" not in b.controller and b is not a
    jobs = [["sim.horizon=8.0", "paths.root_dir=/tmp/r1"], ["controller.chi=1.5", "sim.seed=3"], []]
    for job in jobs:  # values only: no composition more, and Hydra's config
        assert OmegaConf.to_yaml(config.compose("simulate", job)) == theirs(job) and len(calls) == 1, job
    for job in (["controller=smooth", "sim.horizon=8.0"], ["controller=smooth"], ["+sim.extra=1", "sim.horizon=2.0"]):
        assert OmegaConf.to_yaml(config.compose("simulate", job, check=False)) == theirs(job), job
    assert len(calls) == 3  # a group choice composes (once), and an added key goes to Hydra with every override
    for _ in range(2):
        for bad in (["sim.horizonn=1"], ["controller=nope"], ["sim.horizon=[1"]):
            with pytest.raises(ConfigError):
                config.compose("simulate", bad)
    assert len(calls) == 5  # each bad group choice tried by Hydra each time (the bad value and parse: no composition)
