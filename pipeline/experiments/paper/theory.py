"""The true-state scenarios of the theory (SPEC §4): the coverings, the sensitive set K, Proposition 1 against
Theorem 1 (the robustness sweep), the hysteresis margin map, the sample-and-hold against continuous time, the
authors' scene and the scheme of the closed loop."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from types import SimpleNamespace
from typing import Annotated, ClassVar

import numpy as np
import pandas as pd

from pipeline.control import in_covering_set, in_diamond, potential
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context
from pipeline.experiments.paper.camera_loop import MonteCarlo
from pipeline.experiments.results import Results, summarise
from pipeline.experiments.scenario import Points, Scenario, practical_success
from pipeline.schema import Interval, NonEmpty, NonNegative, Positive, PositiveInt, Range
from pipeline.sim import CameraSettings, SimSettings, simulate, starts
from pipeline.sim.disturbances import PerAgent
from pipeline.sim.metrics import wilson
from pipeline.sim.settings import FailureRate, TimeModel


# --------------------------------------------------------------------------------- coverings
@dataclass(kw_only=True)
class Coverings(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_coverings"
    grid_step: Positive = 0.25

    def uses(self):
        return {"controllers": [], "disturbances": [], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        step = self.grid_step / min(1.0, ctx.scale) ** 0.5
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


# ---------------------------------------------------------------------------- sensitive set
@dataclass(kw_only=True)
class SensitiveSet(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_sensitive_set"
    grid_step: Positive = 1.0
    grid_step_y: Positive = 0.25   # fine across K to resolve the ε band
    eps: NonNegative = 0.5         # size of the adversarial disturbance in the second column
    time_model: TimeModel = "continuous"  # the paper's hybrid arcs (true state): sim.model for this figure

    def uses(self):
        return {"controllers": ["smooth", "hybrid"], "disturbances": ["adversarial"], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        coarsen = 1.0 / min(1.0, ctx.scale) ** 0.5
        step, step_y = self.grid_step * coarsen, self.grid_step_y * coarsen
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0 + 1, x1 - 1 + 1e-9, step), np.arange(y0 + 1, y1 - 1 + 1e-9, step_y)
        X, Y = np.meshgrid(xs, ys)
        pts = np.stack([X.ravel(), Y.ravel()], 1)
        keep = np.hypot(*(pts - ctx.scene.p_0).T) > ctx.scene.obstacle_radius
        pts = pts[keep]
        arrays = {"x": xs, "y": ys, "keep": keep}
        rows = []
        for case, dist in (("clean", None), (f"adversarial eps={self.eps}", ctx.disturbance("adversarial", eps=self.eps))):
            for ctrl in ("smooth", "hybrid"):
                res = ctx.simulate(ctx.controller(ctrl), pts, disturbance=dist, record_every=10, model=self.time_model)
                a, b = ctx.scene.to_frame(res.p.reshape(-1, 2))
                a, b = a.reshape(res.p.shape[:2]), b.reshape(res.p.shape[:2])
                passed = a >= 0  # beyond the obstacle's centre along the target direction
                first = np.where(passed.any(0), passed.argmax(0), -1)
                side = np.where(first >= 0, np.sign(b[np.maximum(first, 0), np.arange(len(pts))]), 0)
                cls = np.where(res.metrics["success"], np.where(side >= 0, 1, 2), 0)  # 1: K_1, 2: K_2, 0: stalls
                arrays[f"{ctrl}|{case}"] = cls.astype(np.int8)
                rows.append({"controller": ctrl, "case": case, "n": len(pts), "K_1": float((cls == 1).mean()),
                             "K_2": float((cls == 2).mean()), "stalled_or_failed": float((cls == 0).mean())})
        return Results({"sensitive_set": pd.DataFrame(rows)}, arrays, {"eps": self.eps})


# ------------------------------------------------------------------------------- robustness sweep
@dataclass(kw_only=True)
class RobustnessSweep(Scenario):
    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_robustness_sweep"
    eps: list[NonNegative] = field(default_factory=lambda: [0.0, 0.1, 0.25, 0.5, 1.0, 1.5])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial", "alternating"])
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_agents: PositiveInt = 200      # initial conditions within eps of K per cell
    min_band: NonNegative = 0.1      # at eps = 0 the starts are within this band of K
    a_range: Interval = field(default_factory=lambda: [-45.0, -15.0])
    time_model: TimeModel = "continuous"  # the paper's hybrid arcs (true state)

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": list(self.disturbances), "occlusions": []}

    def sweep(self, ctx: Context, scene, label: str) -> pd.DataFrame:
        """One row per (disturbance, ε, controller). Every ε > 0 of a disturbance runs in one batch per controller
        (`PerAgent`: each start keeps its own ε, and its arc is the one a run of its own gives); ε = 0 runs
        alone (the undisturbed loop is integrated without frames)."""
        n = ctx.n(self.n_agents)
        x0 = {eps: starts.NearK(n=n, seed=ctx.seed, band=max(eps, self.min_band), a_range=list(self.a_range))(scene)
              for eps in self.eps}
        rows = []
        for dist in self.disturbances:
            for group in ([e for e in self.eps if e == 0], [e for e in self.eps if e > 0]):
                if not group:
                    continue
                ctx.label = f"{label} {dist} eps={','.join(f'{e:g}' for e in group)}"
                d = None if group[0] == 0 else PerAgent([ctx.disturbance(dist, eps=e) for e in group], [n] * len(group))
                for ctrl in self.controllers:
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), np.concatenate([x0[e] for e in group]),
                                       scene=scene, disturbance=d, record=False, model=self.time_model)
                    for k, eps in enumerate(group):
                        m = {key: np.asarray(v)[k * n:(k + 1) * n] for key, v in res.metrics.items()
                             if np.ndim(v) and len(v) == len(group) * n}
                        rows.append(self._row(label, dist, eps, ctrl, n, m, ctx.delta))
        order = {(d, e, c): i for i, (d, e, c) in enumerate((d, e, c) for d in self.disturbances for e in self.eps
                                                             for c in self.controllers)}
        return pd.DataFrame(sorted(rows, key=lambda r: order[(r["disturbance"], r["eps"], r["controller"])]))

    @staticmethod
    def _row(label: str, dist: str, eps: float, ctrl: str, n: int, m: dict, delta: float) -> dict:
        s, c = int(m["success"].sum()), int(m["collision"].sum())
        sp = int(practical_success(SimpleNamespace(metrics=m), delta, eps).sum())
        lo, hi = wilson(s, n)
        plo, phi = wilson(sp, n)
        return {"scene": label, "disturbance": dist, "eps": eps, "controller": ctrl, "n": n,
                "success_rate": s / n, "success_lo": float(lo), "success_hi": float(hi),
                "practical_success_rate": sp / n, "practical_lo": float(plo), "practical_hi": float(phi),
                "collision_rate": c / n, "stalled": float(np.mean(m["outcome"] == "stalled")),
                "mean_jumps": float(m["jumps"].mean())}

    def runs(self) -> int:
        """Simulations of one sweep (the progress total): disturbance x (ε = 0, every ε > 0) x controller."""
        groups = int(any(e == 0 for e in self.eps)) + int(any(e > 0 for e in self.eps))
        return len(self.disturbances) * groups * len(self.controllers)

    def compute(self, ctx: Context) -> Results:
        ctx.expect(self.runs())
        return Results({"sweep": self.sweep(ctx, ctx.scene, "default")}, {}, {})


# ---------------------------------------------------------------------------------- authors' scene
@dataclass(kw_only=True)
class AuthorsCode(Scenario):
    """The authors' released-code scene (composed as `other_scene`: r = 8, apex 1.5 r, log barrier) side by side
    with the default, through the true-state scenarios (the maps are trained on the default scene's images)."""

    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_authors_code"

    eps: list[NonNegative] = field(default_factory=lambda: [0.0, 0.25, 0.5, 1.0])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial"])
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_agents: PositiveInt = 200
    min_band: NonNegative = 0.1
    a_range: Interval = field(default_factory=lambda: [-45.0, -15.0])
    sigma: NonNegative = 0.5
    p_fail: FailureRate = 0.5
    time_model: TimeModel = "continuous"  # of the sweep (the Monte Carlo has camera failures: sampled)

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": sorted({*self.disturbances, "gaussian"}),
                "occlusions": []}

    def check(self, ctx: Context) -> None:
        super().check(ctx)
        ctx.other_scene()

    def compute(self, ctx: Context) -> Results:
        sweep = RobustnessSweep(id=self.id, title=self.title, eps=self.eps, disturbances=self.disturbances,
                                controllers=self.controllers, n_agents=self.n_agents, min_band=self.min_band,
                                a_range=self.a_range, time_model=self.time_model)
        mc = MonteCarlo(id=self.id, title=self.title, controllers=self.controllers, sigma=self.sigma,
                        p_fail=self.p_fail, camera=False, n_agents=self.n_agents, n_agents_camera=1)
        sweeps, mcs = [], []
        ctx.expect(2 * (sweep.runs() + len(mc.conditions(ctx, camera=False)) * len(self.controllers)))
        for label, scene in (("default", ctx.scene), ctx.other_scene()):
            sweeps.append(sweep.sweep(ctx, scene, label))
            mcs.append(mc.metrics(ctx, scene, label, camera=False))
        summary = summarise(pd.concat(mcs, ignore_index=True), ["scene", "condition", "controller"], seed=ctx.seed)
        return Results({"sweep": pd.concat(sweeps, ignore_index=True), "summary": summary}, {}, {})


# ----------------------------------------------------------------------------- hysteresis margin map
@dataclass(kw_only=True)
class HysteresisMargin(Scenario):
    """Theorem 1's robustness margin, measured: over a grid of (χ, λ) with λ < χ - 1, the largest disturbance
    size ε for which the hybrid controller still reaches the target from >= `success` of the starts near K
    (bisection on ε per cell; starts and seed fixed)."""

    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_hysteresis_margin"

    chi: Annotated[list[float], Range(gt=1), NonEmpty()] = field(default_factory=lambda: [1.05, 1.1, 1.2, 1.4, 1.8])
    lam: Annotated[list[float], Range(gt=0), NonEmpty()] = field(default_factory=lambda: [0.01, 0.03, 0.09, 0.2, 0.4])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial", "alternating"])
    n_agents: PositiveInt = 100   # starts near K (a < -c, |b| < band), the same in every cell
    band: Positive = 0.5
    a_range: Interval = field(default_factory=lambda: [-45.0, -15.0])
    success: Annotated[float, Range(gt=0, le=1)] = 0.99  # a cell is robust at ε when this share reaches the target
    eps_max: Positive = 12.0      # bisection bracket [0, eps_max]
    tol: Positive = 0.02          # bisection stops when the bracket is this narrow
    paper_cell: list[float] = field(default_factory=lambda: [1.1, 0.09])
    time_model: TimeModel = "continuous"  # the paper's hybrid arcs (true state)

    def validate(self) -> None:
        if not self.tol < self.eps_max:
            raise ConfigError("experiment.tol", f"needs tol < eps_max, got tol={self.tol}, eps_max={self.eps_max}")
        if not self.cells():
            raise ConfigError("experiment.lam", "no (chi, lam) cell with lam < chi - 1")

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": list(self.disturbances), "occlusions": []}

    def cells(self) -> list[tuple[float, float]]:
        return [(c, v) for c in self.chi for v in self.lam if v < c - 1]

    def starts(self, ctx: Context) -> np.ndarray:
        return starts.NearK(n=ctx.n(self.n_agents), seed=ctx.seed, band=self.band, a_range=list(self.a_range))(ctx.scene)

    def success_rate(self, ctx: Context, x0, ctrl, dist: str, eps: float, scene=None) -> float:
        """Share of starts that get past the obstacle to the target up to the disturbance: |p - p_T| <= delta + ε
        at the horizon, never in N (a biased measurement moves the equilibrium by up to ε, so the strict
        |p - p_T| <= delta is lost at ε >= delta by every controller, whatever its hysteresis)."""
        d = ctx.disturbance(dist, eps=eps) if eps > 0 else None
        res = ctx.simulate(ctrl, x0, scene=scene, disturbance=d, record=False, model=self.time_model)
        return float(np.mean(practical_success(res, ctx.delta, eps)))

    def success_rates(self, ctx: Context, x0, ctrl, dist: str, cells: list, eps: list[float], scene=None):
        """`success_rate` of each cell `(chi, lam)` of `cells` (variants of the hybrid controller `ctrl`) at its `ε`,
        all in one batch: a hysteresis and a disturbance per agent (:meth:`HybridController.with_hysteresis` with
        arrays, `PerAgent`), each agent's outcome, arrival time and jumps those of a run of its own cell (only the
        final position of a batch's last agent to stop depends on the batch, docs/control.md, and the practical
        success reads it only for runs that end at the horizon). The continuous time model steps its agents apart
        (a variant per agent needs the whole batch at every call): its cells run one by one."""
        if self.time_model != "sampled" or len(cells) <= 1:
            return [self.success_rate(ctx, x0, ctrl.with_hysteresis(c, v), dist, e, scene)
                    for (c, v), e in zip(cells, eps)]
        n, k = len(x0), len(cells)
        chi, lam = (np.repeat([cell[j] for cell in cells], n) for j in (0, 1))
        d = None if max(eps) == 0 else PerAgent([ctx.disturbance(dist, eps=e) for e in eps], [n] * k)
        res = ctx.simulate(ctrl.with_hysteresis(chi, lam), np.tile(x0, (k, 1)), scene=scene, disturbance=d,
                           record=False, model=self.time_model)
        ctx.advance(k - 1)  # k simulations in one
        ok = practical_success(res, ctx.delta, np.repeat(np.asarray(eps, float), n)).reshape(k, n)
        return [float(np.mean(row)) for row in ok]

    def margins(self, ctx: Context, x0, ctrl, dist: str, cells: list, scene=None) -> list[tuple[float, float, int]]:
        """Per cell `(chi, lam)` of `cells`: (largest robust ε found, smallest failing ε found, simulations), by
        bisection on [0, eps_max] of that hysteresis variant of the hybrid controller `ctrl` (on `scene`); every
        step of the cells' bisections runs in one batch (:meth:`success_rates`)."""
        k, label = len(cells), ctx.label

        def step(r: int, rows: list) -> list:  # the progress line: the bisections' step and how many cells run it
            ctx.label = f"{label}, step {r}/{self.steps()} of {len(rows)} cell(s)"
            return rows
        lo, hi, sims, out = [0.0] * k, [self.eps_max] * k, [1] * k, [None] * k
        step(1, cells)
        for i, rate in enumerate(self.success_rates(ctx, x0, ctrl, dist, cells, [0.0] * k, scene)):
            if rate < self.success:
                out[i] = (float("nan"), 0.0, 1)
        live = step(2, [i for i in range(k) if out[i] is None])
        rates = self.success_rates(ctx, x0, ctrl, dist, [cells[i] for i in live], [hi[i] for i in live], scene)
        for i, rate in zip(live, rates):
            sims[i] += 1
            if rate >= self.success:
                out[i] = (hi[i], float("inf"), sims[i])
        while live := [i for i in range(k) if out[i] is None and hi[i] - lo[i] > self.tol]:
            mid = [0.5 * (lo[i] + hi[i]) for i in step(max(sims) + 1, live)]
            for i, m, rate in zip(live, mid, self.success_rates(ctx, x0, ctrl, dist, [cells[i] for i in live], mid,
                                                                scene)):
                sims[i] += 1
                if rate >= self.success:
                    lo[i] = m
                else:
                    hi[i] = m
        return [o if o is not None else (lo[i], hi[i], sims[i]) for i, o in enumerate(out)]

    def steps(self) -> int:
        """The most simulations one cell's bisection runs: eps = 0, eps_max, then halving down to `tol`."""
        return 2 + math.ceil(math.log2(self.eps_max / self.tol))

    def compute(self, ctx: Context) -> Results:
        x0 = self.starts(ctx)
        rows = []
        ctx.expect(len(self.disturbances) * len(self.cells()) * self.steps())
        hybrid = ctx.controller("hybrid")  # built once: the cells are its hysteresis variants
        for dist in self.disturbances:
            ctx.label = f"{dist} chi={','.join(f'{c:g}' for c in self.chi)}"
            for (chi, lam), (lo, hi, sims) in zip(self.cells(), self.margins(ctx, x0, hybrid, dist, self.cells())):
                ctx.advance(self.steps() - sims)  # a bisection that stopped early
                rows.append({"disturbance": dist, "chi": chi, "lam": lam, "eps_margin": lo, "eps_fails": hi,
                             "n_starts": len(x0), "simulations": sims})
        return Results({"margin": pd.DataFrame(rows)}, {"x0": x0}, {"paper_cell": list(self.paper_cell)})


# ------------------------------------------------------------------------------------- the scheme
@dataclass(kw_only=True)
class Scheme(Scenario):
    """Fig. 4: the closed loop's block diagram, drawn from code (nothing to compute)."""

    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_scheme"

    def uses(self):
        return {"controllers": [], "disturbances": [], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        return Results({}, {}, {})


# --------------------------------------------------------------------------------- sample-and-hold
@dataclass(kw_only=True)
class SampleAndHold(Scenario):
    """What the camera's sample-and-hold costs: the hybrid controller's arcs under the sampled model (a frame
    every `camera.period`), the continuous-time model, and the sampled model with dt = period = `limit_dt`
    (the dt -> 0 limit), on the true state without disturbance."""

    figures: ClassVar[str] = "pipeline.experiments.paper.figures:draw_sample_and_hold"

    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-45.0, 0.3], [-37.0, -17.0],
                                                                [-30.0, 20.0], [10.0, 25.0]])
    limit_dt: Positive = 0.0005

    def time_models(self, ctx: Context) -> set[str]:
        return {"sampled", "continuous"}

    def compute(self, ctx: Context) -> Results:
        x0 = np.asarray(self.initial_conditions, float)
        literal, guarded = ctx.controller("hybrid", guard=False), ctx.controller("hybrid", guard=True)
        runs = {"sampled": ctx.simulate(literal, x0, model="sampled", record_every=1),  # SPEC §3.3's literal rule
                "guarded": ctx.simulate(guarded, x0, model="sampled", record_every=1),  # with its sampled-data guard
                "continuous": ctx.simulate(literal, x0, model="continuous", record_every=1),
                "limit": simulate(ctx.scene, literal, x0,
                                  sim=SimSettings(dt=self.limit_dt, horizon=ctx.horizon, delta=ctx.delta),
                                  camera=CameraSettings(period=self.limit_dt), record=False)}
        df = pd.DataFrame({"x0": x0[:, 0], "y0": x0[:, 1]})
        for name, res in runs.items():
            df[f"t_{name}"] = res.metrics["time_to_target"]
            df[f"jumps_{name}"] = res.metrics["jumps"]
            df[f"path_{name}"] = res.metrics["path_length"]
        for name in ("sampled", "guarded"):
            df[f"pushouts_{name}"] = runs[name].metrics["pushouts"]
        df["guard_frames"] = runs["guarded"].metrics["guard_frames"]
        for name in ("sampled", "guarded", "continuous"):
            df[f"err_{name}_%"] = 100 * (df[f"t_{name}"] - df["t_limit"]) / df["t_limit"]
        arrays = {f"{k}_p": runs[k].p[:, 0] for k in ("sampled", "guarded", "continuous")}
        return Results({"sample_and_hold": df}, arrays, {"period": ctx.frame_period})
