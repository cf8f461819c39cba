"""The certificate's property tests reach `make test-explore`'s budget (issue 47: they ran 8–12 examples even under
the explore profile, their own `max_examples` capping it)."""

import re
from pathlib import Path

from budget import EXPLORE_FACTOR, examples

CERTIFICATE_TESTS = ["test_bracket_certificate.py", "test_bracket_loop_that_runs.py", "test_certify_bounds.py",
                     "test_certify_pose.py", "test_certified_training.py"]


def test_explore_scales_the_counts(monkeypatch):
    monkeypatch.delenv("HYPOTHESIS_PROFILE", raising=False)
    assert examples(12) == 12
    monkeypatch.setenv("HYPOTHESIS_PROFILE", "explore")
    assert examples(12) == 12 * EXPLORE_FACTOR >= 100


def test_no_certificate_property_test_caps_the_explore_profile():
    here = Path(__file__).parent
    for name in CERTIFICATE_TESTS:
        text = (here / name).read_text()
        assert "@settings(" in text or "@given(" in text, name
        assert not re.search(r"max_examples=\d", text), f"{name}: a literal max_examples caps make test-explore"
