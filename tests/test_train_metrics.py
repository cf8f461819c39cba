"""`pipeline.perception.metrics`: the near-target and visible/hidden splits are the whole-set metric on each subset."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.perception.metrics import error_metrics, perception_metrics


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 10_000), n=st.integers(5, 300), ppu=st.floats(0.5, 3.0))
def test_splits_are_the_metric_of_their_subsets(seed, n, ppu):
    rng = np.random.default_rng(seed)
    true = rng.uniform([-50, -30], [50, 30], (n, 2))
    true[: n // 3] = [40.0, 0.0] + rng.normal(0, 2.0, (n // 3, 2))  # a third near the target
    pred = true + rng.normal(0, 1.0, (n, 2)) * rng.uniform(0.1, 5, (n, 1))
    alpha = rng.uniform(0, 1, n)
    m = perception_metrics(pred, true, ppu, target=(40.0, 0.0), leader_alpha=alpha, near_radius=5.0)
    dist = np.hypot(*((pred - true) * ppu).T)
    near = np.hypot(*(true - [40.0, 0.0]).T) <= 5.0
    assert m["near_target"]["n"] == near.sum()
    if near.any():
        assert np.isclose(m["near_target"]["max"], dist[near].max())
        assert np.isclose(m["near_target"]["mean"], dist[near].mean())
    hidden = alpha >= 0.8
    assert m["hidden"]["n"] + m["visible"]["n"] == n == m["n"]
    assert np.isclose(m["hidden"]["share"], hidden.mean())
    if (~hidden).any():
        assert m["visible"] == error_metrics(pred[~hidden], true[~hidden], ppu)
    # the whole-set MAE is the count-weighted mean of the two subsets' MAEs
    parts = [(m[k]["mae_px"], m[k]["n"]) for k in ("visible", "hidden") if m[k]["n"]]
    assert np.isclose(sum(a * b for a, b in parts) / n, m["mae_px"])


def test_empty_subsets_are_none_not_nan():
    true = np.zeros((4, 2)) + [-40.0, 0.0]
    m = perception_metrics(true + 1.0, true, 1.0, target=(40.0, 0.0), leader_alpha=np.zeros(4))
    assert m["near_target"]["n"] == 0 and m["near_target"]["p95"] is None
    assert m["hidden"]["n"] == 0 and m["hidden"]["mae_px"] is None and m["visible"]["mae_px"] == 1.0
