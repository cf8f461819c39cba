"""Hypothesis example counts for the math's property tests: the fast suite's count, 25 times it under `make
test-explore` (HYPOTHESIS_PROFILE=explore), where a test's own `max_examples` would otherwise cap the profile's 500."""

import os

EXPLORE_FACTOR = 25


def examples(n: int) -> int:
    return n * EXPLORE_FACTOR if os.environ.get("HYPOTHESIS_PROFILE") == "explore" else n
