"""A covering from the discs alone (issue 45): `python -m pipeline.fieldcheck ... write=FILE` writes the scene with
the largest covering SPEC §3.6 admits for the loop it will run in, or says in one line which pair of discs makes
every covering impossible and by how much."""

from __future__ import annotations

import pytest
import yaml

from pipeline.config import build, compose
from pipeline.control.validity import field_violations
from pipeline.errors import ConfigError
from pipeline.fieldcheck import geometry, run, starts_of
from pipeline.sim import simulate

# benchmark-like discs of radius 0.5 around the goal at the origin, centres 2.2 apart at the closest, no covering
DISCS = [[2.2, 0.0], [0.0, 2.2], [-2.2, 0.0], [0.0, -2.2], [3.3, 3.3], [-3.3, 3.3], [-3.3, -3.3], [3.3, -3.3],
         [5.0, 0.4]]


def _obstacles(discs, r=0.5) -> str:
    return "scene.obstacles=[" + ",".join(f"{{center:[{x},{y}],radius:{r}}}" for x, y in discs) + "]"


def _cfg(*extra):
    return compose("fieldcheck", ["scene=case6", "init=circle", "controller=hybrid_dense", _obstacles(DISCS), *extra])


def _check_written(path, *extra):
    """The written scene, composed as a user would run it: SPEC §3.6's rules find nothing, and the covering is
    near the largest (a covering 5 % larger in apex and reach is rejected)."""
    node = yaml.safe_load(path.read_text())
    obstacles = node["obstacles"]
    over = "scene.obstacles=[" + ",".join(
        f"{{center:[{o['center'][0]},{o['center'][1]}],radius:{o['radius']},apex:{o['apex']},"
        f"barrier_scale:{o['barrier_scale']}}}" for o in obstacles) + "]"
    cfg = compose("fieldcheck", ["scene=case6", "init=circle", "controller=hybrid_dense", over, *extra])
    g = geometry(cfg)
    kw = dict(h=cfg.controller.cell_hysteresis, u_max=cfg.controller.u_max, T_s=cfg.camera.period,
              arena=g["arena"], starts=starts_of(cfg, g["target"]))
    assert field_violations(g["centers"], g["radii"], g["target"], apex=g["apex"], reach=g["reach"], **kw) == []
    big = field_violations(g["centers"], g["radii"], g["target"], apex=1.3 * g["apex"], reach=1.3 * g["reach"], **kw)
    assert big, "the written covering is far from the largest one the field admits"
    return cfg


def test_write_a_covering_the_rules_admit(tmp_path, capsys):
    out = run(_cfg(f"write={tmp_path / 'cov.yaml'}"))
    assert out["violations"], "the scene's default covering must be rejected here (the point of writing one)"
    cfg = _check_written(tmp_path / "cov.yaml")
    assert "0 violations" in capsys.readouterr().out
    scene = build(cfg.scene, "scene")  # the scene's own checks accept it, the controller's V3 too, and it drives
    ctl = build(cfg.controller, "controller", scene=scene)
    res = simulate(scene, ctl, build(cfg.init, "init")(scene)[::25], sim=build(cfg.sim, "sim"),
                   camera=build(cfg.camera, "camera"))
    assert res.metrics["success"].all() and not res.metrics["collision"].any()


def test_write_for_the_unicycle_grows_with_the_look_ahead(tmp_path):
    run(_cfg("vehicle=unicycle", "vehicle.lookahead=0.1", f"write={tmp_path / 'uni.yaml'}"))
    cfg = _check_written(tmp_path / "uni.yaml", "vehicle=unicycle", "vehicle.lookahead=0.1")
    node = yaml.safe_load((tmp_path / "uni.yaml").read_text())
    run(_cfg(f"write={tmp_path / 'si.yaml'}"))
    plain = yaml.safe_load((tmp_path / "si.yaml").read_text())
    assert node["obstacles"][0]["apex"] < plain["obstacles"][0]["apex"]  # the grown discs leave less room
    assert geometry(cfg)["inflation"] == pytest.approx(0.1)


def test_no_covering_names_the_pair_and_the_shortfall(tmp_path):
    close = DISCS[:-1] + [[2.2, 1.5]]  # 1.5 from disc 0: no covering holds both
    cfg = compose("fieldcheck", ["scene=case6", "init=circle", "controller=hybrid_dense", _obstacles(close),
                                 f"write={tmp_path / 'x.yaml'}"])
    with pytest.raises(ConfigError, match=r"scene\.obstacles\[0,8\]: discs 0 and 8 are 1\.5 apart; every covering "
                                          r"needs more than [0-9.]+ .* short by [0-9.]+"):
        run(cfg)
    assert not (tmp_path / "x.yaml").exists()


def test_write_margin_is_checked(tmp_path):
    with pytest.raises(ConfigError, match="write_margin"):
        run(_cfg(f"write={tmp_path / 'cov.yaml'}", "write_margin=1.5"))
