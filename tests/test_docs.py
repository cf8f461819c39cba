"""Docs that cannot rot (issue 21): every shell command in README.md and docs/*.md, and every Python snippet.

Each shell command (a `python -m pipeline.<stage> ...` or `make <target> ...` line of a ```bash / ``` block,
or quoted inline) is
composed and checked as the stage's preflight does, every job of a sweep included (`pipeline.preflight.preflight`:
Hydra's parse, unknown keys, values, output paths, the stage's own check) in an empty root, where the only error
allowed is a missing upstream output ("... not built; run ..."). The cheap ones also run for real, at a tiny
size (the simulate demos, with a few starts). A line that needs an
extra that is not installed (a Hydra launcher, the Optuna sweeper) is composed without it, or skipped when
nothing is left. Every ```python block runs as written, in a sandbox where recipe names mean tiny outputs
built once (`debug=tiny`); a block marked `<!-- docs-test: signatures -->` lists signatures, and each listed
function must exist with the listed parameters.
"""

from __future__ import annotations

import importlib.util
import inspect
import re
import shlex
from pathlib import Path

import pytest

from pipeline.cli import REPO_ROOT, compose
from pipeline.config import resolve
from pipeline.errors import PipelineError
from pipeline.preflight import _expand, preflight

DOCS = [REPO_ROOT / "README.md", *sorted((REPO_ROOT / "docs").glob("*.md"))]
FENCE = re.compile(r"^(?:<!-- docs-test: (?P<mark>[\w-]+) -->\n)?```(?P<lang>\w*)\n(?P<body>.*?)^```", re.S | re.M)
PLUGINS = {"hydra/launcher=joblib": "hydra_plugins.hydra_joblib_launcher",
           "hydra/launcher=submitit_slurm": "hydra_plugins.hydra_submitit_launcher",
           "hydra/launcher=submitit_local": "hydra_plugins.hydra_submitit_launcher",
           "hparams_search=perception_optuna": "hydra_plugins.hydra_optuna_sweeper"}


def _stages() -> dict[str, tuple[str, str | None]]:
    """`python -m <module>` -> (config name, check) of every stage, read from its `stage_main(...)` line."""
    found = {}
    for f in (REPO_ROOT / "pipeline").rglob("*.py"):
        for m in re.finditer(r'stage_main\("(\w+)", run="[^"]+"(?:, check="([^"]+)")?\)', f.read_text()):
            mod = ".".join(f.relative_to(REPO_ROOT).with_suffix("").parts).removesuffix(".__main__")
            found[mod] = (m.group(1), m.group(2))
    return found


STAGES = _stages()


def _blocks(lang: set[str]):
    for md in DOCS:
        text = md.read_text()
        for m in FENCE.finditer(text):
            if m.group("lang") in lang:
                yield md, text[:m.start()].count("\n") + 1, m.group("mark"), m.group("body")


def _commands() -> list[tuple[str, list[str]]]:
    """(where, words) of every `python -m ...` / `make ...` line (continuations joined, comments dropped), and
    of every such command quoted inline in the prose (but templates: a `<placeholder>` other than `name-<id>`)."""
    found = []
    for md, line_no, _, body in _blocks({"", "bash", "sh"}):
        for i, line in enumerate(body.replace("\\\n", " ").splitlines()):
            if line.lstrip().startswith(("python ", "make")):
                found.append((f"{md.name}:{line_no + 1 + i}", shlex.split(line, comments=True)))
    for md in DOCS:
        text = FENCE.sub(lambda m: "\n" * m.group(0).count("\n"), md.read_text())
        for m in re.finditer(r"`((?:python -m pipeline|make )[^`]*)`", text):
            if not re.search(r"<\w+>", m.group(1).replace("-<id>", "")):  # `experiment=<id>`: a template
                found.append((f"{md.name}:{text[:m.start()].count(chr(10)) + 1}", shlex.split(m.group(1))))
    out, seen = [], set()
    for where, words in found:
        if words and tuple(words) not in seen:
            seen.add(tuple(words))
            out.append((where, words))
    return out


def _make_recipe(target: str) -> list[str] | None:
    """The words of `make <target>`'s `$(PY) -m ...` recipe line (None: not a python stage, e.g. pytest)."""
    text = (REPO_ROOT / "Makefile").read_text()
    rule = re.search(rf"^{re.escape(target)}:([^\n#]*)(?:##[^\n]*)?\n((?:\t[^\n]*\n)*)", text, re.M)
    assert rule, f"make {target}: no such target in the Makefile"
    for line in rule.group(2).splitlines():
        if line.strip().startswith("$(PY) -m pipeline."):
            return shlex.split(line.replace("$(PY)", "python").replace("$(ARGS)", ""))
    deps = rule.group(1).split()
    if deps and deps[0] != "$(STAMP)":  # an alias (`run: paper`)
        return _make_recipe(deps[0])
    return None


def _as_python(words: list[str]) -> list[str] | None:
    if words[0] != "make":
        return words
    recipe = _make_recipe(words[1])
    if recipe is None:
        return None
    args = [a.split("=", 1)[1] for a in words[2:] if a.startswith("ARGS=")]
    return recipe + [w for a in args for w in shlex.split(a)]


COMMANDS = _commands()
NOT_BUILT = re.compile(r"not built|is not built")


def _has(module: str) -> bool:
    try:
        return importlib.util.find_spec(module) is not None
    except ModuleNotFoundError:  # its parent package (hydra_plugins) is not there either
        return False


def _without_missing_plugins(args: list[str]) -> tuple[list[str], list[str]]:
    """The overrides without those whose Hydra plugin is not installed (and the launcher's own keys)."""
    missing = [a for a in args if a in PLUGINS and not _has(PLUGINS[a])]
    launcher = any(m.startswith("hydra/launcher=") for m in missing)
    return [a for a in args if a not in missing and not (launcher and a.startswith("hydra.launcher."))], missing


@pytest.fixture(scope="module")
def composed_once():
    """`pipeline.config.compose` memoised for this module's dry checks: the commands compose the same configs
    again and again (each stage's check recomputes the ids of its inputs); a copy of the cached config each time.
    And `lineage.expected_map_id` / `expected_dataset_id` (pure functions of conf/ and their arguments), memoised."""
    import pickle
    import sys

    from pipeline import config, lineage

    real, cache = config.compose, {}

    def compose(config_name, overrides=None, *, check=True):
        key = (config_name, tuple(overrides or ()), check)
        if key not in cache:
            try:
                cache[key] = pickle.dumps(real(config_name, overrides, check=check))
            except Exception as err:  # noqa: BLE001 - the same error each time
                cache[key] = err
        if isinstance(cache[key], Exception):
            raise cache[key]
        return pickle.loads(cache[key])

    def memoised(real_id):  # the ids a name means: the same few maps and datasets, again and again
        ids = {}

        def expected(name, overrides=()):
            key = (name, tuple(overrides))
            if key not in ids:
                try:
                    ids[key] = real_id(name, overrides)
                except Exception as err:  # noqa: BLE001 - the same error each time
                    ids[key] = err
            if isinstance(ids[key], Exception):
                raise ids[key]
            return ids[key]
        return expected

    swaps = [(real, compose), *((getattr(lineage, fn), memoised(getattr(lineage, fn)))
                                for fn in ("expected_map_id", "expected_dataset_id"))]
    patched = [(m, attr, old, new) for m in list(sys.modules.values()) for old, new in swaps
               for attr in ("compose", "expected_map_id", "expected_dataset_id") if getattr(m, attr, None) is old]
    for m, attr, _, new in patched:
        setattr(m, attr, new)
    yield
    for m, attr, old, _ in patched:
        setattr(m, attr, old)


def _check_key(words: list[str]):
    cmd = _as_python(words)
    return None if cmd is None else (cmd[2], tuple(sorted(_without_missing_plugins(cmd[3:])[0])))


CHECKS = [(w, c) for i, (w, c) in enumerate(COMMANDS)  # one check per distinct (stage, overrides) left to compose
          if _check_key(c) is None or _check_key(c) not in {_check_key(d) for _, d in COMMANDS[:i]}]


@pytest.mark.parametrize("where,words", CHECKS, ids=[w for w, _ in CHECKS])
def test_every_documented_command_composes_and_passes_its_preflight(where, words, tmp_path_factory, composed_once):
    cmd = _as_python(words)
    if cmd is None:  # make test / lint / setup: the target exists (checked above), it is not a stage
        return
    if cmd[:3] == ["python", "-m", "pipeline.bench"]:  # argparse, not Hydra: its areas exist
        from pipeline.bench import AREAS

        assert set(cmd[3:]) - {"--quick"} <= set(AREAS), f"{where}: {' '.join(words)}"
        return
    if cmd[:3] == ["python", "-m", "pipeline.docs_check"]:  # argparse, not Hydra: a report of the docs themselves
        assert importlib.util.find_spec("pipeline.docs_check") is not None, f"{where}: {' '.join(words)}"
        return
    assert cmd[:2] == ["python", "-m"] and cmd[2] in STAGES, f"{where}: {' '.join(words)}: not a stage command"
    name, check = STAGES[cmd[2]]
    args, missing = _without_missing_plugins([a.replace("<id>", "0123456789") for a in cmd[3:]])
    if cmd[2] == "pipeline.errormap":  # its __main__ reads `model=` as `maps=`
        from pipeline.errormap.__main__ import _alias_model_override

        args = _alias_model_override(args)
    if any(m.startswith("hparams_search=") for m in missing):  # the search space is the sweeper's config
        pytest.skip(f"{where}: needs {', '.join(missing)} (extra not installed)")
    try:
        root = tmp_path_factory.getbasetemp() / "docs_empty_root"  # one empty root: the cache's keys repeat
        jobs = preflight(name, [*args, f"paths.root_dir={root}"], resolve(check) if check else None)
    except PipelineError as err:
        assert NOT_BUILT.search(str(err)), f"{where}: `{' '.join(words)}` -> error: {err}"
        return
    assert jobs >= 1 or any(a.startswith(("--cfg", "--info", "--help")) for a in args), \
        f"{where}: {' '.join(words)} composed no job"


def _tiny(name: str, job: list[str]) -> list[str]:
    """A few starts instead of hundreds (what the command means stays: scene, controller, disturbance, model)."""
    init = compose(name, job).get("init")
    target = init["_target_"].rsplit(".", 1)[-1] if init is not None else ""
    return {"Grid": ["init.nx=3", "init.ny=2"], "NearK": ["init.n=3"], "Random": ["init.n=3"]}.get(target, [])


RUNS = [(w, c) for w, c in COMMANDS if c[:3] == ["python", "-m", "pipeline.simulate"]]  # a second or two each


@pytest.mark.parametrize("where,words", RUNS, ids=[w for w, _ in RUNS])
def test_the_cheap_documented_commands_run_at_a_tiny_size(where, words, tmp_path):
    from pipeline.simulate import run

    name, _ = STAGES[words[2]]
    args = [a for a in words[3:] if a != "-m"]
    for k, job in enumerate(_expand(args)):
        base = [*job, f"paths.root_dir={tmp_path}", f"paths.output_dir={tmp_path / str(k)}"]
        out = run(compose(name, [*base, *_tiny(name, job), *(["plot=false"] if k else [])]))
        assert out, f"{where}: {' '.join(words)}: job {job} returned nothing"


def test_the_readme_multirun_example_shows_a_difference(tmp_path, monkeypatch):
    """README's multirun sweep (issue 46), run as written at a tiny size: its jobs do not all score the same (with
    the default `init=points`, the paper's two starts, every job reached the target: a sweep that showed nothing).
    Through the `python -m` entry in this process (`run_cli`): a fresh interpreter's imports are not the claim."""
    import pandas as pd
    from shared import run_cli  # tests/shared.py

    sweeps = [w for where, w in RUNS if where.startswith("README.md") and "-m" in w[3:]]
    assert len(sweeps) == 1, sweeps
    args = sweeps[0][3:]
    tiny = _tiny("simulate", _expand([a for a in args if a != "-m"])[0])
    assert sweeps[0][1] == "-m", sweeps[0]
    monkeypatch.chdir(REPO_ROOT)
    proc = run_cli(sweeps[0][2], *args, *tiny, "plot=false", f"paths.root_dir={tmp_path}",
                   f"hydra.sweep.dir={tmp_path / 'sweep'}")
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = pd.read_csv(tmp_path / "sweep" / "summary.csv")
    assert len(summary) == 6 and (summary["status"] == "ok").all(), summary
    assert summary["success_rate"].nunique() > 1, summary[["overrides", "success_rate"]]


# ------------------------------------------------------------------------------------------ Python snippets
PY_BLOCKS = [(f"{md.name}:{line}", mark, body) for md, line, mark, body in _blocks({"python"})]


TINY_DATA = ["debug=tiny"]
TINY_MAP = ["debug=tiny", "trainer=debug", "eval_levels=[none]", "model.uncertainty=none"]  # seconds, not a minute


@pytest.fixture(scope="module")
def tiny_root(tmp_path_factory):
    """A tiny `clean` dataset and map (`debug=tiny`) in a root of their own, built once."""
    from pipeline.data.stage import run as data_run
    from pipeline.train.stage import run as train_run

    root = tmp_path_factory.mktemp("docs_root")
    data_run(compose("data", ["data=clean", *TINY_DATA, f"paths.root_dir={root}"]))
    train_run(compose("train", ["data=clean", *TINY_MAP, f"paths.root_dir={root}", f"paths.output_dir={root / 'run'}"]))
    return root


@pytest.fixture
def sandbox(tiny_root, monkeypatch, tmp_path):
    """Names mean the tiny outputs of `tiny_root`, as they mean the full ones on a user's machine."""
    from pipeline import lineage
    from pipeline.data import dataset
    from pipeline.perception import maps

    for fn, tiny in (("expected_dataset_id", TINY_DATA), ("expected_map_id", TINY_MAP)):
        real = getattr(lineage, fn)
        monkeypatch.setattr(lineage, fn, lambda name, overrides=(), real=real, tiny=tiny: real(name, [*overrides, *tiny]))
    monkeypatch.setattr(dataset, "default_datasets_dir", lambda: tiny_root / "data" / "datasets")
    monkeypatch.setattr(maps, "DEFAULT_MODELS_DIR", tiny_root / "outputs" / "models")
    monkeypatch.chdir(tmp_path)
    return tiny_root


@pytest.mark.parametrize("where,mark,body", PY_BLOCKS, ids=[w for w, _, _ in PY_BLOCKS])
def test_every_python_snippet_runs_as_written(where, mark, body, request):
    if mark == "signatures":
        return _check_signatures(where, body)
    assert mark is None, f"{where}: unknown docs-test mark {mark!r}"
    needs_outputs = re.search(r"open_dataset\(|load_perception_map\(|load_error_map\(\"", body)
    if needs_outputs:
        request.getfixturevalue("sandbox")
    exec(compile(body, where, "exec"), {"__name__": "__docs__"})  # noqa: S102 - the docs' own code


def _check_signatures(where: str, body: str) -> None:
    """`from m import a, b` lines, then `a(x, y=1) -> ...` lines: each `a` takes (at least) the listed names."""
    namespace: dict = {}
    exec(compile("\n".join(ln for ln in body.splitlines() if ln.startswith(("from ", "import "))), where, "exec"),
         namespace)
    listed = re.findall(r"^(\w+)\((.*?)\)\s*->", body, re.M)
    assert listed, f"{where}: a signatures block lists no `name(...) ->` line"
    for fn, params in listed:
        assert fn in namespace, f"{where}: {fn} is not imported by the block"
        names = [p.strip().split("=")[0].strip(" *") for p in params.split(",") if p.strip() not in ("", "*")]
        actual = inspect.signature(namespace[fn]).parameters
        assert [n for n in names if n not in actual] == [], f"{where}: {fn}{inspect.signature(namespace[fn])}"


def _same(shown, conf, where: str, path: str = "") -> None:
    """Every key and value the docs show is the config file's (the file may hold more keys)."""
    if isinstance(shown, dict):
        for k, v in shown.items():
            assert isinstance(conf, dict) and k in conf, f"{where}: {path}{k} is not in the file"
            _same(v, conf[k], where, f"{path}{k}.")
    else:
        assert shown == conf, f"{where}: {path[:-1]} is {conf!r} in the file, the docs say {shown!r}"


def test_a_documented_config_file_is_the_one_in_conf():
    import yaml

    shown = 0
    for md, line, _, body in _blocks({"yaml"}):
        first = body.splitlines()[0]
        if first.startswith("# conf/"):
            _same(yaml.safe_load(body), yaml.safe_load((REPO_ROOT / first[2:].strip()).read_text()),
                  f"{md.name}:{line} ({first[2:].strip()})")
            shown += 1
    assert shown >= 1


def test_where_outputs_go_names_every_output_folder():
    """README's "Where outputs go" lists each folder of conf/paths/default.yaml, the experiments' cache and the
    MLflow store (the logger's `tracking_uri`)."""
    import yaml

    section = (REPO_ROOT / "README.md").read_text().split("## Where outputs go", 1)[1].split("\n## ", 1)[0]
    paths = yaml.safe_load((REPO_ROOT / "conf" / "paths" / "default.yaml").read_text())
    folders = [v.replace("${paths.outputs_dir}", "outputs").replace("${paths.data_dir}", "data")
               for k, v in paths.items() if k.endswith("_dir") and isinstance(v, str) and "${paths." in v
               and k not in ("data_dir", "outputs_dir")]
    mlflow = compose("train", ["logger=mlflow"]).logger.mlflow
    store = mlflow.tracking_uri.removeprefix("sqlite:///").replace(compose("train").paths.outputs_dir, "outputs")
    folders += ["outputs/experiments", "outputs/runs", "outputs/multirun", store]
    assert [f for f in folders if f"`{f}" not in section] == [], section


def test_the_docs_test_finds_what_it_checks():
    """The extraction itself: it sees the README's commands and snippets (a test that finds nothing passes)."""
    wheres = {w.split(":")[0] for w, _ in COMMANDS}
    assert {"README.md", "control.md", "data.md", "train.md", "dagger.md"} <= wheres
    assert len(COMMANDS) > 30 and len(CHECKS) > 25 and len(PY_BLOCKS) >= 6 and len(RUNS) >= 8
    assert _as_python(["make", "run"])[:3] == ["python", "-m", "pipeline.paper"]
    assert _as_python(["make", "paper", "ARGS=debug=tiny seed=1"])[-2:] == ["debug=tiny", "seed=1"]
    assert _as_python(["make", "test"]) is None
    with pytest.raises(AssertionError, match="no such target"):
        _make_recipe("no-such-target")
    assert Path(inspect.getfile(preflight)).is_file()


def test_certify_md_opens_with_commands_that_work_after_make_run():
    """Issue 46: docs/certify.md's first command (`maps=clean`) failed after `make run`, which trains only the
    maps of conf/paper.yaml (its preflight passes in an empty root, where every map is "not built"). The commands of
    its first block certify maps `make run` builds, by name (a `name-id` pins a map some other run trained)."""
    import yaml

    built = yaml.safe_load((REPO_ROOT / "conf" / "paper.yaml").read_text())["maps"]
    default = yaml.safe_load((REPO_ROOT / "conf" / "certify.yaml").read_text())["maps"]
    first = next(body for md, _, _, body in _blocks({"", "bash", "sh"}) if md.name == "certify.md")
    commands = [shlex.split(ln, comments=True) for ln in first.replace("\\\n", " ").splitlines()
                if ln.lstrip().startswith("python -m pipeline.certify")]
    assert commands, first
    for words in commands:
        ref = next((w.split("=", 1)[1] for w in words if w.startswith("maps=")), default)
        assert ref in built, f"certify.md: `{' '.join(words)}`: {ref} is not among make run's maps {built}"
