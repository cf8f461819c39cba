"""Dense fields (issue 29): the friction a user meets on the hybrid-RL benchmark's clutter, the benchmark's scenes,
starts and noise, and the side hysteresis of docs/dense.md."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from pipeline.cli import compose
from pipeline.config import build
from pipeline.control import HybridController, Scene
from pipeline.errors import ConfigError
from pipeline.preflight import preflight
from pipeline.sim import Adversarial, WorldAlternating, simulate
from pipeline.sim.starts import Circle, Points
from pipeline.sweep import simulate_headline


def _scene(name: str) -> Scene:
    return build(compose("simulate", [f"scene={name}"]).scene, "scene")


# ---- friction 2: the documented controller keys need no `+`, in a sweep over every controller too
@pytest.mark.parametrize("argv", [["controller.cell_hysteresis=0.5"], ["controller.push_speed=3"],
                                  ["controller=hybrid,smooth,cbf", "controller.push_speed=3"],
                                  ["controller=hybrid_dense,smooth,cbf", "controller.u_max=1"]])
def test_documented_controller_keys_need_no_plus(argv):
    assert preflight("simulate", argv) >= 1


# ---- friction 3: the V2 message names the scene's key, not `controller.obstacles`
def test_v2_message_names_the_scene_key():
    cfg = compose("simulate", ["scene=case6", "controller=hybrid"])
    with pytest.raises(ConfigError) as err:
        build(cfg.controller, "controller", scene=build(cfg.scene, "scene"))
    assert err.value.field.startswith("scene.obstacles[") and "V2" in err.value.reason


# ---- friction 4: the count of further violations is the true one and says which conditions it counts
def test_construction_message_says_which_conditions_it_counted():
    with pytest.raises(ConfigError) as err:
        HybridController(_scene("case6"), cell_hysteresis=1.0, u_max=10.0)
    assert "V1-V2" in err.value.reason and "frame period" in err.value.reason


def test_more_violations_count_is_the_number_of_violations():
    from pipeline.control.validity import field_violations
    scene = _scene("case6")
    ctl = HybridController(scene, cell_hysteresis=0.05, u_max=10.0)
    arr = scene.arrays
    found = field_violations(arr["center"], arr["radius"], scene.p_T, apex=arr["c"], reach=arr["reach"], h=0.05,
                             u_max=10.0, T_s=0.05)
    with pytest.raises(ConfigError) as err:
        ctl.check_loop(0.05)
    assert f"[{len(found) - 1} more violation" in err.value.reason and "V1-V3" in err.value.reason


# ---- friction 6: a start inside a diamond is rejected (SPEC §3.6), on the circle starts too
def test_start_inside_a_diamond_is_rejected():
    scene = _scene("default")   # one disc r = 4 at the origin, apex 11.3
    with pytest.raises(ConfigError, match="diamond"):
        Points(points=[[-9.0, 0.0]])(scene)   # outside the disc, inside the diamond
    Points(points=[[-12.0, 2.0]])(scene)
    with pytest.raises(ConfigError, match="diamond"):
        Circle(n=4, radius=5.1)(_scene("case6"))   # (5.1, 0): 0.6 from the disc at (4.5, 0), apex 1


# ---- friction 7: a run where no agent arrives makes no 'Mean of empty slice' warning
def test_headline_of_a_run_where_nobody_arrives_has_no_warning():
    import pandas as pd
    m = pd.DataFrame({"success": [False, False], "collision": [False, False], "time_to_target": [np.nan, np.nan]})
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        row = simulate_headline({"metrics": m})
    assert np.isnan(row["median_time_to_target"]) and row["success_rate"] == 0.0


# ---- friction 9: the benchmark's alternating disturbance in a world-fixed direction
def test_world_alternating_is_s_times_m_minus_m():
    d = WorldAlternating(m=0.2)
    p = np.zeros((3, 2))
    rng = np.random.default_rng(0)
    e0, e1 = d(p, 0, rng, None), d(p, 1, rng, None)
    assert np.allclose(e0, [0.2, -0.2]) and np.allclose(e1, -e0)


# ---- the benchmark's case6 with the dense design: every start arrives under its noise and the adversary
def _case6_runs(disturbance, controller):
    cfg = compose("simulate", ["scene=case6", f"controller={controller}", "controller.u_max=1", "init=circle"])
    scene = build(cfg.scene, "scene")
    ctl = build(cfg.controller, "controller", scene=scene)
    x0 = build(cfg.init, "init")(scene)
    r = simulate(scene, ctl, x0, horizon=10.0, disturbance=disturbance, record=False, stall_speed=0.025)
    return np.asarray(r.metrics["success"]), np.asarray(r.metrics["collision"])


@pytest.mark.parametrize("disturbance", [WorldAlternating(m=0.05), WorldAlternating(m=0.2), Adversarial(eps=0.28)])
def test_dense_hybrid_arrives_from_every_start_of_case6(disturbance):
    ok, hit = _case6_runs(disturbance, "hybrid_dense")
    assert ok.all() and not hit.any()


def test_side_hysteresis_is_what_beats_the_adversary():
    ok_with, _ = _case6_runs(Adversarial(eps=0.28), "hybrid_dense")
    cfg = compose("simulate", ["scene=case6", "controller=hybrid_dense", "controller.noise_tolerance=null"])
    scene = build(cfg.scene, "scene")
    ctl = build(cfg.controller, "controller", scene=scene)
    r = simulate(scene, ctl, build(cfg.init, "init")(scene) if False else Circle()(scene), horizon=10.0,
                 disturbance=Adversarial(eps=0.28), record=False, stall_speed=0.025)
    assert ok_with.mean() > np.asarray(r.metrics["success"]).mean()
