"""Figures and tables of the several-obstacle scenarios (pipeline.experiments.multi.fields; drawing code only)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from pipeline.control import Scene  # noqa: E402
from pipeline.experiments.report import draw_frame, figure_stem  # noqa: E402
from pipeline.viz import legend_outside  # noqa: E402

COLORS = {"hybrid": "tab:blue", "smooth": "tab:orange", "cbf": "tab:green"}
SUMMARY_COLUMNS = ["n", "success_rate", "success_lo", "success_hi", "collision_rate", "stalled", "median_time",
                   "clearance_min", "mean_cell_jumps", "mean_mode_jumps", "mean_pushouts", "total_pushouts",
                   "mean_guard_frames"]


def columns(df, first: list[str]):
    return df[[c for c in first + SUMMARY_COLUMNS if c in df.columns]]


def draw_multi_cells(scen, ctx, res, out) -> None:
    a, scene = res.arrays, ctx.scene
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.4))
    ax = axes[0]
    M = scene.n_obstacles
    ax.pcolormesh(a["x"], a["y"], a["cell"], cmap=plt.get_cmap("Pastel1", max(M, 2)), vmin=-0.5,
                  vmax=max(M, 2) - 0.5, shading="nearest")
    ax.contourf(a["x"], a["y"], a["band"].astype(float), levels=[0.5, 1.5], hatches=["...."], colors="none")
    arr = scene.arrays
    for c, R in zip(arr["center"], arr["R"]):
        ax.add_patch(Circle(c, R, fill=False, ls=":", color="k", lw=0.8))
    draw_frame(ax, scene, ctx.arena)
    ax.set_title(f"cells of the locally active obstacle (dotted: $D_i$; hatched: hysteresis band h = {res.info['h']:g})",
                 fontsize=9)
    ax = axes[1]
    V = a["V"]
    finite = np.isfinite(V)
    logV = np.log10(np.where(finite, V, np.nan) - np.nanmin(V[finite]) + 1.0)  # the barriers show beside |p - p_T|²
    levels = np.unique(np.nanquantile(logV, np.linspace(0.02, 0.98, 18)))
    ax.contour(a["x"], a["y"], logV, levels=levels, colors="k", linewidths=0.5)
    p, i = a["p"], a.get("i")
    tab10 = plt.get_cmap("tab10")
    for n in range(p.shape[1]):
        if i is None:
            ax.plot(p[:, n, 0], p[:, n, 1], lw=1.5, label=f"run from ({p[0, n, 0]:g}, {p[0, n, 1]:g})")
            continue
        ax.scatter(p[:, n, 0], p[:, n, 1], c=i[:, n], cmap=tab10, vmin=0, vmax=9, s=3, zorder=4)
    if i is not None:  # the colour key: which obstacle was active
        for k in np.unique(i[np.isfinite(i)]).astype(int):
            ax.plot([], [], "o", ms=4, color=tab10(k % 10), label=f"active obstacle {k}")
    draw_frame(ax, scene, ctx.arena)
    legend_outside(ax, below=True, ncol=4)
    ax.set_title(r"active potential $\min_q V_i^q$ on each cell; true-state runs coloured by the active obstacle",
                 fontsize=9)
    out.figure(fig, "fig17_multi_cells", "Several obstacles (SPEC §3.6): the cells of the locally active obstacle with "
               "each obstacle's diamond and D_i, the hysteresis band, the active level sets and true-state runs.")
    out.table(res.tables["obstacles"], "tab_multi_cells",
              f"The field's obstacles: apex c_i, barrier reach rho_i, R_i, V1 slack (|p_T - c_i| - R_i), share of the "
              f"arena in each cell. {res.info['summary'].splitlines()[0]}")


def draw_multi_adversarial(scen, ctx, res, out) -> None:
    t = res.tables["summary"]
    fig, ax = plt.subplots(figsize=(6.5, 4))
    for ctrl, g in t.groupby("controller", sort=False):
        ax.plot(g["eps"], g["success_rate"], "o-", color=COLORS.get(ctrl), label=ctrl)
        ax.fill_between(g["eps"], g["success_lo"], g["success_hi"], color=COLORS.get(ctrl), alpha=0.2)
    ax.set_xlabel("ε (adversary, SPEC §3.5, in the nearest obstacle's frame)")
    ax.set_ylabel("success rate (95% Wilson CI)")
    ax.set_ylim(-0.03, 1.03)
    legend_outside(ax, fontsize=8)
    n = len(res.info["scenes"])
    ax.set_title(f"starts near every obstacle's K, {n} random fields", fontsize=9)
    out.figure(fig, "fig18_multi_adversarial", f"Proposition 1 behind every obstacle: success versus ε from starts "
               f"near each obstacle's set K on {n} random valid fields (hybrid vs smooth vs CBF).")
    out.table(columns(t, ["eps", "controller"]), "tab_multi_adversarial",
              "Success versus ε near every obstacle's K (Wilson CIs), with jumps by kind and push-outs per agent.")


def _field_runs(ax, scene: Scene, arena, runs: dict, title: str) -> None:
    draw_frame(ax, scene, arena)
    for ctrl, p in runs.items():
        for n in range(p.shape[1]):
            ax.plot(p[:, n, 0], p[:, n, 1], color=COLORS.get(ctrl), lw=1.0, label=ctrl if n == 0 else None)
    ax.legend(fontsize=7, loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=4)  # below: the field fills the arena
    ax.set_title(title, fontsize=9)


def draw_multi_monte_carlo(scen, ctx, res, out) -> None:
    t = res.tables["summary"]
    first = Scene(**res.info["first"]) if isinstance(res.info.get("first"), dict) else None
    fig, axes = plt.subplots(1, 2, figsize=(13, 4.2))
    conds = list(dict.fromkeys(t["condition"]))
    ctrls = list(dict.fromkeys(t["controller"]))
    width = 0.8 / len(ctrls)
    for k, ctrl in enumerate(ctrls):
        g = t[t["controller"] == ctrl].set_index("condition").loc[conds]
        x = np.arange(len(conds)) + k * width
        axes[0].bar(x, g["success_rate"], width, color=COLORS.get(ctrl), label=ctrl,
                    yerr=np.clip([g["success_rate"] - g["success_lo"], g["success_hi"] - g["success_rate"]], 0, None),
                    capsize=3)  # a Wilson bound at a rate of 1 can sit an ulp below it
    axes[0].set_xticks(np.arange(len(conds)) + 0.4 - width / 2, conds)
    axes[0].set_ylabel("success rate (95% Wilson CI)")
    axes[0].set_ylim(0, 1.05)
    legend_outside(axes[0], below=True, fontsize=8)  # a rate of 1 fills the axes
    axes[0].set_title(f"{len(res.info['scenes'])} random valid fields x {int(t['n'].iloc[0] / len(res.info['scenes']))} "
                      "starts (true state)", fontsize=9)
    if first is not None:
        runs = {c: res.arrays[f"p_{c}"] for c in ctrls if f"p_{c}" in res.arrays}
        _field_runs(axes[1], first, first.bounds, runs, f"the first field ({first.name}): the same starts")
    out.figure(fig, "fig19_multi_monte_carlo", "Monte Carlo over random valid fields (3–5 discs): success by "
               "condition and controller, and runs on the first field.")
    out.table(columns(t, ["condition", "controller"]), "tab_multi_monte_carlo",
              "Random valid fields x starts x disturbances x controllers: success/collision with Wilson CIs, outcome "
              "shares, median time, min clearance, jumps by kind, push-outs and guard frames per agent (means).")
    out.table(columns(res.tables["per_scene"], ["scene", "condition", "controller"]), "tab_multi_monte_carlo_fields",
              "The same per field.")


def draw_multi_camera(scen, ctx, res, out) -> None:
    t = res.tables["summary"]
    fig, ax = plt.subplots(figsize=(8, 5))
    runs = {c: res.arrays[f"p_{c}"] for c in t["controller"] if f"p_{c}" in res.arrays}
    clouds = f"{res.info['occlusion']} clouds" if res.info["occlusion"] != "none" else "clean images"
    _field_runs(ax, ctx.scene, ctx.arena, runs, f"camera in the loop: {res.info.get('drawn', clouds)}")
    for c in runs:
        m = res.arrays[f"m_{c}"]
        ax.plot(m[:, :, 0].ravel(), m[:, :, 1].ravel(), ".", ms=0.8, color=COLORS.get(c), alpha=0.3)
    where = f"{ctx.scene.n_obstacles}-disc scene {ctx.scene.name!r}"
    out.figure(fig, figure_stem(scen.id), f"Hybrid, smooth and CBF on the {where} with the CNN in the loop on "
               f"{clouds} (drawn: {res.info.get('drawn', clouds)}; dots: the perceived positions).")
    out.table(columns(t, ["condition", "controller"]) .assign(perception_error_mean=t["perception_error_mean"]),
              f"tab_{scen.id}", f"Camera in the loop on the {where} (learned map, {clouds}): outcomes with Wilson CIs "
              "and the mean perception error along the runs.")
