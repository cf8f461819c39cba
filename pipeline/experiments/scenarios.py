"""The paper's scenarios (SPEC §4): each is `compute(ctx) -> Results` (cached) and `draw(ctx, res, out)`.

A scenario's `maps` lists the perception maps its results depend on (part of its cache key).
"""

from __future__ import annotations

import numpy as np
import pandas as pd

from pipeline.control import in_covering_set, in_diamond, potential
from pipeline.experiments.common import Context, Outputs, Results, draw_frame, summarise, wilson
from pipeline.sim import Gaussian
from pipeline.sim.build import initial_conditions

REGISTRY: dict[str, type] = {}


def scenario(cls):
    REGISTRY[cls.__name__] = cls
    return cls


def _plt():
    import matplotlib

    matplotlib.use("Agg", force=False)
    import matplotlib.pyplot as plt

    return plt


def _frame_index(t: np.ndarray, times) -> list[int]:
    return [int(min(np.searchsorted(t, s - 1e-9), len(t) - 1)) for s in times]


def _agent_rows(res, **cols) -> pd.DataFrame:
    df = res.metrics_frame()
    for k, v in cols.items():
        df[k] = v
    return df


# --------------------------------------------------------------------------------- coverings
@scenario
class coverings:  # noqa: N801 - the experiment id
    maps: tuple = ()

    def compute(self, ctx: Context) -> Results:
        step = float(ctx.param("grid_step", 0.25)) / min(1.0, ctx.scale) ** 0.5
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        arrays = {"x": xs, "y": ys}
        rows = []
        for q in (1, 2):
            V = potential(ctx.scene, q, pts).reshape(X.shape)
            arrays[f"V{q}"] = V
            rows.append({"set": f"O_{q}", "share_of_arena": float(in_covering_set(ctx.scene, q, pts).mean()),
                         "min_V": float(np.nanmin(V[np.isfinite(V)]))})
        rows.append({"set": "diamond", "share_of_arena": float(in_diamond(ctx.scene, pts).mean()), "min_V": np.nan})
        return Results({"coverings": pd.DataFrame(rows)}, arrays, {})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
        fig, axes = plt.subplots(1, 2, figsize=(11, 3.6))
        x, y = res.arrays["x"], res.arrays["y"]
        for q, ax in zip((1, 2), axes):
            V = res.arrays[f"V{q}"]
            finite = np.isfinite(V)
            ax.contourf(x, y, finite.astype(float), levels=[0.5, 1.5], colors=["#cfe3f7" if q == 1 else "#f7dccf"])
            levels = np.quantile(V[finite], np.linspace(0.02, 0.9, 12))
            ax.contour(x, y, np.where(finite, V, np.nan), levels=np.unique(levels), colors="k", linewidths=0.5)
            draw_frame(ax, ctx.scene, ctx.arena)
            ax.set_title(f"O_{q} (shaded) and level sets of V_{q}")
        out.figure(fig, "fig4_coverings", "Coverings O_1, O_2 (shaded) with level sets of V_1, V_2 (paper Fig. coverings).")
        out.table(res.tables["coverings"], "tab_coverings", "Share of the arena in each covering set.")


# ---------------------------------------------------------------------------- sensitive set
@scenario
class sensitive_set:  # noqa: N801
    maps: tuple = ()

    def compute(self, ctx: Context) -> Results:
        coarsen = 1.0 / min(1.0, ctx.scale) ** 0.5
        step = float(ctx.param("grid_step", 1.0)) * coarsen
        step_y = float(ctx.param("grid_step_y", step)) * coarsen  # fine across K to resolve the ε band
        eps = float(ctx.param("eps", 0.5))
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0 + 1, x1 - 1 + 1e-9, step), np.arange(y0 + 1, y1 - 1 + 1e-9, step_y)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        keep = np.hypot(*(pts - ctx.scene.p_0).T) > ctx.scene.obstacle_radius
        pts = pts[keep]
        tables, arrays = {}, {"x": xs, "y": ys, "keep": keep}
        rows = []
        for case, dist in (("clean", None), (f"adversarial eps={eps}", ctx.disturbance("adversarial", eps=eps))):
            for ctrl in ("smooth", "hybrid"):
                res = ctx.simulate(ctx.controller(ctrl), pts, disturbance=dist, record_every=10)
                a, b = ctx.scene.to_frame(res.p.reshape(-1, 2))
                a, b = a.reshape(res.p.shape[:2]), b.reshape(res.p.shape[:2])
                passed = a >= 0  # beyond the obstacle's centre along the target direction
                first = np.where(passed.any(0), passed.argmax(0), -1)
                side = np.where(first >= 0, np.sign(b[np.maximum(first, 0), np.arange(len(pts))]), 0)
                cls = np.where(res.metrics["success"], np.where(side >= 0, 1, 2), 0)  # 1: K_1, 2: K_2, 0: stalls
                arrays[f"{ctrl}|{case}"] = cls.astype(np.int8)
                rows.append({"controller": ctrl, "case": case, "n": len(pts), "K_1": float((cls == 1).mean()),
                             "K_2": float((cls == 2).mean()), "stalled_or_failed": float((cls == 0).mean())})
        tables["sensitive_set"] = pd.DataFrame(rows)
        return Results(tables, arrays, {"eps": eps})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
        from matplotlib.colors import ListedColormap

        eps = res.info["eps"]
        x, y, keep = res.arrays["x"], res.arrays["y"], res.arrays["keep"]
        cmap = ListedColormap(["#d62728", "#1f77b4", "#ff7f0e"])  # stall, K_1, K_2
        cases = ["clean", f"adversarial eps={eps}"]
        fig, axes = plt.subplots(2, 2, figsize=(11, 6.5))
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


# ------------------------------------------------------------------------------ noise + failure
@scenario
class noise_failure:  # noqa: N801
    maps = ("clean",)

    def compute(self, ctx: Context) -> Results:
        sigma, p_fail = float(ctx.param("sigma", 0.5)), float(ctx.param("p_fail", 0.5))
        ics = np.asarray(ctx.param("initial_conditions", [[-12.0, 2.0], [-37.0, -17.0]]), float)
        noise = Gaussian(sigma=sigma)
        single = ctx.simulate(ctx.controller("hybrid"), ics, disturbance=noise, p_fail=p_fail,
                              measure=ctx.camera_measure("clean"))
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[1:2], kind="clean", sigma=sigma, p_fail=p_fail)
        rows = pd.concat([_agent_rows(single, role="vehicle"), _agent_rows(lead, role="leader"),
                          _agent_rows(foll, role="follower")], ignore_index=True)
        arrays = {"single_p": single.p, "single_m": single.m, "lead_p": lead.p, "foll_p": foll.p,
                  "foll_target": foll.target, "lead_t": lead.t, "foll_t": foll.t}
        return Results({"metrics": rows}, arrays, {"sigma": sigma, "p_fail": p_fail})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
        a = res.arrays
        fig, axes = plt.subplots(1, 2, figsize=(12, 4))
        ax = axes[0]
        draw_frame(ax, ctx.scene, ctx.arena)
        for i in range(a["single_p"].shape[1]):
            ax.plot(a["single_m"][:, i, 0], a["single_m"][:, i, 1], ".", ms=1.5, color="0.6")
            ax.plot(a["single_p"][:, i, 0], a["single_p"][:, i, 1], lw=1.5)
        ax.set_title(f"hybrid, CNN in the loop, noise σ={res.info['sigma']}, {res.info['p_fail']:.0%} camera failure",
                     fontsize=9)
        ax = axes[1]
        draw_frame(ax, ctx.scene, ctx.arena)
        ax.plot(a["lead_p"][:, 0, 0], a["lead_p"][:, 0, 1], color="k", lw=1.5, label="leader")
        ax.plot(a["foll_p"][:, 0, 0], a["foll_p"][:, 0, 1], color="tab:green", lw=1.5, label="follower")
        ax.plot(a["foll_target"][:, 0, 0], a["foll_target"][:, 0, 1], ".", ms=1.5, color="tab:olive",
                label="leader as perceived by the follower")
        ax.legend(fontsize=7, loc="lower right")
        ax.set_title("leader-follower", fontsize=9)
        out.figure(fig, "fig6_robustness_noise_failure",
                   "Hybrid controller with the CNN in the loop under noise and camera failure: single vehicle from "
                   "both initial conditions (grey: perceived positions) and leader-follower (paper Fig. robustness).")
        out.table(res.tables["metrics"][["role", "x0", "y0", "success", "collision", "time_to_target", "min_clearance",
                                         "jumps", "final_error"]],
                  "tab_noise_failure", "Per-vehicle outcomes of the noise/failure scenario.")


# --------------------------------------------------------------------------------------- occlusion
@scenario
class occlusion:  # noqa: N801
    maps = ("clean", "occluded")

    def compute(self, ctx: Context) -> Results:
        level = str(ctx.param("occlusion", "heavy"))
        ics = np.asarray(ctx.param("initial_conditions", [[-12.0, 2.0], [-37.0, -17.0]]), float)
        n_mc = ctx.n(int(ctx.param("n_agents", 100)))
        leaders = np.repeat(ics[:1], n_mc, 0)
        followers = initial_conditions({"mode": "random", "n": n_mc, "seed": ctx.seed, "margin": 3.0},
                                       ctx.scene, ctx.scene_cfg)
        followers[0] = ics[1]
        rows, arrays = [], {}
        for kind in ("clean", "occluded"):
            lead, foll, track = ctx.leader_follower(leaders, followers, kind=kind, level=level)
            err = np.hypot(*(foll.target - track.position(foll.t)).transpose(2, 0, 1))
            df = _agent_rows(foll, map=kind, occlusion=level)
            df["tracking_error_mean"] = np.nanmean(err, axis=0)
            rows.append(df)
            arrays[f"{kind}_foll_p"] = foll.p[:, 0]
            arrays[f"{kind}_foll_target"] = foll.target[:, 0]
            arrays[f"{kind}_lead_p"] = lead.p[:, 0]
            arrays[f"{kind}_err"] = err[:, 0]
        metrics = pd.concat(rows, ignore_index=True)
        table = summarise(metrics, ["map", "occlusion"], seed=ctx.seed)
        g = metrics.groupby("map", sort=False)
        table["tracking_error_mean"] = g["tracking_error_mean"].mean().to_numpy()
        # the follower stops next to a leader it only sees through clouds: how close it gets matters more
        # than the strict |p - p_T| <= delta success
        table["final_error_median"] = g["final_error"].median().to_numpy()
        table["within_3_units"] = g["final_error"].apply(lambda e: float((e <= 3.0).mean())).to_numpy()
        return Results({"metrics": metrics, "summary": table}, arrays, {"level": level})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
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
        out.figure(fig, "fig7_occlusion",
                   "Follower with the map trained without and with occlusion, tested on occluded frames (paper Fig. occlusion).")
        cols = ["map", "occlusion", "n", "success_rate", "success_lo", "success_hi", "collision_rate",
                "tracking_error_mean", "final_error_median", "within_3_units", "mean_jumps"]
        out.table(res.tables["summary"][cols], "tab_occlusion",
                  "Followers from random initial conditions on occluded frames, per perception map: success "
                  "(|p - p_T| <= delta, 95% CIs), mean error of the perceived leader, median final distance to "
                  "the target, share ending within 3 units.")


# --------------------------------------------------------------------------------- leader-follower
@scenario
class leader_follower:  # noqa: N801
    maps = ("clean",)

    def compute(self, ctx: Context) -> Results:
        ics = np.asarray(ctx.param("initial_conditions", [[-12.0, 2.0], [-37.0, -17.0]]), float)
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[1:2], kind="clean", sigma=float(ctx.param("sigma", 0.0)))
        frames = [int(f) for f in ctx.param("instants", [1, 90, 180])]
        period = ctx.frame_period or ctx.dt
        idx = _frame_index(foll.t, [f * period for f in frames])
        step = float(ctx.param("grid_step", 0.5))
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0, x1 + 1e-9, step), np.arange(y0, y1 + 1e-9, step)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        arrays = {"x": xs, "y": ys, "lead_p": lead.p[:, 0], "foll_p": foll.p[:, 0], "foll_t": foll.t,
                  "foll_q": foll.q[:, 0], "foll_target": foll.target[:, 0], "idx": np.asarray(idx)}
        rows = []
        for f, k in zip(frames, idx):
            q = int(foll.q[k, 0])
            arrays[f"V_{f}"] = potential(ctx.scene, q, pts, foll.target[k, 0]).reshape(X.shape)
            rows.append({"frame": f, "t": float(foll.t[k]), "mode_q": q, "target_x": float(foll.target[k, 0, 0]),
                         "target_y": float(foll.target[k, 0, 1]), "follower_x": float(foll.p[k, 0, 0]),
                         "follower_y": float(foll.p[k, 0, 1])})
        return Results({"instants": pd.DataFrame(rows),
                        "metrics": pd.concat([_agent_rows(lead, role="leader"), _agent_rows(foll, role="follower")])},
                       arrays, {"frames": frames})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
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
        out.figure(fig, "fig8_leader_follower_level_sets",
                   "Level sets of the follower's V_q around the moving target (the perceived leader) at three "
                   "instants (paper Fig. level sets).")
        out.table(res.tables["instants"], "tab_leader_follower_instants", "Follower state at the plotted instants.")


# ---------------------------------------------------------------------------- perception closeness
@scenario
class perception_closeness:  # noqa: N801
    maps = ("clean",)

    def compute(self, ctx: Context) -> Results:
        x0 = np.asarray(ctx.param("initial_conditions", [[-37.0, -17.0]]), float)
        res = ctx.simulate(ctx.controller("hybrid"), x0, measure=ctx.camera_measure("clean"))
        err = np.hypot(*(res.m - res.p).transpose(2, 0, 1))
        eps, source = ctx.eps_perception("clean", "none")
        if eps is None:
            eps, source = float(np.max(err)), "max error along this run (no error map)"
        table = pd.DataFrame([{"eps": eps, "eps_source": source, "max_error_on_run": float(err.max()),
                               "mean_error_on_run": float(err.mean()), "inside_tube": float((err <= eps).mean()),
                               "success": bool(res.metrics["success"][0])}])
        return Results({"closeness": table}, {"p": res.p[:, 0], "m": res.m[:, 0]}, {"eps": eps})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
        from matplotlib.patches import Circle

        p, m, eps = res.arrays["p"], res.arrays["m"], res.info["eps"]
        fig, ax = plt.subplots(figsize=(8, 4.5))
        draw_frame(ax, ctx.scene, ctx.arena)
        for c in p[:: max(1, len(p) // 150)]:
            ax.add_patch(Circle(c, max(eps, 1e-3), color="tab:blue", alpha=0.06, lw=0))
        ax.plot(p[:, 0], p[:, 1], "tab:blue", lw=1.5, label="true position p")
        ax.plot(m[:, 0], m[:, 1], ".", ms=2, color="tab:red", label="CNN prediction l(h(p))")
        ax.set_title(f"perception closeness: ε-tube with ε = {eps:.3f}", fontsize=9)
        ax.legend(fontsize=8, loc="lower right")
        out.figure(fig, "fig3_perception_closeness",
                   "A closed-loop trajectory with the CNN's predictions inside the ε-tube of the error map (paper Fig. closeness).")
        out.table(res.tables["closeness"], "tab_perception_closeness", "Perception error along the trajectory vs ε.")


# ------------------------------------------------------------------------------- robustness sweep
@scenario
class robustness_sweep:  # noqa: N801
    maps = ()

    def compute(self, ctx: Context, scene=None, label: str = "default") -> Results:
        eps_list = [float(e) for e in ctx.param("eps", [0.0, 0.1, 0.25, 0.5, 1.0, 1.5])]
        disturbances = list(ctx.param("disturbances", ["adversarial", "alternating"]))
        controllers = list(ctx.param("controllers", ["hybrid", "smooth", "cbf"]))
        n = ctx.n(int(ctx.param("n_agents", 200)))
        scene = scene or ctx.scene
        rows = []
        for dist in disturbances:
            for eps in eps_list:
                band = max(eps, float(ctx.param("min_band", 0.1)))
                x0 = initial_conditions({"mode": "near_k", "n": n, "seed": ctx.seed, "band": band,
                                         "a_range": ctx.param("a_range", [-45.0, -15.0])}, scene)
                for ctrl in controllers:
                    d = ctx.disturbance(dist, eps=eps) if eps > 0 else None
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, disturbance=d, record=False)
                    s, c = int(res.metrics["success"].sum()), int(res.metrics["collision"].sum())
                    lo, hi = wilson(s, n)
                    rows.append({"scene": label, "disturbance": dist, "eps": eps, "controller": ctrl, "n": n,
                                 "success_rate": s / n, "success_lo": float(lo), "success_hi": float(hi),
                                 "collision_rate": c / n, "mean_jumps": float(res.metrics["jumps"].mean())})
        return Results({"sweep": pd.DataFrame(rows)}, {}, {})

    def draw(self, ctx: Context, res: Results, out: Outputs, stem: str = "fig9_robustness_sweep") -> None:
        plt = _plt()
        df = res.tables["sweep"]
        dists = list(dict.fromkeys(df["disturbance"]))
        fig, axes = plt.subplots(1, len(dists), figsize=(5.5 * len(dists), 3.6), squeeze=False)
        for ax, dist in zip(axes[0], dists):
            for ctrl, g in df[df.disturbance == dist].groupby("controller", sort=False):
                ax.plot(g.eps, g.success_rate, "o-", label=ctrl)
                ax.fill_between(g.eps, g.success_lo, g.success_hi, alpha=0.2)
            ax.set(xlabel="ε", ylabel="success rate", ylim=(-0.03, 1.03), title=f"{dist} disturbance, starts within ε of K")
            ax.legend(fontsize=8)
            ax.grid(alpha=0.3)
        out.figure(fig, stem, "Success rate against the disturbance size ε from initial conditions near K: "
                   "Proposition 1 (smooth and CBF stall) against Theorem 1 (hybrid is robust).")
        out.table(df, "tab_robustness_sweep", "Success rate vs ε (95% Wilson CIs), per disturbance and controller.")


# ------------------------------------------------------------------------------------ Monte Carlo
def _mc_conditions(ctx: Context, camera: bool):
    sigma = float(ctx.param("sigma", 0.5))
    conds = [("none", {}), (f"gaussian σ={sigma}", {"disturbance": Gaussian(sigma=sigma)}),
             (f"gaussian σ={sigma} + {ctx.param('p_fail', 0.5):.0%} failure",
              {"disturbance": Gaussian(sigma=sigma), "p_fail": float(ctx.param("p_fail", 0.5))})]
    if camera:
        level = str(ctx.param("occlusion", "heavy"))
        for kind in ("clean", "occluded"):
            conds.append((f"{level} occlusion, {kind} map", {"camera": (kind, level)}))
    return conds


def monte_carlo_metrics(ctx: Context, scene, label: str, camera: bool) -> pd.DataFrame:
    controllers = list(ctx.param("controllers", ["hybrid", "smooth", "cbf"]))
    n = ctx.n(int(ctx.param("n_agents", 300)))
    n_cam = ctx.n(int(ctx.param("n_agents_camera", 100)))
    x0_all = initial_conditions({"mode": "random", "n": max(n, n_cam), "seed": ctx.seed, "margin": 2.0},
                                scene, ctx.scene_cfg)
    frames = []
    for cond, kw in _mc_conditions(ctx, camera):
        kw = dict(kw)
        measure = None
        x0 = x0_all[:n]
        if "camera" in kw:
            kind, level = kw.pop("camera")
            measure = ctx.camera_measure(kind, level)
            x0 = x0_all[:n_cam]
        for ctrl in controllers:
            res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, measure=measure, record=False, **kw)
            frames.append(_agent_rows(res, scene=label, condition=cond))
    return pd.concat(frames, ignore_index=True)


@scenario
class monte_carlo:  # noqa: N801
    maps = ("clean", "occluded")

    def compute(self, ctx: Context) -> Results:
        metrics = monte_carlo_metrics(ctx, ctx.scene, "default", camera=bool(ctx.param("camera", True)))
        table = summarise(metrics, ["condition", "controller"], seed=ctx.seed)
        return Results({"metrics": metrics, "summary": table}, {}, {})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        cols = ["condition", "controller", "n", "success_rate", "success_lo", "success_hi", "collision_rate",
                "median_time", "final_error_median", "min_clearance", "mean_jumps"]
        out.table(res.tables["summary"][cols], "tab1_monte_carlo",
                  "Monte Carlo over random initial conditions: success (|p - p_T| <= delta) and collision rates "
                  "(95% Wilson CIs), median time to target, median final distance to the target, minimum "
                  "clearance, mean jumps, per condition and controller.")
        plt = _plt()
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
        ax.legend(fontsize=8)
        out.figure(fig, "fig10_monte_carlo", "Monte Carlo success rates with 95% CIs per condition and controller.")


# ---------------------------------------------------------------------------------- authors' scene
@scenario
class authors_code:  # noqa: N801
    """The authors' released-code scene (r = 8, apex 1.5 r, log barrier) side by side with the default,
    through the true-state scenarios (the perception maps are trained on the default scene's images)."""

    maps = ()

    def compute(self, ctx: Context) -> Results:
        from omegaconf import OmegaConf

        from pipeline.cli import CONF_DIR
        from pipeline.sim.build import build_scene

        other = str(ctx.param("other_scene", "authors_code"))
        path = CONF_DIR / "scene" / f"{other}.yaml"
        if not path.is_file():
            from pipeline.errors import ConfigError

            raise ConfigError("experiment.other_scene", f"no scene preset {other!r} in conf/scene/")
        layer = OmegaConf.load(path)
        base = [OmegaConf.load(CONF_DIR / "scene" / f"{d}.yaml") for d in layer.pop("defaults", []) if d != "_self_"]
        other_cfg = OmegaConf.merge(*base, layer)
        scenes = [("default", ctx.scene), (str(other_cfg.get("name", "authors_code")), build_scene(other_cfg))]
        sweeps, mcs = [], []
        for label, scene in scenes:
            sweeps.append(robustness_sweep().compute(ctx, scene=scene, label=label).tables["sweep"])
            mcs.append(monte_carlo_metrics(ctx, scene, label, camera=False))
        sweep = pd.concat(sweeps, ignore_index=True)
        mc = summarise(pd.concat(mcs, ignore_index=True), ["scene", "condition", "controller"], seed=ctx.seed)
        return Results({"sweep": sweep, "summary": mc}, {}, {})

    def draw(self, ctx: Context, res: Results, out: Outputs) -> None:
        plt = _plt()
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
        out.figure(fig, "fig11_authors_code_vs_default",
                   "The authors' released-code scene next to the default scene: success vs ε near K.")
        cols = ["scene", "condition", "controller", "n", "success_rate", "success_lo", "success_hi",
                "collision_rate", "median_time", "min_clearance", "mean_jumps"]
        out.table(res.tables["summary"][cols], "tab2_authors_code_vs_default",
                  "Monte Carlo (true state) on the default and the authors' scene, 95% CIs.")
