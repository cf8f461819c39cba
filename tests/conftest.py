"""Shared test setup: headless plotting, few threads (the CI machine has 2 cores), Hydra state cleared."""

import os

os.environ.setdefault("MPLBACKEND", "Agg")
os.environ.setdefault("HYDRA_FULL_ERROR", "0")
# torch's OpenMP threads sleep instead of spinning while they wait: the numbers are the same, and on a busy
# machine (CI beside other jobs) a spinning thread steals the core its partner needs (5-8x slower steps)
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")

import pytest  # noqa: E402
from hypothesis import settings  # noqa: E402

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
