"""Figures, tables and the animation of the attack scenarios (`pipeline.experiments.attacks.camera`; drawing code only:
re-drawn from the cached results, never re-simulated)."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg", force=False)
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

from pipeline.experiments.paper.animation import frame_indices  # noqa: E402
from pipeline.experiments.report import draw_frame  # noqa: E402
from pipeline.render import CloudSample  # noqa: E402
from pipeline.viz import legend_outside, save_gif  # noqa: E402

TABLE = ["budget", "attack", "controller", "gated", "n", "success_rate", "success_lo", "success_hi", "stalled_rate",
         "stalled_lo", "stalled_hi", "collision_rate", "collision_lo", "collision_hi", "timed_out",
         "induced_along_near_K", "induced_norm_near_K", "induced_along_start", "induced_norm_start", "induced_norm_run",
         "flag_rate", "flag_rate_near_K", "gated_share", "frames_near_K",
         "stopped_by_drift", "rejected"]  # dead reckoning's agents stopped, and with a frame rejected (camera.innovation)


def _sweep_figure(res, xlabel: str, title: str):
    df = res.tables["summary"]
    budgets = list(dict.fromkeys(df["budget"]))
    xs = np.arange(len(budgets))
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.8))
    for (ctrl, gated), g in df.groupby(["controller", "gated"], sort=False):
        g = g.set_index("budget").reindex(budgets)
        label = f"{ctrl}{' (gated)' if gated else ''}"
        ls = "--" if gated else "-"
        for ax, key in zip(axes[:2], ("success", "stalled")):
            yerr = np.clip([g[f"{key}_rate"] - g[f"{key}_lo"], g[f"{key}_hi"] - g[f"{key}_rate"]], 0, None)
            ax.errorbar(xs, g[f"{key}_rate"], yerr=yerr, fmt="o" + ls, capsize=3, label=label)
    for ax, key in zip(axes[:2], ("success", "stalled")):
        ax.set(xlabel=xlabel, ylabel=f"{key} rate (95% CI)", ylim=(-0.03, 1.03), title=f"{key}: {title}")
        ax.set_xticks(xs, [f"{b:g}" if isinstance(b, float) else str(b) for b in budgets])
        ax.grid(alpha=0.3)
        legend_outside(ax, below=True, ncol=2)  # rates fill the axes from 0 to 1
    ax = axes[2]
    ungated = df[~df["gated"].astype(bool)]
    for ctrl, g in ungated.groupby("controller", sort=False):
        g = g.set_index("budget").reindex(budgets)
        ax.plot(xs, g["induced_norm_near_K"], "o-", label=f"{ctrl}: |induced error| near K")
    first = ungated.groupby("budget", sort=False)["induced_along_start"].mean().reindex(budgets)
    ax.plot(xs, first, "k^--", label="along -sign(b) e_b, first frame (starts)")
    ax.axhline(0.5, color="0.5", lw=0.8, ls=":")
    ax.set(xlabel=xlabel, ylabel="world units", title="estimate error the attack induces")
    ax.set_xticks(xs, [f"{b:g}" if isinstance(b, float) else str(b) for b in budgets])
    if "flag_rate" in df and df["flag_rate"].notna().any():
        tw = ax.twinx()
        fl = ungated.groupby("budget", sort=False)["flag_rate"].mean().reindex(budgets)
        tw.plot(xs, fl, "s:", color="tab:purple", label="flag rate (uncertainty head)")
        tw.set(ylabel="flag rate", ylim=(-0.03, 1.03))
    handles = [h for a in fig.axes[2:] for h in a.get_legend_handles_labels()[0]]  # the twin's line in one key
    legend_outside(ax, handles, below=True, ncol=1)
    ax.grid(alpha=0.3)
    return fig


def _table(scen, res, out, stem: str, caption: str) -> None:
    df = res.tables["summary"]
    out.table(df[[c for c in TABLE if c in df]], stem, caption)


def draw_camera_attack(scen, ctx, res, out) -> None:
    fig = _sweep_figure(res, "κ (intensity levels)", "pixel attack, starts near K")
    out.figure(fig, f"fig14_{scen.id}",
               "Proposition 1 through the camera: starts near K, the clean map in the loop, each frame perturbed by "
               "PGD within |δ|∞ <= κ to push the estimate along -sign(b(p)) e_b; success and stall rates (95% "
               f"Wilson CIs) per controller ({gated_words(res)[0]}) and the estimate error the attack induces near K.")
    _table(scen, res, out, f"tab_{scen.id}",
           f"Pixel attack (PGD) vs κ from {int(res.tables['summary']['n'].iloc[0])} starts near K: success, stall and "
           "collision rates with 95% Wilson CIs; the induced estimate error (attacked - clean) along -sign(b) e_b and "
           "in norm near K (a < -c, |b| < band), on the first frame (the starts) and over the run; the uncertainty "
           f"head's flag rate on attacked frames at gate {_gate(res)} and {gated_words(res)[1]}.")
    for note in res.info.get("notes", []):
        print(f"[experiments] {scen.id}: {note}")


def gated_words(res) -> tuple[str, str]:
    """What the figure's and the table's captions say of the gated loop: it ran (its dashed lines, the share of
    frames it held) or it did not (`experiment.gated` empty, or a map without an uncertainty head)."""
    if res.tables["summary"]["gated"].astype(bool).any():
        return ("dashed: the loop gated by the map's uncertainty head", "the share of frames the gated loop held")
    return ("ungated loops only; the gated loop (dashed) is run and drawn only when `experiment.gated` names a "
            "controller and the map has an uncertainty head", "gated_share, 0 here: no gated loop ran "
            "(`experiment.gated` is empty, or the map has no uncertainty head)")


def _reckoning_words(res) -> str:
    """The caption's words for dead reckoning's columns, where the table has them."""
    df, words = res.tables["summary"], ""
    if "stopped_by_drift" in df:
        words += "; stopped_by_drift: agents dead reckoning stopped at least once (camera.predict)"
    if "rejected" in df:
        words += ("; rejected: agents of the gated loop with a kept frame rejected against their own motion "
                  "(camera.innovation), the vehicle stopped until two frames agreed")
    return words


def _gate(res) -> str:
    g = res.info.get("gate")
    return "–" if g is None else f"{g:.3g} units"


def draw_worst_cloud(scen, ctx, res, out) -> None:
    fig = _sweep_figure(res, "cloud level (the adversary's ranges)", "worst cloud, starts near K")
    out.figure(fig, f"fig15_{scen.id}",
               f"The worst cloud: each frame the worst of {ctx.cfg.disturbances[scen.attack].candidates} cloud layouts "
               f"of the level per agent, the {scen.map} map in the loop, starts near K; success and stall rates "
               f"(95% CIs) per controller ({gated_words(res)[0]}) and the estimate error the clouds induce near K.")
    _table(scen, res, out, f"tab_{scen.id}",
           "Worst cloud vs level from starts near K: success, stall and collision rates with 95% Wilson CIs; the "
           "induced estimate error (clouded - clear) along -sign(b) e_b and in norm near K, first frame and run; "
           f"flag rate of the uncertainty head at gate {_gate(res)} and {gated_words(res)[1]}"
           f"{_reckoning_words(res)}.")
    if res.info.get("record") is not None and "rec_smooth_p" in res.arrays and "rec_hybrid_p" in res.arrays:
        _worst_cloud_gif(scen, ctx, res, out, max_frames=max(8, round(40 * min(1.0, ctx.scale))))  # debug=tiny: 8


def pick_agent(metrics, level) -> tuple[int, str]:
    """The first start where the smooth controller stalled (else failed) and the hybrid one reached the target."""
    m = metrics[(metrics["budget"] == level) & ~metrics["gated"].astype(bool)]
    s = m[m["controller"] == "smooth"].reset_index(drop=True)
    h = m[m["controller"] == "hybrid"].reset_index(drop=True)
    for cond, what in (((s["outcome"] == "stalled") & h["success"]), "smooth stalled, hybrid reached"), \
                      ((~s["success"]) & h["success"], "smooth failed, hybrid reached"):
        idx = np.flatnonzero(cond.to_numpy())
        if len(idx):
            return int(idx[0]), what
    return 0, "no start where the smooth controller failed and the hybrid one passed: start 0"


def _camera_frames(ctx, res, scen, ctrl: str, agent: int):
    """k -> the image the agent's camera delivered at frame k (the chosen cloud re-rendered), or the clear frame."""
    rows, clouds = res.arrays[f"rec_{ctrl}_rows"], res.arrays[f"rec_{ctrl}_clouds"]
    mine = rows[:, 1] == agent
    by_frame = {int(f): c for f, c in zip(rows[mine, 0], clouds[mine])} if len(clouds) == len(rows) else {}
    cam, occ = ctx.camera(scen.map), ctx.occlusion(res.info["record"])
    p = res.arrays[f"rec_{ctrl}_p"][:, agent]

    def image(k: int):
        c = by_frame.get(k)
        if c is None or occ is None:
            return cam.render(p[k:k + 1])[0]
        sample = CloudSample(np.array([bool(c[0])]), c[1:2], c[2:3], c[3:4])
        return cam.render(p[k:k + 1], occlusion=occ, clouds=sample)[0]

    return image


def _worst_cloud_gif(scen, ctx, res, out, max_frames: int = 40, fps: int = 6) -> None:
    level = res.info["record"]
    agent, what = pick_agent(res.tables["metrics"], level)
    t = res.arrays["rec_hybrid_t"]
    n = min(len(t), len(res.arrays["rec_smooth_t"]))
    idx = frame_indices(n, max_frames)
    runs = {c: (res.arrays[f"rec_{c}_p"][:n, agent], res.arrays[f"rec_{c}_m"][:n, agent],
                _camera_frames(ctx, res, scen, c, agent)) for c in ("smooth", "hybrid")}
    colors = {"smooth": "tab:red", "hybrid": "tab:blue"}
    fig, axes = plt.subplots(1, 3, figsize=(12, 3))
    draw_frame(axes[0], ctx.scene, ctx.arena)
    artists = {}
    for c in runs:
        trail, = axes[0].plot([], [], "-", color=colors[c], lw=1.4, label=c)
        dot, = axes[0].plot([], [], "o", color=colors[c], mec="k", ms=6, zorder=6)
        seen, = axes[0].plot([], [], "x", color=colors[c], ms=8, mew=2, zorder=7)
        artists[c] = (trail, dot, seen)
    axes[0].legend(fontsize=7, loc="lower left")
    (x0, x1), (y0, y1) = ctx.arena
    ims = {}
    for ax, c in zip(axes[1:], ("smooth", "hybrid")):
        ims[c] = ax.imshow(runs[c][2](0), extent=(x0, x1, y0, y1), origin="upper", interpolation="nearest")
        ax.set_title(f"{c}'s camera (worst {level} cloud)", fontsize=9)
        ax.set_xticks([])
        ax.set_yticks([])
    head = fig.suptitle("", fontsize=10)

    def update(j):
        k = idx[j]
        for c, (p, m, image) in runs.items():
            trail, dot, seen = artists[c]
            trail.set_data(p[: k + 1, 0], p[: k + 1, 1])
            dot.set_data([p[k, 0]], [p[k, 1]])
            seen.set_data([m[k, 0]], [m[k, 1]])
            ims[c].set_data(image(k))
        head.set_text(f"worst {level} cloud, start {agent} ({what}); x: perceived  t = {t[k]:.2f} s")
        return [a for v in artists.values() for a in v] + list(ims.values()) + [head]

    path = save_gif(fig, update, len(idx), out.dir / f"anim15_{scen.id}.gif", fps=fps, dpi=70)
    out.items.append({"kind": "animation", "files": [path.name],
                      "caption": f"A smooth controller and the hybrid one from the same start near K under the worst "
                                 f"{level} cloud ({what}); right: what each camera delivered."})


def draw_geometry_margin(scen, ctx, res, out) -> None:
    df = res.tables["margin"]
    dists = list(dict.fromkeys(df["disturbance"]))
    apexes, rhos, scales = sorted(set(df["apex_ratio"])), sorted(set(df["rho"])), sorted(set(df["barrier_scale"]))
    vmax = float(np.nanmax(df["eps_margin"].to_numpy())) if df["eps_margin"].notna().any() else 1.0
    fig, axes = plt.subplots(len(dists), len(scales), figsize=(4.4 * len(scales), 3.6 * len(dists)), squeeze=False)
    d = res.info["default"]
    for i, dist in enumerate(dists):
        for j, ell in enumerate(scales):
            ax = axes[i, j]
            grid = np.full((len(rhos), len(apexes)), np.nan)
            g = df[(df.disturbance == dist) & (df.barrier_scale == ell)]
            for r in g.itertuples():
                grid[rhos.index(r.rho), apexes.index(r.apex_ratio)] = r.eps_margin
            im = ax.imshow(grid, origin="lower", cmap="viridis", vmin=0, vmax=vmax, aspect="auto")
            for a in range(len(rhos)):
                for b in range(len(apexes)):
                    txt = f"{grid[a, b]:.2f}" if np.isfinite(grid[a, b]) else "skip"
                    ax.text(b, a, txt, ha="center", va="center", fontsize=7,
                            color="w" if not np.isfinite(grid[a, b]) or grid[a, b] < 0.6 * vmax else "k")
            ax.set_xticks(range(len(apexes)), [f"{v:.3g}" for v in apexes])
            ax.set_yticks(range(len(rhos)), [f"{v:g}" for v in rhos])
            is_default = np.isclose(ell, d["barrier_scale"])
            ax.set(xlabel="apex c / r", ylabel="ρ_b", title=f"{dist}, ℓ_B = {ell:g}{' (default)' if is_default else ''}")
            fig.colorbar(im, ax=ax, label="ε margin")
    out.figure(fig, f"fig16_{scen.id}",
               f"Theorem 1's margin over the geometry (beside Fig. 11's flat (χ, λ) map): the largest ε with >= "
               f"{scen.success:.0%} of the starts near K reaching the target, per apex c / r, barrier ρ_b and ℓ_B, at "
               f"(χ, λ) = ({scen.chi[0]:g}, {scen.lam[0]:g}); 'skip': the cell's scene is not valid (docs/attacks.md).")
    out.table(df, f"tab_{scen.id}", "Largest robust ε per (c / r, ρ_b, ℓ_B) (eps_fails: the smallest failing ε "
                                         "found; c, the barrier's reach ℓ_B sqrt(ρ_b); notes on skipped cells).")
