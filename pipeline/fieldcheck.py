"""`python -m pipeline.fieldcheck <simulate overrides>`: every violated condition of SPEC §3.6 (arena, V1, V2, V3, the
starts) for the composed scene, controller, camera, vehicle and starts, and the settings that would make the field
valid (apex / barrier reach factors, the largest cell hysteresis), instead of the first violation alone (issue 29).

It reads the same config as `python -m pipeline.simulate` (the `fieldcheck` config is `simulate` with its own run
folder) and reports without rejecting: exit 0 with the list, also when the field is invalid.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.control.fields import analyse_field
from pipeline.control.validity import field_violations
from pipeline.sim import starts


def geometry(cfg: DictConfig) -> dict:
    """The field's arrays as the controller sees them (the unicycle's: every disc grown by its look-ahead, apex and
    barrier scale in proportion, as `Scene.inflated`), without the scene's own checks: centres, radii, apex,
    reach, target, arena."""
    node = tracking.to_plain(cfg.scene)
    d = float(cfg.vehicle.get("lookahead") or 0.0) if cfg.get("vehicle") is not None else 0.0
    if "obstacles" not in node:  # a generator (random_scene, dense_scene): valid by construction, read it back
        arr = build(cfg.scene, "scene").config()
        node = {**node, **arr}
    bar = node.get("barrier") or {}
    rho, scale = float(bar.get("rho", 0.5)), bar.get("scale")
    c, r, apex, reach = [], [], [], []
    for o in node["obstacles"]:
        ri = float(o["radius"])
        grow = (ri + d) / ri
        a = 2.0 * math.sqrt(2.0) * ri if o.get("apex") is None else float(o["apex"])
        ell = o.get("barrier_scale") or scale or ri
        c.append([float(x) for x in o["center"]])
        r.append(ri + d)
        apex.append(a * grow)
        reach.append(math.sqrt(rho) * float(ell) * grow)
    ar = node.get("arena") or {"x": [-50.0, 50.0], "y": [-30.0, 30.0]}
    return {"centers": np.array(c), "radii": np.array(r), "apex": np.array(apex), "reach": np.array(reach),
            "target": np.asarray(node["target"], float), "arena": (tuple(ar["x"]), tuple(ar["y"])), "inflation": d}


def starts_of(cfg: DictConfig, target: np.ndarray) -> np.ndarray | None:
    """The configured starts where they are explicit (points, a circle); None for drawn ones (they avoid the
    diamonds by construction)."""
    init = build(cfg.init, "init")  # the distribution itself (it needs no scene until it is drawn)
    if isinstance(init, starts.Points):
        return np.asarray(init.points, float)
    if isinstance(init, starts.Circle):
        return init.on_circle(target)
    return None


def run(cfg: DictConfig) -> dict:
    g = geometry(cfg)
    ctl = cfg.controller
    h = float(ctl.get("cell_hysteresis") or 1.0)
    u_max = ctl.get("u_max")
    T_s = cfg.camera.get("period")
    P = starts_of(cfg, g["target"])
    found = field_violations(g["centers"], g["radii"], g["target"], apex=g["apex"], reach=g["reach"], h=h,
                             u_max=u_max, T_s=T_s, arena=g["arena"], starts=P)
    where = f" (the discs grown by vehicle.lookahead = {g['inflation']:g})" if g["inflation"] else ""
    print(f"{len(found)} violation(s) of SPEC §3.6 (h = {h:g}, u_max = {u_max}, T_s = {T_s}){where}:")
    for v in found:
        print(f"  {v.line}")
    rr = g["radii"]
    ana = analyse_field(g["centers"], rr, g["target"], starts=P, arena=g["arena"], h=h, u_max=u_max, T_s=T_s)
    # rr are already the grown radii r_i + d: the analysis is the same, and it records (and prints) the d used
    ana = dataclasses.replace(ana, inflation=g["inflation"])
    print("Feasible covering settings (uniform in the radius r_i" + (" + d" if g["inflation"] else "") + "):")
    print("  " + ana.summary().replace("\n", "\n  "))
    R = g["apex"] + math.sqrt(2.0) * g["reach"]
    ii, jj = np.triu_indices(len(R), 1)
    step = 2.0 * float(u_max) * float(T_s) if u_max is not None and T_s is not None else 0.0
    if len(ii):
        h_max = float(np.min(np.hypot(*(g["centers"][ii] - g["centers"][jj]).T) - R[ii] - R[jj] - step))
        print(f"Largest cell hysteresis h with this covering (V2, V3): {h_max:.4g}"
              + ("" if h_max > 0 else " (none: shrink the covering first)"))
    return {"violations": found, "analysis": ana}


main = stage_main("fieldcheck", run="pipeline.fieldcheck:run")

if __name__ == "__main__":
    main()
