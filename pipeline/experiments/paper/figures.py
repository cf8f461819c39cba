"""Figures and tables of each scenario, under the paper's figure numbers (drawing code only: restyling a
figure re-draws from the cached results and never re-simulates).

Each scenario names its drawing function here (`Scenario.figures`); `pipeline.experiments.report.FIGURES` lists
the paper's figures in its order.
"""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.colors import ListedColormap  # noqa: E402
from matplotlib.patches import Circle  # noqa: E402

from pipeline.experiments.paper.animation import leader_follower_gif  # noqa: E402
from pipeline.experiments.paper.scheme import scheme_figure  # noqa: E402
from pipeline.experiments.report import draw_frame  # noqa: E402
from pipeline.viz import legend_outside  # noqa: E402


def draw_coverings(scen, ctx, res, out) -> None:
    fig, axes = plt.subplots(2, 1, figsize=(6.5, 7.2), layout="constrained")  # the paper's: q = 1 top, q = 2 bottom
    x, y = res.arrays["x"], res.arrays["y"]
    for q, ax in zip((1, 2), axes):
        V = res.arrays[f"V{q}"]
        finite = np.isfinite(V)
        ax.contourf(x, y, finite.astype(float), levels=[0.5, 1.5], colors=["#cfe3f7" if q == 1 else "#f7dccf"])
        levels = np.quantile(V[finite], np.linspace(0.02, 0.9, 12))
        ax.contour(x, y, np.where(finite, V, np.nan), levels=np.unique(levels), colors="k", linewidths=0.5)
        draw_frame(ax, ctx.scene, ctx.arena)
        ax.set_title(f"$O_{q}$ (shaded) and level sets of $V_{q}$")
    out.figure(fig, "fig3_coverings", "Coverings O_1, O_2 (shaded) with level sets of V_1, V_2 (paper Fig. coverings).")
    out.table(res.tables["coverings"], "tab_coverings", "Share of the arena in each covering set.")


def draw_sensitive_set(scen, ctx, res, out) -> None:
    eps = res.info["eps"]
    x, y, keep = res.arrays["x"], res.arrays["y"], res.arrays["keep"]
    cmap = ListedColormap(["#d62728", "#1f77b4", "#ff7f0e"])  # stall, K_1, K_2
    cases = ["clean", f"adversarial eps={eps}"]
    fig, axes = plt.subplots(2, 2, figsize=(11, 6.5), layout="constrained")  # no title over the panel above
    for i, ctrl in enumerate(("smooth", "hybrid")):
        for j, case in enumerate(cases):
            grid = np.full(keep.shape, np.nan)
            grid[keep] = res.arrays[f"{ctrl}|{case}"]
            ax = axes[i, j]
            ax.pcolormesh(x, y, grid.reshape(len(y), len(x)), cmap=cmap, vmin=0, vmax=2, shading="nearest")
            draw_frame(ax, ctx.scene, ctx.arena)
            ax.set_title(f"{ctrl}, {case}", fontsize=9)
    fig.suptitle("Basins $K_1$ (blue: passes above), $K_2$ (orange: below); red: never reaches the target", fontsize=10)
    out.figure(fig, "fig2_sensitive_set",
               f"Basins K_1, K_2 of the smooth flow and the set K between them; with an adversary of size {eps} "
               "the smooth flow stalls on a band around K while the hybrid controller does not (paper Fig. obstacle problem).")
    out.table(res.tables["sensitive_set"], "tab_sensitive_set", "Share of grid initial conditions in K_1, K_2, stalled.")


def draw_noise_failure(scen, ctx, res, out) -> None:
    a = res.arrays
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    ax = axes[0]
    draw_frame(ax, ctx.scene, ctx.arena)
    for i in range(a["single_p"].shape[1]):
        ax.plot(a["single_m"][:, i, 0], a["single_m"][:, i, 1], ".", ms=1.5, color="0.6",
                label="perceived positions" if i == 0 else None)
        start = a["single_p"][0, i]
        ax.plot(a["single_p"][:, i, 0], a["single_p"][:, i, 1], lw=1.5, label=f"from ({start[0]:g}, {start[1]:g})")
    legend_outside(ax, below=True)
    ax.set_title(f"hybrid, CNN in the loop, noise σ={res.info['sigma']}, {res.info['p_fail']:.0%} camera failure",
                 fontsize=9)
    ax = axes[1]
    draw_frame(ax, ctx.scene, ctx.arena)
    ax.plot(a["lead_p"][:, 0, 0], a["lead_p"][:, 0, 1], color="k", lw=1.5, label="leader")
    ax.plot(a["foll_p"][:, 0, 0], a["foll_p"][:, 0, 1], color="tab:green", lw=1.5, label="follower")
    ax.plot(a["foll_target"][:, 0, 0], a["foll_target"][:, 0, 1], ".", ms=1.5, color="tab:olive",
            label="leader as perceived by the follower")
    legend_outside(ax, below=True)
    ax.set_title("leader-follower", fontsize=9)
    _gif(ctx, out, "anim7_noise_failure", "leader and follower under noise and camera failure: the arena, the "
         "follower's camera frame and the perceived leader", a["foll_t"], a["lead_p"][:, 0], a["foll_p"][:, 0],
         a["foll_target"][:, 0])
    out.figure(fig, "fig7_robustness_noise_failure",
               "Hybrid controller with the CNN in the loop under noise and camera failure: single vehicle from "
               "both initial conditions (grey: perceived positions) and leader-follower (paper Fig. robustness).")
    out.table(res.tables["metrics"][["role", "x0", "y0", "success", "outcome", "collision", "time_to_target", "min_clearance",
                                     "jumps", "final_error"]],
              "tab_noise_failure", "Per-vehicle outcomes of the noise/failure scenario.")


def draw_occlusion(scen, ctx, res, out) -> None:
    a = res.arrays
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for ax, kind in zip(axes, ("clean", "occluded")):
        draw_frame(ax, ctx.scene, ctx.arena)
        ax.plot(a[f"{kind}_lead_p"][:, 0], a[f"{kind}_lead_p"][:, 1], "k", lw=1.5, label="leader")
        ax.plot(a[f"{kind}_foll_p"][:, 0], a[f"{kind}_foll_p"][:, 1], color="tab:green", lw=1.5, label="follower")
        ax.plot(a[f"{kind}_foll_target"][:, 0], a[f"{kind}_foll_target"][:, 1], ".", ms=2, color="tab:blue",
                label="perceived leader")
        ax.set_title(f"map trained on {kind} images; {res.info['level']} clouds "
                     f"(mean tracking error {np.nanmean(a[f'{kind}_err']):.2f})", fontsize=9)
        ax.legend(fontsize=7, loc="lower right")
    _gif(ctx, out, "anim6_occlusion", f"follower with the occlusion-trained map on {res.info['level']} clouds: the "
         "arena, the follower's camera frame with its clouds and the perceived leader",
         np.arange(len(a["occluded_foll_p"])) * (ctx.frame_period or ctx.dt), a["occluded_lead_p"],
         a["occluded_foll_p"], a["occluded_foll_target"], level=res.info["level"])
    out.figure(fig, "fig6_occlusion",
               "Follower with the map trained without and with occlusion, tested on occluded frames (paper Fig. occlusion).")
    cols = ["map", "occlusion", "n", "success_rate", "success_lo", "success_hi", "success_practical",
            "collision_rate", "reached", "stalled", "timed_out", "tracking_error_mean", "final_error_median",
            "final_p90", "within_3_units", "clearance_median", "clearance_p05", "clearance_min", "mean_jumps"]
    out.table(res.tables["summary"][[c for c in cols if c in res.tables["summary"]]], "tab_occlusion",
              "Followers from random initial conditions on occluded frames, per perception map: success "
              "(|p - p_T| <= delta, 95% CIs), mean error of the perceived leader, median final distance to "
              "the target, share ending within 3 units.")


def draw_leader_follower(scen, ctx, res, out) -> None:
    a = res.arrays
    frames = res.info["frames"]
    fig, axes = plt.subplots(1, len(frames), figsize=(5 * len(frames), 3.4))
    for ax, f, k, row in zip(np.atleast_1d(axes), frames, a["idx"], res.tables["instants"].itertuples()):
        V = a[f"V_{f}"]
        fin = np.isfinite(V)
        if fin.any():
            ax.contour(a["x"], a["y"], np.where(fin, V, np.nan),
                       levels=np.unique(np.quantile(V[fin], np.linspace(0.01, 0.8, 12))), linewidths=0.6)
        draw_frame(ax, ctx.scene, ctx.arena)
        ax.plot(a["lead_p"][: k + 1, 0], a["lead_p"][: k + 1, 1], "k", lw=1)
        ax.plot(a["foll_p"][: k + 1, 0], a["foll_p"][: k + 1, 1], color="tab:green", lw=1)
        ax.plot(*a["foll_target"][k], "o", color="tab:blue", ms=5)
        ax.set_title(f"frame {f} (t = {row.t:.2f} s), q = {row.mode_q}", fontsize=9)
    out.figure(fig, "fig5_leader_follower_level_sets",
               "Level sets of the follower's V_q around the moving target (the perceived leader) at three "
               "instants (paper Fig. level sets).")
    out.table(res.tables["instants"], "tab_leader_follower_instants", "Follower state at the plotted instants.")


def draw_perception_closeness(scen, ctx, res, out) -> None:
    p, m, eps = res.arrays["p"], res.arrays["m"], res.info["eps"]
    fig, ax = plt.subplots(figsize=(8, 4.5))
    draw_frame(ax, ctx.scene, ctx.arena)
    for c in p[:: max(1, len(p) // 150)]:
        ax.add_patch(Circle(c, max(eps, 1e-3), color="tab:blue", alpha=0.06, lw=0))
    ax.plot(p[:, 0], p[:, 1], "tab:blue", lw=1.5, label="true position p")
    ax.plot(m[:, 0], m[:, 1], ".", ms=2, color="tab:red", label="CNN prediction l(h(p))")
    ax.set_title(f"perception closeness: ε-tube with ε = {eps:.3f}", fontsize=9)
    ax.legend(fontsize=8, loc="lower right")
    out.figure(fig, "fig1_perception_closeness",
               "A closed-loop trajectory with the CNN's predictions inside the ε-tube of the error map (paper Fig. closeness).")
    out.table(res.tables["closeness"], "tab_perception_closeness", "Perception error along the trajectory vs ε.")


# one style per controller, so that equal curves stay apart: marker, line style, a small shift along ε
STYLES = [("o", "-", 10), ("s", "--", 7), ("^", ":", 5), ("D", "-.", 4), ("v", (0, (3, 1, 1, 1)), 3)]


def draw_robustness_sweep(scen, ctx, res, out, stem: str = "fig8_robustness_sweep") -> None:
    df = res.tables["sweep"]
    dists = list(dict.fromkeys(df["disturbance"]))
    ctrls = list(dict.fromkeys(df["controller"]))
    rows = [("success", "strict success: |p - p_T| <= δ")]
    if "practical_success_rate" in df:
        rows.append(("practical", "practical success: |p - p_T| <= δ + ε, no collision"))
    span = float(df["eps"].max() - df["eps"].min()) or 1.0
    fig, axes = plt.subplots(len(rows), len(dists), figsize=(5.5 * len(dists), 3.4 * len(rows)), squeeze=False,
                             layout="constrained")
    for i, (key, what) in enumerate(rows):
        rate = "success_rate" if key == "success" else "practical_success_rate"
        for ax, dist in zip(axes[i], dists):
            for k, ctrl in enumerate(ctrls):
                g = df[(df.disturbance == dist) & (df.controller == ctrl)]
                marker, ls, ms = STYLES[k % len(STYLES)]
                x = g.eps + (k - (len(ctrls) - 1) / 2) * 0.012 * span
                line, = ax.plot(x, g[rate], marker=marker, ls=ls, ms=ms, mfc="none", mew=1.5, label=ctrl)
                ax.fill_between(x, g[f"{key}_lo"], g[f"{key}_hi"], alpha=0.12, color=line.get_color(), lw=0)
            ax.set(xlabel="ε", ylabel="success rate", ylim=(-0.05, 1.05), title=f"{dist}: {what}")
            ax.title.set_fontsize(9)
            ax.grid(alpha=0.3)
    legend_outside(axes[0, -1], fontsize=8)
    delta = getattr(ctx, "delta", None)
    out.figure(fig, stem, "Success rate against the disturbance size ε from initial conditions near K: "
               "Proposition 1 (smooth and CBF stall) against Theorem 1 (hybrid is robust). "
               + (f"Top: strict success (|p - p_T| <= δ{f' = {delta:g}' if delta is not None else ''}); bottom: "
                  "practical success (|p - p_T| <= δ + ε without a collision: under a bias of size ε the equilibrium "
                  "moves by up to ε, so from ε near δ on the strict criterion can count a vehicle resting at "
                  "p_T + ε as a failure). " if len(rows) == 2 else "Strict success "
                  "(|p - p_T| <= δ). ")
               + "One marker and line style per controller, each shifted slightly along ε so that equal rates "
                 "stay visible; shaded: 95% Wilson CIs.")
    out.table(df, "tab_robustness_sweep", "Success rate vs ε (95% Wilson CIs), per disturbance and controller: "
              "strict (|p - p_T| <= δ) and practical (<= δ + ε, no collision).")


def draw_monte_carlo(scen, ctx, res, out) -> None:
    cols = ["condition", "controller", "n", "success_rate", "success_lo", "success_hi", "success_practical",
            "collision_rate", "reached", "stalled", "timed_out", "median_time", "final_median", "final_p90",
            "clearance_median", "clearance_p05", "clearance_min", "mean_jumps"]
    df = res.tables["summary"]
    dp = float(df["delta_practical"].iloc[0]) if "delta_practical" in df else float("nan")
    out.table(df[[c for c in cols if c in df]], "tab1_monte_carlo",
              f"Monte Carlo over random initial conditions: success (|p - p_T| <= delta, 95% Wilson CIs) and at the "
              f"practical delta = {dp:g} (about the perception error near the target), collision rate, outcome "
              "classes (reached / stalled: an undesired equilibrium away from the target / timed out), median "
              "time to target, final distance (median, p90), per-agent minimum clearance (median and 5th "
              "percentile over agents; global minimum), mean jumps, per condition and controller.")
    df = res.tables["summary"]
    conds = list(dict.fromkeys(df["condition"]))
    ctrls = list(dict.fromkeys(df["controller"]))
    fig, ax = plt.subplots(figsize=(max(6, 1.6 * len(conds)), 3.6))
    w = 0.8 / len(ctrls)
    for i, ctrl in enumerate(ctrls):
        g = df[df.controller == ctrl].set_index("condition").reindex(conds)
        xs = np.arange(len(conds)) + (i - (len(ctrls) - 1) / 2) * w
        yerr = np.clip([g.success_rate - g.success_lo, g.success_hi - g.success_rate], 0, None)
        ax.bar(xs, g.success_rate, w, label=ctrl, yerr=yerr, capsize=2)
    ax.set_xticks(np.arange(len(conds)), conds, rotation=20, ha="right", fontsize=7)
    ax.set(ylabel="success rate", ylim=(0, 1.05))
    legend_outside(ax, fontsize=8)  # beside the bars: a rate of 1 fills the axes
    out.figure(fig, "fig9_monte_carlo", "Monte Carlo success rates with 95% CIs per condition and controller.")


def draw_authors_code(scen, ctx, res, out) -> None:
    df = res.tables["sweep"]
    scenes = list(dict.fromkeys(df["scene"]))
    dists = list(dict.fromkeys(df["disturbance"]))
    fig, axes = plt.subplots(len(dists), len(scenes), figsize=(5.2 * len(scenes), 3.2 * len(dists)), squeeze=False)
    for i, dist in enumerate(dists):
        for j, sc in enumerate(scenes):
            ax = axes[i, j]
            for ctrl, g in df[(df.disturbance == dist) & (df.scene == sc)].groupby("controller", sort=False):
                ax.plot(g.eps, g.success_rate, "o-", label=ctrl)
            ax.set(xlabel="ε", ylabel="success rate", ylim=(-0.03, 1.03), title=f"scene {sc}, {dist}")
            ax.legend(fontsize=7)
            ax.grid(alpha=0.3)
    out.figure(fig, "fig10_authors_code_vs_default",
               "The authors' released-code scene next to the default scene: success vs ε near K.")
    cols = ["scene", "condition", "controller", "n", "success_rate", "success_lo", "success_hi",
            "collision_rate", "reached", "stalled", "timed_out", "median_time", "final_median",
            "clearance_median", "clearance_p05", "clearance_min", "mean_jumps"]
    out.table(res.tables["summary"][cols], "tab2_authors_code_vs_default",
              "Monte Carlo (true state) on the default and the authors' scene, 95% CIs.")


def draw_hysteresis_margin(scen, ctx, res, out) -> None:
    df = res.tables["margin"]
    dists = list(dict.fromkeys(df["disturbance"]))
    chis, lams = sorted(set(df["chi"])), sorted(set(df["lam"]))
    vmax = float(np.nanmax(df["eps_margin"].to_numpy())) if df["eps_margin"].notna().any() else 1.0
    fig, axes = plt.subplots(1, len(dists), figsize=(5.6 * len(dists), 4.2), squeeze=False)
    for ax, dist in zip(axes[0], dists):
        grid = np.full((len(lams), len(chis)), np.nan)
        for r in df[df.disturbance == dist].itertuples():
            grid[lams.index(r.lam), chis.index(r.chi)] = r.eps_margin
        im = ax.imshow(grid, origin="lower", cmap="viridis", vmin=0, vmax=vmax, aspect="auto")
        for i in range(len(lams)):
            for j in range(len(chis)):
                if np.isfinite(grid[i, j]):
                    ax.text(j, i, f"{grid[i, j]:.2f}", ha="center", va="center", fontsize=7,
                            color="w" if grid[i, j] < 0.6 * vmax else "k")
        ax.set_xticks(range(len(chis)), [f"{c:g}" for c in chis])
        ax.set_yticks(range(len(lams)), [f"{v:g}" for v in lams])
        pc, pl = res.info["paper_cell"]
        if pc in chis and pl in lams:
            ax.add_patch(__import__("matplotlib.patches", fromlist=["Rectangle"]).Rectangle(
                (chis.index(pc) - 0.5, lams.index(pl) - 0.5), 1, 1, fill=False, ec="red", lw=2, label="paper (1.1, 0.09)"))
            ax.legend(fontsize=7, loc="upper left")
        ax.set(xlabel="χ", ylabel="λ (λ < χ - 1; blank: not allowed)", title=f"{dist}: largest ε with ≥ {scen.success:.0%} success")
        fig.colorbar(im, ax=ax, label="ε margin")
    out.figure(fig, "fig11_hysteresis_margin",
               "Hysteresis margin map: the largest disturbance ε for which the hybrid controller still reaches the "
               "target from the starts near K, per (χ, λ) (bisection on ε; red: the paper's cell).")
    out.table(df, "tab_hysteresis_margin", "Largest robust ε per (χ, λ) and disturbance (eps_fails: the smallest "
                                           "failing ε the bisection found).")


def draw_scheme(scen, ctx, res, out) -> None:
    out.figure(scheme_figure(), "fig4_scheme",
               "Scheme of the closed loop: camera h(p) -> perception map l(θ) -> hybrid supervisor (flow set C, jump "
               "set D, mode q) -> gradient flow -k∇V_q -> vehicle, with the disturbance and camera-failure inputs "
               "where the simulator applies them (paper Fig. 4).")


def draw_sample_and_hold(scen, ctx, res, out) -> None:
    a, df = res.arrays, res.tables["sample_and_hold"]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    row = df.iloc[0]
    for ax, zoom in zip(axes, (False, True)):
        draw_frame(ax, ctx.scene, ctx.arena)
        ax.plot(a["sampled_p"][:, 0], a["sampled_p"][:, 1], color="tab:red", lw=0.9,
                label=f"sampled at {1 / res.info['period']:g} Hz: {row.t_sampled:.2f} s" if res.info["period"] else "sampled")
        if "guarded_p" in a:
            ax.plot(a["guarded_p"][:, 0], a["guarded_p"][:, 1], color="tab:green", lw=1.1,
                    label=f"sampled with the guard (SPEC §3.3): {row.t_guarded:.2f} s, "
                          f"{int(row.pushouts_guarded)} push-outs (literal rule: {int(row.pushouts_sampled)})")
        ax.plot(a["continuous_p"][:, 0], a["continuous_p"][:, 1], color="tab:blue", lw=1.2,
                label=f"continuous time: {row.t_continuous:.2f} s (dt -> 0 limit {row.t_limit:.2f} s)")
        if zoom:
            c = ctx.scene.c
            ax.set_xlim(-c - 2, 2)
            ax.set_ylim(-1, c + 1)
            ax.set_title("zoom on the diamond's edge: the zigzag of the held velocity", fontsize=9)
        else:
            ax.legend(fontsize=7, loc="lower right")
            ax.set_title(f"hybrid controller from ({row.x0:g}, {row.y0:g})", fontsize=9)
    out.figure(fig, "fig12_sample_and_hold",
               "What the camera's sample-and-hold costs: under SPEC §3.3's literal rule the sampled arc zigzags along the "
               "diamond's edge (a stiff barrier gradient saturated at u_max, held between frames); with the sampled-data "
               "guard the held segment never enters the active wedge and the arc follows the continuous-time one.")
    out.table(df, "tab_sample_and_hold", "Time to target, jumps and path length: sampled (the literal rule), sampled "
                                         "with the guard, continuous time and the dt = period -> 0 limit; push-outs "
                                         "and guard-active frames; relative errors against the limit.")


def draw_perception_generalisation(scen, ctx, res, out) -> None:
    df = res.tables["summary"]
    levels = list(dict.fromkeys(df["level"]))
    xs = np.arange(len(levels))
    fig, axes = plt.subplots(1, 2, figsize=(12, 4))
    for i, (name, g) in enumerate(df.groupby("map", sort=False)):
        g = g.set_index("level").reindex(levels)
        color = f"C{i}"
        axes[0].semilogy(xs, g["mae_px"].clip(lower=1e-3), "o-", color=color, label=f"{name}: MAE")
        axes[0].semilogy(xs, g["near_target_p95_px"].clip(lower=1e-3), "s--", color=color, alpha=0.7,
                         label=f"{name}: near-target p95")
        axes[1].plot(xs, g["follower_success_rate"], "o-", color=color, label=f"{name}: |p - p_T| <= {res.info['delta']:g}")
        axes[1].plot(xs, g["follower_success_practical"], "s--", color=color, alpha=0.7,
                     label=f"{name}: within {res.info['delta_practical']:g}")
    axes[0].set(ylabel="error (px, log)", title="perception error on fresh test positions")
    axes[1].set(ylabel="follower success", ylim=(-0.03, 1.03), title="follower of the occlusion scenario")
    for ax in axes:
        ax.set_xticks(xs, levels)
        ax.set_xlabel("cloud level")
        ax.grid(alpha=0.3, which="both")
        ax.legend(fontsize=6, ncol=2)
    out.figure(fig, "fig13_perception_generalisation",
               "Each perception map (trained on clean images, the authors' clouds, heavy clouds; and the paper's "
               "network on clean images) on each cloud level: MAE and near-target p95 (px, log scale), and the "
               "follower's success in the occlusion scenario.")
    cols = ["map", "level", "mae_px", "p95_px", "near_target_p95_px", "hidden_mae_px", "hidden_share",
            "follower_n", "follower_success_rate", "follower_success_lo", "follower_success_hi",
            "follower_success_practical", "follower_collision_rate", "follower_final_error_median"]
    out.table(df[cols], "tab_perception_generalisation",
              f"Perception maps across cloud levels: MAE (per coordinate), p95 and near-target p95 (within "
              f"{scen.near_radius:g} units of the target) of the Euclidean error in px on fresh test positions; "
              f"MAE on hidden frames (cloud opacity over the leader >= {scen.hidden_alpha:g}) and their share; the "
              f"occlusion scenario's follower with the map under the level: success (|p - p_T| <= "
              f"{res.info['delta']:g}, 95% Wilson CI), within {res.info['delta_practical']:g} units, collisions, "
              "median final distance.")


def _gif(ctx, out, stem: str, caption: str, t, lead, foll, perceived, level=None) -> None:
    """The arena with both vehicles, the follower's camera frame (with its clouds) and the perceived leader."""
    cam, occ = ctx.camera(), ctx.occlusion(level)
    n = min(len(t), len(lead), len(foll), len(perceived))
    lead, foll, perceived, t = lead[:n], foll[:n], perceived[:n], t[:n]

    def frame(k: int):
        return cam.render(lead[k:k + 1], foll[k:k + 1], occlusion=occ, rng=np.random.default_rng(k))[0]

    frames = max(8, round(60 * min(1.0, ctx.scale)))  # 60; a small scale (debug=tiny) draws fewer
    path = leader_follower_gif(out.dir / f"{stem}.gif", ctx.scene, ctx.arena, t, lead, foll, perceived, frame,
                               title=caption, max_frames=frames)
    out.items.append({"kind": "animation", "files": [path.name], "caption": caption})
