"""Figures, tables and the animation of the unicycle scenarios (pipeline.experiments.multi.unicycle; drawing code only)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.config import build  # noqa: E402
from pipeline.experiments.paper.animation import frame_indices  # noqa: E402
from pipeline.experiments.report import draw_frame  # noqa: E402
from pipeline.viz import save_gif  # noqa: E402

STYLE = {"true_state": ("tab:blue", "-"), "camera": ("tab:red", "-"), "imu": ("tab:purple", "--"),
         "integrator": ("0.4", ":")}
COLUMNS = ["condition", "vehicle", "n", "success_rate", "success_lo", "success_hi", "collision_rate", "stalled",
           "median_time", "median_time_ratio", "paper_starts_time", "clearance_min", "mean_omega_saturation",
           "mean_heading_error_deg", "mean_heading_error_deg_hi", "mean_mode_jumps", "mean_cell_jumps",
           "total_pushouts", "mean_guard_frames"]


def _wrap_deg(a):
    return np.degrees(np.angle(np.exp(1j * a)))


def draw_unicycle(scen, ctx, res, out) -> None:
    a, t = res.arrays, res.tables["summary"]
    conds = [c for c in scen.conditions if f"p_{c}" in a]
    fig, (ax, axh) = plt.subplots(1, 2, figsize=(13, 4.4), gridspec_kw={"width_ratios": [1.4, 1]})
    draw_frame(ax, ctx.scene, ctx.arena)
    for key in [*conds, "integrator"]:
        p = a.get(f"p_{key}")
        if p is None:
            continue
        color, ls = STYLE.get(key, ("k", "-"))
        for n in range(p.shape[1]):
            ax.plot(p[:, n, 0], p[:, n, 1], ls, color=color, lw=1.0, label=key if n == 0 else None)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4)  # below: the field fills the arena
    ax.set_title(f"axle point of the unicycle (look-ahead d = {res.info['lookahead']:g}) and the single integrator",
                 fontsize=9)
    for c in conds:
        if c == "true_state":
            continue
        err = np.abs(_wrap_deg(a[f"thm_{c}"] - a[f"th_{c}"]))
        axh.plot(a[f"t_{c}"], np.nanmean(err, axis=1), color=STYLE[c][0], label=f"{c}: mean over drawn agents")
    axh.set_xlabel("t (s)")
    axh.set_ylabel("|heading error| (deg)")
    axh.legend(fontsize=7)
    axh.set_title("measured heading against the true one", fontsize=9)
    out.figure(fig, f"fig21_{scen.id}", f"The unicycle on {res.info['scene']} (SPEC §3.7): runs from the paper's "
               "starts and random starts under each perception condition, the single integrator from the same "
               "starts, and the heading error along the runs.")
    cap = (f"The unicycle on {res.info['scene']}: success/collision (Wilson CIs), time (and its median ratio to the "
           f"single integrator on the same starts; times from the paper's starts), min clearance of the axle point, "
           f"share of frames with |ω| saturated, heading error along the runs (imu noise "
           f"{res.info['imu_noise_deg']:.1f} deg).")
    h = res.info.get("errormap_heading_clean")
    if h:
        cap += (f" The pose map on clean images ({res.info['errormap']}): heading error mean {h['mean_deg']:.2f} deg, "
                f"p95 {h['p95_deg']:.2f} deg.")
    out.table(t[[c for c in COLUMNS if c in t.columns]], f"tab_{scen.id}", cap)
    if scen.gif:
        _gif(scen, ctx, res, out, next((c for c in ("camera", "imu") if c in conds), conds[0]))


def _gif(scen, ctx, res, out, cond: str) -> None:
    a, k = res.arrays, min(scen.gif_agent, res.arrays[f"p_{cond}"].shape[1] - 1)
    t, p, th, m, thm = a[f"t_{cond}"], a[f"p_{cond}"][:, k], a[f"th_{cond}"][:, k], a[f"m_{cond}"][:, k], \
        a[f"thm_{cond}"][:, k]
    done = np.flatnonzero(np.hypot(*(p - ctx.scene.p_T).T) <= ctx.delta)
    n = int(done[0]) + 1 if len(done) else len(t)
    cam = ctx.camera(scen.map_kind) if scen.maps else build(ctx.cfg.render, "render", scene=ctx.scene)
    caption = (f"the unicycle ({cond}) from ({p[0, 0]:g}, {p[0, 1]:g}) on {res.info['scene']}: the arena with its "
               "true pose (triangle) and perceived pose (cross and arrow), beside its camera view")
    path = unicycle_gif(out.dir / f"anim21_{scen.id}.gif", ctx, cam, t[:n], p[:n], th[:n], m[:n], thm[:n],
                        max_frames=max(8, round(60 * min(1.0, ctx.scale))))
    out.items.append({"kind": "animation", "files": [path.name], "caption": caption})


def unicycle_gif(path, ctx, cam, t, p, th, m, thm, *, fps: int = 10, max_frames: int = 60, dpi: int = 80):
    """An animated GIF: left the arena, the run's trail, the true pose and the perceived one; right the frame the
    camera renders at the true pose (what the pose map reads). `p`, `m` `(T, 2)`, `th`, `thm` `(T,)`."""
    idx = frame_indices(len(t), max_frames)
    (x0, x1), (y0, y1) = ctx.arena
    fig, (ax, axc) = plt.subplots(1, 2, figsize=(10, 3.6))
    draw_frame(ax, ctx.scene, ctx.arena)
    trail, = ax.plot([], [], "-", color="tab:red", lw=1.2)
    pose, = ax.plot([], [], marker=(3, 0, 0), ms=9, color="tab:red", mec="k", ls="none", zorder=6)
    seen, = ax.plot([], [], "x", ms=8, mew=2, color="tab:blue", zorder=7)
    arrow = ax.quiver([m[0, 0]], [m[0, 1]], [1.0], [0.0], color="tab:blue", scale=25, width=0.005, zorder=7)
    im = axc.imshow(cam.render(p[:1], heading=th[:1])[0], extent=(x0, x1, y0, y1), origin="upper",
                    interpolation="nearest")
    axc.set_xticks([])
    axc.set_yticks([])
    axc.set_title("its camera", fontsize=9)
    head = fig.suptitle("", fontsize=10)

    def update(j):
        k = idx[j]
        trail.set_data(p[: k + 1, 0], p[: k + 1, 1])
        pose.set_data([p[k, 0]], [p[k, 1]])
        pose.set_marker((3, 0, np.degrees(th[k]) - 90.0))  # the triangle's apex along the heading
        seen.set_data([m[k, 0]], [m[k, 1]])
        arrow.set_offsets([m[k]])
        arrow.set_UVC([np.cos(thm[k])], [np.sin(thm[k])])
        im.set_data(cam.render(p[k:k + 1], heading=th[k:k + 1])[0])
        head.set_text(f"t = {t[k]:.2f} s, heading error {abs(_wrap_deg(thm[k] - th[k])):.1f} deg")
        return trail, pose, seen, arrow, im, head

    return save_gif(fig, update, len(idx), path, fps=fps, dpi=dpi)
