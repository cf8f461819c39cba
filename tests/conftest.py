"""Shared test setup: headless plotting, few threads (the CI machine has 2 cores), Hydra state cleared."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("HYDRA_FULL_ERROR", "0")
# torch's OpenMP threads sleep instead of spinning while they wait: the numbers are the same, and on a busy
# machine (CI beside other jobs) a spinning thread steals the core its partner needs (5-8x slower steps)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")
# under pytest-xdist (`make test` runs one worker per core) each worker and its subprocesses use one thread:
# two workers of two threads each on two cores would only take turns
if os.environ.get("PYTEST_XDIST_WORKER"):
    os.environ.setdefault("OMP_NUM_THREADS", "1")

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

from pipeline.allocator import keep_freed_memory  # noqa: E402

keep_freed_memory()  # as every stage's process does (pipeline.allocator): the same bytes, fewer page faults

# `make test` (and CI) draws the same property-test examples every run, so a result does not depend on the
# day; `make test-explore` (HYPOTHESIS_PROFILE=explore) draws fresh ones each run (500 where a test sets no count) to look for new failures.
# A failure found there goes into the test as an `@example`.
settings.register_profile("ci", derandomize=True, print_blob=True)
settings.register_profile("explore", max_examples=500, print_blob=True)
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "ci"))


@pytest.fixture(autouse=True)
def _clear_hydra():
    from hydra.core.global_hydra import GlobalHydra

    GlobalHydra.instance().clear()
    yield
    GlobalHydra.instance().clear()


@pytest.fixture(scope="module")
def one_torch_thread():
    """Tiny batches: one torch thread is fastest (two on a shared 2-core machine can be 50x slower). A module asks
    for it with `pytestmark = pytest.mark.usefixtures("one_torch_thread")`."""
    import torch

    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="session")
def tiny_maps(tmp_path_factory):
    """Tiny clean/occluded datasets and fast_dev_run perception maps (the camera path, not accuracy), trained once
    per session for every test module that needs a map in the loop: `(root, {"clean": id, "occluded": id})`."""
    from pipeline.cli import compose
    from pipeline.data.stage import run as data_run
    from pipeline.train.stage import run as train_run

    root = tmp_path_factory.mktemp("exp_maps")
    ids = {}
    for recipe in ("clean", "occluded"):
        small = [f"data={recipe}", "data.splits.train=128", "data.splits.val=32", "data.splits.test=32",
                 f"paths.datasets_dir={root / 'datasets'}"]
        data_run(compose("data", small))
        out = train_run(compose("train", [*small, "trainer=debug", f"name={recipe}", "eval_levels=[none]",
                                          f"paths.models_dir={root / 'models'}"]))
        ids[recipe] = f"{out['name']}-{out['id']}"
    return root, ids


@pytest.fixture(scope="session")
def production():
    """Make paper's occluded keypoint map at production size (filters 16-32-64, BatchNorm, CoordConv, the keypoint
    head and a gaussian uncertainty head; the weights of `occluded_keypoint-f87011bfec`, committed as
    `tests/fixtures/occluded_keypoint.pt`, 1.7 MB): `(model, its deployed network, the default scene's camera)`."""
    from pathlib import Path
    from types import SimpleNamespace

    import torch

    from pipeline.perception.network import FoldedPerceptionNet
    from pipeline.render import Camera
    from pipeline.train.module import PerceptionMap

    blob = torch.load(Path(__file__).parent / "fixtures" / "occluded_keypoint.pt", weights_only=True)
    model = PerceptionMap.of(**blob["hparams"])
    model.load_state_dict(blob["state_dict"])
    assert tuple(blob["hparams"]["filters"]) == (16, 32, 64) and model.var_head is not None
    scene = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))
    return model.eval(), FoldedPerceptionNet(model.eval()), Camera(scene)


# The modules holding the suite's longest tests run first (in this order), the others after them in file order.
# `make test` runs one pytest-xdist worker per core with `--dist worksteal`: each worker starts on its half of the
# collection and an idle worker takes tests from the end of the other's queue, but never a test already running, so
# a 50 s test begun in the last minute leaves the other core idle (37 s of a 681 s run, measured 2026-12-07, the
# paper's lineage test at the end of tests/test_config_truth.py). A module moves whole: its module-scoped fixtures
# are built once, as in file order. A stale list only changes the order, never a result.
LONGEST_FIRST = ("test_config_truth.py", "test_bracket_loop_that_runs.py", "test_dagger.py", "test_bracket_camera.py",
                 "test_experiments.py", "test_bracket_several.py", "test_bracket_map_falsifier.py",
                 "test_certify_bounds.py", "test_bracket_clouds.py", "test_bracket_stage.py")


def pytest_collection_modifyitems(items):
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda item: rank.get(item.path.name, len(rank)))  # stable: file order within and after
