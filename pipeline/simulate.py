"""Stage: closed-loop simulation on the true state + disturbance (`python -m pipeline.simulate`).

Writes to the Hydra run dir: `metrics.csv` (one row per agent), `trajectories.npz`, `trajectories.png`,
and the resolved config (`.hydra/config.yaml`).
"""

from __future__ import annotations

import time
from pathlib import Path

from omegaconf import DictConfig

from pipeline.cli import stage_main
from pipeline.schema import CameraTiming, SimSettings, load
from pipeline.sim import check_timing, simulate
from pipeline.sim.build import (
    arena_bounds,
    build_controller,
    build_disturbance,
    build_scene,
    initial_conditions,
    sim_model_kwargs,
)


def build(cfg: DictConfig):
    """Every object of the run, validated: (scene, controller, disturbance, initial conditions, timing)."""
    scene = build_scene(cfg.scene)
    controller = build_controller(cfg.controller, scene)
    disturbance = build_disturbance(cfg.disturbance)
    x0 = initial_conditions(cfg.init, scene, cfg.scene)
    timing = load(cfg.camera, "camera", CameraTiming)
    sim = load(cfg.sim, "sim", SimSettings)
    check_timing(sim.dt, sim.horizon, timing.period)
    return scene, controller, disturbance, x0, timing


def check(cfg: DictConfig) -> None:
    """Preflight: build every object (no simulation)."""
    build(cfg)


def run(cfg: DictConfig) -> dict:
    """Run one batched simulation; returns `{"metrics": DataFrame, "result": SimResult, "run_dir": Path}`."""
    scene, controller, disturbance, x0, timing = build(cfg)  # validate everything before any work
    run_dir = Path(cfg.paths.output_dir)
    t0 = time.perf_counter()
    result = simulate(
        scene, controller, x0,
        dt=cfg.sim.dt, horizon=cfg.sim.horizon, delta=cfg.sim.delta,
        camera_period=timing.period, p_fail=timing.p_fail, disturbance=disturbance,
        seed=cfg.sim.seed, record_every=cfg.sim.record_every, stop_on_success=cfg.sim.stop_on_success,
        progress=len(x0) >= 1000, **sim_model_kwargs(cfg.sim),
    )
    elapsed = time.perf_counter() - t0
    run_dir.mkdir(parents=True, exist_ok=True)
    df = result.metrics_frame()
    df.to_csv(run_dir / "metrics.csv", index=False)
    result.save_npz(run_dir / "trajectories.npz")
    if cfg.get("plot", True):
        from pipeline.viz import save, trajectory_figure

        fig = trajectory_figure(
            scene, result.p, result.metrics["success"], arena=arena_bounds(cfg.scene),
            title=f"{controller.name} controller, disturbance {disturbance.name}, {cfg.sim.get('model', 'sampled')}",
        )
        save(fig, run_dir / "trajectories")
    med = df.time_to_target.dropna().median() if df.success.any() else float("nan")
    print(
        f"simulate ({cfg.sim.get('model', 'sampled')}): {controller.name} / {disturbance.name}: {len(df)} agents, "
        f"success {df.success.mean():.1%}, "
        f"collision {df.collision.mean():.1%}, median time {med:.2f} s, "
        f"{elapsed:.2f} s -> {run_dir}"
    )
    return {"metrics": df, "result": result, "run_dir": run_dir}


@stage_main("simulate", check=check)
def main(cfg: DictConfig) -> None:
    run(cfg)


if __name__ == "__main__":
    main()
