"""Several disturbance conditions in one batch (`PerAgent`, issue 30): each group's agents end exactly as in a run
of their own, in both time models, so the batched robustness sweep reports the rows the separate runs did."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.control import HybridController, Obstacle, Scene, SmoothController
from pipeline.sim import Adversarial, Alternating, CameraSettings, SimSettings, simulate
from pipeline.sim.disturbances import PerAgent
from pipeline.sim.starts import NearK

KEYS = ("success", "collision", "final_error", "jumps", "time_to_target")


@pytest.fixture(scope="module")
def scene() -> Scene:
    return Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])


def _run(scene, ctrl, x0, dist, model):
    # a short horizon: the arcs near K under the adversary are where the batch could differ (and the costly part)
    return simulate(scene, ctrl, x0, sim=SimSettings(dt=0.01, horizon=1.5, model=model),
                    camera=CameraSettings(period=0.05), disturbance=dist, seed=0, record=False)


@pytest.mark.parametrize("model", ["continuous", "sampled"])
@pytest.mark.parametrize("cls", [HybridController, SmoothController])
def test_a_batch_of_conditions_equals_the_runs_of_each(scene, model, cls):
    ctrl = cls(scene=scene)
    groups = [(Adversarial(0.25), NearK(n=3, seed=0, band=0.25, a_range=[-14.0, -12.0])(scene)),
              (Adversarial(1.0), NearK(n=3, seed=1, band=1.0, a_range=[-14.0, -12.0])(scene)),
              (Alternating(0.5), NearK(n=2, seed=2, band=0.5, a_range=[-14.0, -12.0])(scene))]
    batch = _run(scene, ctrl, np.concatenate([x for _, x in groups]),
                 PerAgent([d for d, _ in groups], [len(x) for _, x in groups]), model)
    start = 0
    for dist, x0 in groups:
        alone = _run(scene, ctrl, x0, dist, model)
        for key in KEYS:
            np.testing.assert_array_equal(np.asarray(batch.metrics[key])[start:start + len(x0)],
                                          np.asarray(alone.metrics[key]), err_msg=f"{key} ({dist})")
        start += len(x0)


@settings(max_examples=30, deadline=None)
@given(sizes=st.lists(st.integers(0, 5), min_size=1, max_size=4), seed=st.integers(0, 10))
def test_each_agent_gets_its_own_groups_disturbance(scene, sizes, seed):
    rng = np.random.default_rng(seed)
    eps = rng.uniform(0.1, 2.0, len(sizes))
    dist = PerAgent([Adversarial(e) for e in eps], sizes)
    n = sum(sizes)
    p = rng.uniform(-40, 40, (n, 2))
    e = dist(p, 0, rng, scene)
    owner = np.repeat(np.arange(len(sizes)), sizes)
    for k, ek in enumerate(eps):
        np.testing.assert_allclose(e[owner == k], Adversarial(ek)(p[owner == k], 0, rng, scene))
    idx = rng.permutation(n)[: n // 2]  # a sampled loop measures a subset of the batch this frame
    np.testing.assert_allclose(dist(p[idx], 0, rng, scene, idx), e[idx])


def test_a_mismatched_batch_is_an_error(scene):
    with pytest.raises(ValueError, match="2 disturbances for 1 groups"):
        PerAgent([Adversarial(1.0), Adversarial(2.0)], [3])
    with pytest.raises(ValueError, match="4 positions for 3 agents"):
        PerAgent([Adversarial(1.0)], [3])(np.zeros((4, 2)), 0, np.random.default_rng(0), scene)
