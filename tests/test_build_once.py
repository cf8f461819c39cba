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


@settings(max_examples=20, deadline=None)
@given(chis=st.lists(st.floats(1.05, 3.0), min_size=2, max_size=5), share=st.floats(0.05, 0.95),
       seed=st.integers(0, 1000))
def test_a_hysteresis_per_agent_is_each_agents_own_variant(chis, share, seed):
    """A batch of several cells in one variant (arrays `(N,)`, the margin map's batched bisection) decides every
    agent as its own cell's variant does, bit for bit; on a part of its batch it refuses."""
    n = 40
    m = np.random.default_rng(seed).uniform([-45, -25], [45, 25], (n * len(chis), 2))
    lams = [share * (c - 1) for c in chis]
    xd = BASE.initial_state(m)
    rows = BASE.with_hysteresis(np.repeat(chis, n), np.repeat(lams, n))
    for k, (chi, lam) in enumerate(zip(chis, lams)):
        own, part = BASE.with_hysteresis(chi, lam), slice(k * n, (k + 1) * n)
        xk = {key: v[part] for key, v in xd.items()}
        np.testing.assert_array_equal(rows.jump_set(m, xd)[part], own.jump_set(m[part], xk))
        np.testing.assert_array_equal(rows.flow_set(m, xd)[part], own.flow_set(m[part], xk))
    with pytest.raises(ValueError, match="whole batch"):
        rows.jump_set(m[:n], {key: v[:n] for key, v in xd.items()})


@pytest.mark.parametrize(("chi", "lam", "field"), [(1.0, 0.05, "controller.chi"), (1.2, 0.2, "controller.lam"),
                                                   (1.2, 0.0, "controller.lam")])
def test_a_bad_variant_is_one_error_naming_the_field(chi, lam, field):
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):
        BASE.with_hysteresis(chi, lam)
    with pytest.raises(ConfigError, match=field.replace(".", r"\.")):  # one bad agent of a batch
        BASE.with_hysteresis([1.1, chi], [0.09, lam])


# ------------------------------------------------------------------------------- each value checked once per run
def _count_checks(monkeypatch, module: str, argv: list[str], counted) -> int:
    """Run the stage `module` in this process (preflight, then Hydra's run) and count the checks of the values
    `counted(path)` selects: every `check_value` on such a path (at composition, in a build, in a constructor)."""
    import importlib
    import sys

    import pipeline.schema as schema

    monkeypatch.setattr(schema, "_ACCEPTED", set())  # a fresh process: nothing checked yet
    seen = []
    original = schema.check_value

    def spy(value, tp, path):
        if counted(path):
            seen.append(path)
        return original(value, tp, path)

    for mod in [m for m in list(sys.modules.values()) if getattr(m, "check_value", None) is original]:
        monkeypatch.setattr(mod, "check_value", spy)
    monkeypatch.setattr(schema, "check_value", spy)
    monkeypatch.setattr(sys, "argv", [module, *argv])
    importlib.import_module(f"{module}.__main__").main()
    return len(seen)


def test_an_experiments_run_checks_the_controllers_chi_at_most_three_times(monkeypatch, tmp_path):
    """`controller.chi`: its type and range (at composition, in the preflight's build, in the run's) and its
    cross-field rule `lam < chi - 1` (each construction) together at most 3 times (issue 27: about 8 before)."""
    import functools

    built = []
    init = HybridController.__init__

    @functools.wraps(init)
    def counting_init(self, *args, **kwargs):
        built.append(1)
        init(self, *args, **kwargs)

    monkeypatch.setattr(HybridController, "__init__", counting_init)
    n = _count_checks(monkeypatch, "pipeline.experiments",
                      ["debug=tiny", "experiment=monte_carlo", "perception=oracle", f"paths.outputs_dir={tmp_path}",
                       f"hydra.run.dir={tmp_path / 'run'}"],
                      lambda path: path in ("controller.chi", "controllers.hybrid.chi"))
    assert any((tmp_path / "experiments").glob("monte_carlo-*")), "the run did not compute"
    assert n + len(built) <= 3, f"chi checked {n} times and its rule {len(built)} times"


def test_a_data_run_checks_its_occlusion_level_at_most_three_times(monkeypatch, tmp_path):
    """The recipe's cloud level (`occluded`: heavy_mix), at composition, resolving the dataset's id and rendering:
    at most 3 checks (issue 27: 10 before)."""
    n = _count_checks(monkeypatch, "pipeline.data",
                      ["debug=tiny", "data=occluded", f"paths.datasets_dir={tmp_path}",
                       f"hydra.run.dir={tmp_path / 'run'}"],
                      lambda path: path in ("occlusions.heavy_mix.probability", "occlusion.probability"))
    assert any(tmp_path.glob("occluded-*")), "the run did not render"
    assert 1 <= n <= 3, f"the level checked {n} times"


def test_a_value_accepted_for_one_annotation_is_still_checked_against_another(tmp_path, monkeypatch):
    """A value a node's check accepted is not checked again for the same annotation, but a constructor the target
    calls inside (a namesake, before: matched by class name) checks it against its own (`size: Positive`)."""
    from pipeline.config import build

    (tmp_path / "namesakes_b.py").write_text(
        "from pipeline.schema import Positive, checked\n\n\n@checked('inner')\nclass Part:\n"
        "    def __init__(self, size: Positive = 1.0):\n        self.size = size\n")
    (tmp_path / "namesakes_a.py").write_text(
        "import namesakes_b\n\n\nclass Part:\n    def __init__(self, size: float = 1.0):\n"
        "        self.inner = namesakes_b.Part(size=size)\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert build({"_target_": "namesakes_a.Part", "size": 2.0}, "part").inner.size == 2.0
    with pytest.raises(ConfigError, match="size: must be a number > 0"):
        build({"_target_": "namesakes_a.Part", "size": -1.0}, "part")
