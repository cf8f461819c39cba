"""Fig. 4 of the paper ("Scheme of the closed-loop system"), drawn from code.

camera `h(p)` -> perception map `l(θ)` -> hybrid supervisor (flow set `C`, jump set `D`, mode `q`) ->
gradient flow `-k ∇V_q` -> vehicle `p_dot = u`, with the inputs where the simulator applies them: the
measurement disturbance `e` (SPEC §3.5, added to the perceived position: `m = l(θ) + e`), camera failures `p_fail` (the
last estimate held) and occlusions (on the image). Pure drawing: returns the Figure, no I/O.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
from matplotlib.figure import Figure  # noqa: E402
from matplotlib.patches import Circle, FancyArrowPatch, FancyBboxPatch  # noqa: E402

# block name -> (centre x, centre y, title, body); axes coordinates in a 16 x 7 canvas
BLOCKS = {
    "camera": (1.6, 4.6, "camera", r"$\theta = h(p)$"),
    "map": (5.0, 4.6, "perception map", r"$\ell(\theta) \approx p$"),
    "supervisor": (10.0, 4.6, "hybrid supervisor",
                   "flow set $C$: $V_q(m) \\leq \\chi V_{3-q}(m)$\n"
                   "jump set $D$: $V_q(m) \\geq (\\chi-\\lambda) V_{3-q}(m)$\n"
                   "mode $q \\in \\{1, 2\\}$,  $q^+ = 3 - q$"),
    "flow": (14.3, 4.6, "gradient flow", r"$u = -k \nabla V_q(m)$"),
    "vehicle": (10.0, 1.3, "vehicle", r"$\dot p = u,\ |u| \leq u_{max}$"),
}
SIZES = {"camera": (2.6, 1.3), "map": (3.0, 1.3), "supervisor": (4.7, 2.0), "flow": (3.0, 1.3), "vehicle": (3.4, 1.2)}
JUNCTION = (7.3, 4.6, 0.25)  # m = l(theta) + e


def _box(ax, key):
    x, y, title, body = BLOCKS[key]
    w, h = SIZES[key]
    ax.add_patch(FancyBboxPatch((x - w / 2, y - h / 2), w, h, boxstyle="round,pad=0.05,rounding_size=0.15",
                                fc="#eef3fb" if key != "supervisor" else "#fdf1e3", ec="k", lw=1.2))
    ax.text(x, y + h / 2 - 0.28, title, ha="center", va="center", fontsize=10, weight="bold")
    ax.text(x, y - 0.15, body, ha="center", va="center", fontsize=9, linespacing=1.5)
    return x, y, w, h


def _arrow(ax, a, b, text=None, text_xy=None, color="k", ls="-"):
    ax.add_patch(FancyArrowPatch(a, b, arrowstyle="-|>", mutation_scale=14, lw=1.3, color=color, ls=ls,
                                 shrinkA=0, shrinkB=0))
    if text:
        x, y = text_xy or ((a[0] + b[0]) / 2, (a[1] + b[1]) / 2 + 0.25)
        ax.text(x, y, text, ha="center", va="bottom", fontsize=9, color=color)


def scheme_figure() -> Figure:
    """The closed loop as a block diagram, names as in the paper; disturbance and failure inputs in red."""
    fig = Figure(figsize=(11, 5))
    ax = fig.add_subplot(111)
    ax.set_xlim(0, 16)
    ax.set_ylim(0, 7)
    ax.set_axis_off()
    box = {k: _box(ax, k) for k in BLOCKS}

    def right(k):
        x, y, w, _ = box[k]
        return x + w / 2, y

    def left(k):
        x, y, w, _ = box[k]
        return x - w / 2, y

    _arrow(ax, right("camera"), left("map"), r"$\theta$")
    jx, jy, jr = JUNCTION
    ax.add_patch(Circle((jx, jy), jr, fc="white", ec="k", lw=1.2))
    ax.text(jx, jy, "+", ha="center", va="center", fontsize=11)
    _arrow(ax, right("map"), (jx - jr, jy), r"$\ell(\theta)$")
    _arrow(ax, (jx + jr, jy), left("supervisor"), r"$m$")
    _arrow(ax, right("supervisor"), left("flow"), r"$q$")
    # flow -> vehicle (down and back left), vehicle -> camera (left and up): the loop through p
    fx, fy, _, fh = box["flow"]
    vx, vy, vw, _ = box["vehicle"]
    ax.plot([fx, fx], [fy - fh / 2, vy], color="k", lw=1.3)
    _arrow(ax, (fx, vy), (vx + vw / 2, vy), r"$u$", (fx - 0.9, vy + 0.05))
    cx, cy, _, ch = box["camera"]
    ax.plot([vx - vw / 2, cx], [vy, vy], color="k", lw=1.3)
    _arrow(ax, (cx, vy), (cx, cy - ch / 2), r"$p$", (cx - 0.3, (vy + cy - ch / 2) / 2))
    # where the simulator perturbs the loop
    red = "tab:red"
    mx, my, _, mh = box["map"]
    _arrow(ax, (cx, 6.5), (cx, cy + ch / 2), "occlusion (clouds)", (cx, 6.55), color=red)
    _arrow(ax, (mx, 6.5), (mx, my + mh / 2), r"camera failure $p_{fail}$: last $\ell$ held", (mx, 6.55), color=red)
    _arrow(ax, (jx, 5.95), (jx, jy + jr), r"disturbance $e$ (noise, alternating, adversarial)", (jx + 1.6, 6.0),
           color=red)
    ax.text(8.0, 0.15, "one frame every camera period (sim.model: sampled); evaluated along the flow with "
            "jumps located in time (sim.model: continuous)", ha="center", fontsize=8, color="0.35")
    ax.set_title("Closed-loop scheme of the perception-based hybrid controller (paper Fig. 4)", fontsize=11)
    return fig
