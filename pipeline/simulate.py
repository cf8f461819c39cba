"""Stage: closed-loop simulation on the true state + disturbance (`python -m pipeline.simulate`).

Writes to the Hydra run dir: `metrics.csv` (one row per agent), `trajectories.npz`, `trajectories.png`, and the
resolved config (`.hydra/config.yaml`).
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from omegaconf import DictConfig

from pipeline.cli import stage_main
from pipeline.config import build
from pipeline.errors import ConfigError
from pipeline.perception.adversary import is_attack
from pipeline.plants import steering_warnings
from pipeline.preflight import prepared
from pipeline.sim import simulate
from pipeline.sim.composed import loop_parts


def objects(cfg: DictConfig):
    """Every object of the run, built from its node and checked: (scene, controller, disturbance, starts, keywords).

    The controller steers the vehicle's steered point in `vehicle.steering_scene(scene)` (the unicycle's discs
    inflated by its look-ahead, SPEC §3.7); the keywords of :func:`pipeline.sim.simulate` carry the `sim` and
    `camera` settings, the plant and its initial headings."""
    parts = loop_parts(cfg)
    scene, plant, sim, camera = parts.scene, parts.plant, parts.sim, parts.camera
    controller = parts.law(cfg.controller)
    disturbance = build(cfg.disturbance, "disturbance")
    if is_attack(disturbance):
        raise ConfigError("disturbance", f"{disturbance.name} acts through the camera, and this stage simulates the "
                                         "true state: run it in a camera experiment (experiment=camera_attack)")
    x0 = build(cfg.init, "init")(scene)
    kw = {"sim": sim, "camera": camera, "plant": plant, "heading0": plant.initial_heading(x0, scene)}
    return scene, controller, disturbance, x0, kw


def preset(group: str, default: str) -> str:
    """The option chosen for the config group `group` (`controller=hybrid_dense`: "hybrid_dense") when this stage
    runs as its own Hydra app (`python -m pipeline.simulate`), else `default`."""
    from hydra.core.hydra_config import HydraConfig

    if not HydraConfig.initialized() or HydraConfig.get().job.config_name != "simulate":
        return default
    return HydraConfig.get().runtime.choices.get(group) or default


def check(cfg: DictConfig) -> tuple:
    """Preflight: build every object (no simulation); the run uses them."""
    return objects(cfg)


def run(cfg: DictConfig) -> dict:
    """Run one batched simulation; returns `{"metrics": DataFrame, "result": SimResult, "run_dir": Path}`."""
    scene, controller, disturbance, x0, kw = prepared(cfg, check)  # the preflight's, when it checked this job
    for line in steering_warnings(kw["plant"], controller):  # valid, but the unicycle cannot follow (SPEC §3.7)
        print(f"warning: {line}", file=sys.stderr)
    run_dir = Path(cfg.paths.output_dir)
    name = preset("controller", controller.name)
    name = name if name == controller.name else f"{name} ({controller.name})"
    t0 = time.perf_counter()
    result = simulate(scene, controller, x0, disturbance=disturbance, progress=len(x0) >= 1000, **kw)
    elapsed = time.perf_counter() - t0
    run_dir.mkdir(parents=True, exist_ok=True)
    df = result.metrics_frame()
    df.to_csv(run_dir / "metrics.csv", index=False)
    result.save_npz(run_dir / "trajectories.npz")
    if cfg.get("plot", True):
        from pipeline.viz import save, trajectory_figure  # matplotlib: not imported by the preflight

        fig = trajectory_figure(scene, result.p, result.metrics["success"], arena=scene.bounds,
                                title=f"{name} controller, disturbance {disturbance.name}, {kw['sim'].model}")
        save(fig, run_dir / "trajectories")
    med = df.time_to_target.dropna().median() if df.success.any() else float("nan")
    vehicle = f", {kw['plant'].name}" if kw["plant"].heading else ""
    print(f"simulate ({kw['sim'].model}{vehicle}): {name} / {disturbance.name}: {len(df)} agents, "
          f"success {df.success.mean():.1%}, collision {df.collision.mean():.1%}, median time {med:.2f} s, "
          f"{elapsed:.2f} s -> {run_dir}")
    return {"metrics": df, "result": result, "run_dir": run_dir}


main = stage_main("simulate", run="pipeline.simulate:run", check="pipeline.simulate:check")

if __name__ == "__main__":
    main()
