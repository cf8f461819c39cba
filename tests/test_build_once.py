"""Build once, check once (issue 27): a controller variant is derived from the built object, not rebuilt from its
config; the variant is the controller its parameters would build."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.control import HybridController, Obstacle, Scene
from pipeline.errors import ConfigError

SCENE = Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[0.0, 0.0], radius=4.0)])
BASE = HybridController(SCENE)


@settings(max_examples=20, deadline=None)
@given(chi=st.floats(1.05, 3.0), share=st.floats(0.05, 0.95), seed=st.integers(0, 1000))
def test_hysteresis_variant_is_the_rebuilt_controller(chi, share, seed):
    lam = share * (chi - 1)
    variant, built = BASE.with_hysteresis(chi, lam), HybridController(SCENE, chi=chi, lam=lam)
    m = np.random.default_rng(seed).uniform([-45, -25], [45, 25], (200, 2))
    xd = built.initial_state(m)
    np.testing.assert_array_equal(variant.jump_set(m, xd), built.jump_set(m, xd))
    np.testing.assert_array_equal(variant.flow_set(m, xd), built.flow_set(m, xd))
    np.testing.assert_array_equal(variant.flow_map(m, xd), built.flow_map(m, xd))
    assert (BASE.chi, BASE.lam) == (1.1, 0.09)  # the built object is left as it was


@pytest.mark.parametrize(("chi", "lam", "field"), [(1.0, 0.05, "controller.chi"), (1.2, 0.2, "controller.lam"),
                                                   (1.2, 0.0, "controller.lam")])
def test_a_bad_variant_is_one_error_naming_the_field(chi, lam, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        BASE.with_hysteresis(chi, lam)
