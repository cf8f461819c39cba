"""`python -m pipeline.fieldcheck <simulate overrides>`: every violated condition of SPEC §3.6 (arena, V1, V2, V3, the
starts) for the composed scene, controller, camera, vehicle and starts, and the settings that would make the field
valid (apex / barrier reach factors, the largest cell hysteresis), instead of the first violation alone (issue 29).

It reads the same config as `python -m pipeline.simulate` (the `fieldcheck` config is `simulate` with its own run
folder) and reports without rejecting: exit 0 with the list, also when the field is invalid.

`write=FILE` (issue 45): a covering from the discs alone. It writes the scene (the same discs, target, arena and
barrier) with the largest covering V1–V3 and the starts admit for the loop it will run in (`controller.u_max`,
`controller.cell_hysteresis`, `camera.period`, the vehicle's look-ahead), uniform in the radius: apex
`f (r_i + d)`, reach `g (r_i + d)` with `f + sqrt(2) g = sqrt(2) + (1 - write_margin) (kappa_max - sqrt(2))`, the
headroom split evenly between apex and reach (the apex capped by the starts), checked by SPEC §3.6's rules before
anything is written. Where no covering exists: one line naming the pair of discs (or the disc and the target, or
the start) that makes every covering impossible and by how much, exit 2.
"""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from hydra.utils import get_class
from omegaconf import DictConfig, OmegaConf

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.control.admitted import checked_covering
from pipeline.control.fields import FieldAnalysis, analyse_field
from pipeline.control.validity import field_violations
from pipeline.plants import steering_warnings
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
    out = {"violations": found, "analysis": ana, "steering": steering(cfg)}
    if cfg.get("write"):
        out["written"] = write_covering(cfg, g, ana, P, h=h, u_max=u_max, T_s=T_s)
    return out


def steering(cfg: DictConfig) -> list[str]:
    """The unicycle's steering conditions (docs/dense.md, "The unicycle in clutter"), printed: how fast the
    look-ahead point can move sideways, the heading lag at full speed under `turn_lookahead`, and the warnings of
    :func:`pipeline.plants.steering_warnings` (a turn rate past `omega_max`, the push-out's period-2 orbit)."""
    if cfg.get("vehicle") is None or cfg.vehicle.get("lookahead") is None:
        return []
    plant = build(cfg.vehicle, "vehicle")
    if plant.omega_max is None:
        return []
    ctl = cfg.controller
    u_max = ctl.get("u_max")
    # the law's settings without building it (its scene may be the invalid one reported above); the push-out speed
    # defaults to u_max as in Feedback, and whether it is hybrid is the class's own attribute
    law = SimpleNamespace(u_max=u_max, push_speed=ctl.get("push_speed") or u_max,
                          hybrid=bool(getattr(get_class(ctl._target_), "hybrid", False)))
    d, w, rho = plant.lookahead, plant.omega_max, plant.turn_lookahead
    lines = [f"z moves sideways at most omega_max d = {w * d:.3g} per second; commands averaged over "
             f"{plant.smoothing} frame(s)"]
    if rho is not None and u_max is not None:
        lag = math.degrees(math.asin(min(1.0, w * rho / float(u_max))))
        lines.append(f"turn_lookahead {rho:g}: full speed only with the heading within {lag:.3g} deg of the command "
                     f"(slower beyond)")
    lines += [f"warning: {x}" for x in steering_warnings(plant, law)]
    print("Unicycle steering (docs/dense.md, the unicycle in clutter):")
    for line in lines:
        print(f"  {line}")
    return lines


def write_covering(cfg: DictConfig, g: dict, ana: FieldAnalysis, P, *, h, u_max, T_s) -> str:
    """The scene with the largest uniform covering the field admits, written to `cfg.write` (module docstring)."""
    f, reach_f, kappa = checked_covering(ana, g["centers"], g["radii"], g["target"],
                                         margin=float(cfg.get("write_margin", 0.1)), starts=P, h=h, u_max=u_max,
                                         T_s=T_s, arena=g["arena"])
    rr, d = g["radii"], g["inflation"]
    node = tracking.to_plain(cfg.scene)
    rho = float((node.get("barrier") or {}).get("rho", 0.5))
    r0 = rr - d  # written for the scene's own radii: the unicycle's steering grows apex and reach by (r + d) / r
    node["obstacles"] = [{"center": [float(x) for x in c], "radius": float(r), "apex": round(float(f * r), 6),
                          "barrier_scale": round(float(reach_f * r / math.sqrt(rho)), 6)}
                         for c, r in zip(g["centers"], r0)]
    node.setdefault("barrier", {})["scale"] = None
    node["name"] = f"{node.get('name', 'scene')}_covered"
    path = Path(str(cfg.write))
    path.parent.mkdir(parents=True, exist_ok=True)
    header = (f"# Written by python -m pipeline.fieldcheck write={path}: apex {f:.4f} (r + d), reach {reach_f:.4f} "
              f"(r + d), d = {d:g}\n# (kappa {kappa:.4f} of the admitted sup {ana.kappa_max:.4f}; h = {h:g}, u_max = "
              f"{u_max}, T_s = {T_s}). Use it with scene=<this file's name> from conf/scene/ or +scene=...\n")
    path.write_text(header + OmegaConf.to_yaml(OmegaConf.create(node)))
    print(f"Wrote the covered scene to {path} (apex {f:.4f} (r + d), reach {reach_f:.4f} (r + d), kappa {kappa:.4f} "
          f"< {ana.kappa_max:.4f}); 0 violations")
    return str(path)


main = stage_main("fieldcheck", run="pipeline.fieldcheck:run")

if __name__ == "__main__":
    main()
