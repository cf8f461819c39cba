"""What the 20 Hz sample-and-hold costs: the two time models against the dt -> 0 limit (issue 12 §1).

`model_comparison` gives the table (time to target, jumps, path length per start for the sampled model,
the continuous model and the sampled model with `dt = camera.period = limit_dt`); `zigzag_figure` draws
both arcs along the diamond's edge. Both run the literal sample-and-hold rule by default (`guard=False`: the
zigzag issue 12 measured); `guard=True` runs SPEC §3.3's sampled-data guard (the controller's default). Pure: no I/O.
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.control import HybridController, Scene
from pipeline.sim.simulator import CameraSettings, SimSettings, simulate
from pipeline.viz import draw_scene

EDGE_STARTS = ((-12.0, 2.0), (-45.0, 0.3), (-37.0, -17.0), (-30.0, 20.0), (10.0, 25.0))


def model_comparison(scene: Scene, starts=EDGE_STARTS, *, dt: float = 0.01, camera_period: float = 0.05,
                     limit_dt: float = 0.0005, horizon: float = 30.0, guard: bool = False) -> pd.DataFrame:
    """One row per start: time to target, jumps and path length of the three runs, and the relative errors."""
    x0 = np.asarray(starts, dtype=float)
    ctrl = HybridController(scene, guard=guard)
    runs = {
        "sampled": simulate(scene, ctrl, x0, sim=SimSettings(dt=dt, horizon=horizon),
                            camera=CameraSettings(period=camera_period), record=False),
        "continuous": simulate(scene, ctrl, x0, sim=SimSettings(dt=dt, horizon=horizon, model="continuous"),
                               record=False),
        "limit": simulate(scene, ctrl, x0, sim=SimSettings(dt=limit_dt, horizon=horizon),
                          camera=CameraSettings(period=limit_dt), record=False),
    }
    df = pd.DataFrame({"x0": x0[:, 0], "y0": x0[:, 1]})
    for name, res in runs.items():
        m = res.metrics
        df[f"t_{name}"] = m["time_to_target"]
        df[f"jumps_{name}"] = m["jumps"]
        df[f"path_{name}"] = m["path_length"]
    for name in ("sampled", "continuous"):
        df[f"err_{name}_%"] = 100 * (df[f"t_{name}"] - df["t_limit"]) / df["t_limit"]
    return df


def zigzag_figure(scene: Scene, start=(-12.0, 2.0), *, dt: float = 0.01, camera_period: float = 0.05,
                  horizon: float = 12.0, guard: bool = False):
    """The arc from `start` under both models: whole path, and a zoom on the diamond's edge (the zigzag)."""
    from matplotlib.figure import Figure

    x0 = np.asarray([start], dtype=float)
    ctrl = HybridController(scene, guard=guard)
    samp = simulate(scene, ctrl, x0, sim=SimSettings(dt=dt, horizon=horizon, record_every=1),
                    camera=CameraSettings(period=camera_period))
    cont = simulate(scene, ctrl, x0, sim=SimSettings(dt=dt, horizon=horizon, model="continuous", record_every=1))
    fig = Figure(figsize=(11, 4))
    axes = fig.subplots(1, 2)
    ts, tc = samp.metrics["time_to_target"][0], cont.metrics["time_to_target"][0]
    for ax in axes:
        draw_scene(ax, scene)
        ax.plot(samp.p[:, 0, 0], samp.p[:, 0, 1], "-", color="tab:red", lw=0.9,
                label=f"sampled, camera {1 / camera_period:g} Hz: {ts:.2f} s")
        ax.plot(cont.p[:, 0, 0], cont.p[:, 0, 1], "-", color="tab:blue", lw=1.2,
                label=f"continuous: {tc:.2f} s")
    axes[0].legend(loc="lower right", fontsize=8)
    axes[0].set_title(f"hybrid controller from {tuple(start)}", fontsize=10)
    # zoom on the part of the edge the vehicle slides along
    a, b = scene.to_frame(cont.p[:, 0])
    on_edge = np.abs(np.abs(a) + np.abs(b) - scene.c) < 0.3
    centre = cont.p[on_edge, 0].mean(axis=0) if on_edge.any() else scene.p_0
    axes[1].set_xlim(centre[0] - 1.5, centre[0] + 1.5)
    axes[1].set_ylim(centre[1] - 1.0, centre[1] + 1.0)
    axes[1].set_title("zoom on the diamond's edge: the zigzag of sample-and-hold", fontsize=10)
    return fig
