"""Figures and tables of the dense-field scenarios (pipeline.experiments.multi.dense; drawing code only)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402

from pipeline.control import Scene  # noqa: E402
from pipeline.experiments.multi.figures import COLORS, columns  # noqa: E402
from pipeline.experiments.report import draw_frame, figure_stem  # noqa: E402

EXTRA = ["timed_out"]


def draw_dense_fields(scen, ctx, res, out) -> None:
    t, per = res.tables["summary"], res.tables["per_scene"]
    first = Scene(**res.info["first"])
    vehicle = res.info.get("vehicle", "integrator")
    runs = {k[2:]: v for k, v in res.arrays.items() if k.startswith("p_")}
    fig, axes = plt.subplots(1, len(runs), figsize=(4.2 * len(runs), 4.4), squeeze=False)
    for ax, (ctrl, p) in zip(axes[0], runs.items()):
        draw_frame(ax, first, first.bounds)
        for n in range(p.shape[1]):
            ax.plot(p[:, n, 0], p[:, n, 1], color=COLORS.get(ctrl), lw=0.6)
        ax.set_title(f"{ctrl}", fontsize=9)
    last = scen.conditions(ctx)[-1][0]
    n = len(res.info["scenes"])
    out.figure(fig, figure_stem(scen.id), f"{first.name} ({vehicle}) under {last}: the benchmark's starts on the circle "
                                      f"of radius {scen.start_radius:g}, hybrid (dense design) vs smooth vs CBF.")
    out.table(columns(t, ["condition", "controller"]), f"tab_{scen.id}",
              f"Dense fields ({vehicle}; {n} scenes: {', '.join(res.info['scenes'])}): success and collisions with "
              f"95% Wilson intervals, stalls (traps), jumps and push-outs per agent, pooled over the scenes.")
    out.table(columns(per, ["scene", "condition", "controller"]), f"tab_{scen.id}_per_scene",
              f"Dense fields ({vehicle}), per scene.")
