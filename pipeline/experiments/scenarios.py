"""The paper's scenarios (SPEC §4), each a class with typed keyword arguments built from its experiment bundle
(`conf/experiment/<id>.yaml`, `_target_` + the scenario's parameters) by `hydra.utils.instantiate`.

A scenario computes (`compute(ctx) -> Results`, cached); :mod:`pipeline.experiments.figures` draws. `maps` names
the perception maps its results depend on and `uses()` the composed controllers, disturbances and cloud levels:
with the scenario's own parameters they make its cache key.
"""

from __future__ import annotations

import dataclasses
import typing
from dataclasses import dataclass, field
from typing import ClassVar

import numpy as np
import pandas as pd

from pipeline.control import in_covering_set, in_diamond, potential
from pipeline.errors import ConfigError
from pipeline.experiments.context import Context, Results, summarise, wilson
from pipeline.schema import _describe, _type_ok
from pipeline.sim.build import initial_conditions

Points = list[list[float]]


def _agent_rows(res, **cols) -> pd.DataFrame:
    df = res.metrics_frame()
    for k, v in cols.items():
        df[k] = v
    return df


def practical_success(res, delta: float, eps: float) -> np.ndarray:
    """Per agent: reached the target up to the disturbance (strict success, or |p - p_T| <= delta + ε at the
    end) without a collision. Under a disturbance of size ε the closed loop is only practically stable: its
    equilibrium moves by up to ε, so `delta` alone would count a vehicle resting at p_T + ε as a failure."""
    m = res.metrics
    return (m["success"] | (m["final_error"] <= delta + eps + 1e-9)) & ~m["collision"]


def _frame_index(t: np.ndarray, times) -> list[int]:
    return [int(min(np.searchsorted(t, s - 1e-9), len(t) - 1)) for s in times]


@dataclass(kw_only=True)
class Scenario:
    """Base: `id`, `title` and `paper` (what it reproduces) label the outputs; the rest is the computation."""

    id: str
    title: str
    paper: str = "–"
    maps: ClassVar[tuple[str, ...]] = ()
    DRAW_ONLY: ClassVar[tuple[str, ...]] = ("title", "paper")

    def __post_init__(self):
        hints = typing.get_type_hints(type(self))
        for f in dataclasses.fields(self):
            v = getattr(self, f.name)
            if not _type_ok(v, hints[f.name]):
                raise ConfigError(f"experiment.{f.name}", f"must be {_describe(hints[f.name])}, got {v!r}")
        self.validate()

    def validate(self) -> None:
        """Ranges of the scenario's parameters (ConfigError naming `experiment.<key>`)."""
        for name in ("n_agents", "n_agents_camera"):
            v = getattr(self, name, None)
            if v is not None and v < 1:
                raise ConfigError(f"experiment.{name}", f"must be >= 1, got {v}")
        for name in ("sigma", "p_fail", "eps", "min_band"):
            v = getattr(self, name, None)
            vals = v if isinstance(v, list) else [v]
            if v is not None and any(x < 0 for x in vals):
                raise ConfigError(f"experiment.{name}", f"must be >= 0, got {v}")
        if getattr(self, "p_fail", 0.0) >= 1:
            raise ConfigError("experiment.p_fail", f"must be in [0, 1), got {self.p_fail}")
        for name in ("grid_step", "grid_step_y"):
            v = getattr(self, name, None)
            if v is not None and not v > 0:
                raise ConfigError(f"experiment.{name}", f"must be > 0, got {v}")
        a_range = getattr(self, "a_range", None)
        if a_range is not None and not (len(a_range) == 2 and a_range[0] < a_range[1]):
            raise ConfigError("experiment.a_range", f"must be [min, max] with min < max, got {a_range}")
        tm = getattr(self, "time_model", "sampled")
        if tm not in ("sampled", "continuous"):
            raise ConfigError("experiment.time_model", f"must be sampled or continuous, got {tm!r}")
        ics = getattr(self, "initial_conditions", None)
        if ics is not None and not (ics and all(len(p) == 2 for p in ics)):
            raise ConfigError("experiment.initial_conditions", f"must be a non-empty list of [x, y], got {ics}")

    def uses(self) -> dict[str, list[str]]:
        """Names of the composed controllers, disturbances and cloud levels the computation reads."""
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": []}

    def check(self, ctx: Context) -> None:
        """Preflight: build what the computation will use (no simulation)."""
        for name in self.uses()["controllers"]:
            ctx.controller(name)
        for name in self.uses()["disturbances"]:
            ctx.disturbance(name)
        for level in self.uses()["occlusions"]:
            ctx.occlusion(level)
        ics = getattr(self, "initial_conditions", None)
        if ics is not None:
            initial_conditions({"mode": "points", "points": ics}, ctx.scene, ctx.scene_cfg,
                               path="experiment.initial_conditions")

    def compute(self, ctx: Context) -> Results:  # pragma: no cover - interface
        raise NotImplementedError


# --------------------------------------------------------------------------------- coverings
@dataclass(kw_only=True)
class Coverings(Scenario):
    grid_step: float = 0.25

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
    grid_step: float = 1.0
    grid_step_y: float = 0.25   # fine across K to resolve the ε band
    eps: float = 0.5            # size of the adversarial disturbance in the second column
    time_model: str = "continuous"  # the paper's hybrid arcs (true state): sim.model for this figure

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


# ------------------------------------------------------------------------------ noise + failure
@dataclass(kw_only=True)
class NoiseFailure(Scenario):
    sigma: float = 0.5
    p_fail: float = 0.5
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": ["gaussian"], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        ics = np.asarray(self.initial_conditions, float)
        noise = ctx.disturbance("gaussian", sigma=self.sigma)
        single = ctx.simulate(ctx.controller("hybrid"), ics, disturbance=noise, p_fail=self.p_fail,
                              measure=ctx.camera_measure("clean"))
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[1:2], kind="clean", sigma=self.sigma, p_fail=self.p_fail)
        rows = pd.concat([_agent_rows(single, role="vehicle"), _agent_rows(lead, role="leader"),
                          _agent_rows(foll, role="follower")], ignore_index=True)
        arrays = {"single_p": single.p, "single_m": single.m, "lead_p": lead.p, "foll_p": foll.p,
                  "foll_target": foll.target, "lead_t": lead.t, "foll_t": foll.t}
        return Results({"metrics": rows}, arrays, {"sigma": self.sigma, "p_fail": self.p_fail})


# --------------------------------------------------------------------------------------- occlusion
@dataclass(kw_only=True)
class Occlusion(Scenario):
    occlusion: str = "heavy"
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    n_agents: int = 100   # followers from random initial conditions for the table
    delta_practical: float = 3.0  # success also within this distance of the target
    maps: ClassVar[tuple[str, ...]] = ("clean", "occluded")

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": [], "occlusions": [self.occlusion]}

    def starts(self, ctx: Context) -> tuple[np.ndarray, np.ndarray]:
        """Leaders (all at the first initial condition) and followers (random, the first at the last one)."""
        ics = np.asarray(self.initial_conditions, float)
        n_mc = ctx.n(self.n_agents)
        leaders = np.repeat(ics[:1], n_mc, 0)
        followers = initial_conditions({"mode": "random", "n": n_mc, "seed": ctx.seed, "margin": 3.0},
                                       ctx.scene, ctx.scene_cfg)
        followers[0] = ics[-1]
        return leaders, followers

    def follow(self, ctx: Context, kind: str, level: str | None, leaders, followers):
        """The followers with map `kind` on `level` clouds: per-agent rows (with the mean tracking error of the
        perceived leader), the leader and follower runs and the tracking errors (T, N)."""
        lead, foll, track = ctx.leader_follower(leaders, followers, kind=kind, level=level)
        err = np.hypot(*(foll.target - track.position(foll.t)).transpose(2, 0, 1))
        df = _agent_rows(foll, map=kind, occlusion=level)
        df["tracking_error_mean"] = np.nanmean(err, axis=0)
        return df, lead, foll, err

    @staticmethod
    def summary(metrics: pd.DataFrame, by: list[str], seed: int, delta_practical: float) -> pd.DataFrame:
        table = summarise(metrics, by, seed=seed, delta_practical=delta_practical)
        g = metrics.groupby(by, sort=False)
        table["tracking_error_mean"] = g["tracking_error_mean"].mean().to_numpy()
        # the follower stops next to a leader it only sees through clouds: how close it gets matters more
        # than the strict |p - p_T| <= delta success
        table["final_error_median"] = g["final_error"].median().to_numpy()
        table["within_3_units"] = g["final_error"].apply(lambda e: float((e <= 3.0).mean())).to_numpy()
        return table

    def compute(self, ctx: Context) -> Results:
        level = self.occlusion
        leaders, followers = self.starts(ctx)
        rows, arrays = [], {}
        for kind in ("clean", "occluded"):
            df, lead, foll, err = self.follow(ctx, kind, level, leaders, followers)
            rows.append(df)
            arrays[f"{kind}_foll_p"] = foll.p[:, 0]
            arrays[f"{kind}_foll_target"] = foll.target[:, 0]
            arrays[f"{kind}_lead_p"] = lead.p[:, 0]
            arrays[f"{kind}_err"] = err[:, 0]
        metrics = pd.concat(rows, ignore_index=True)
        table = self.summary(metrics, ["map", "occlusion"], ctx.seed, self.delta_practical)
        return Results({"metrics": metrics, "summary": table}, arrays, {"level": level})


# --------------------------------------------------------------------------------- leader-follower
@dataclass(kw_only=True)
class LeaderFollower(Scenario):
    instants: list[int] = field(default_factory=lambda: [1, 90, 180])   # camera frames
    sigma: float = 0.0
    grid_step: float = 0.5
    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": ["gaussian"] if self.sigma > 0 else [], "occlusions": []}

    def compute(self, ctx: Context) -> Results:
        ics = np.asarray(self.initial_conditions, float)
        lead, foll, _ = ctx.leader_follower(ics[:1], ics[-1:], kind="clean", sigma=self.sigma)
        frames = list(self.instants)
        period = ctx.frame_period or ctx.dt
        idx = _frame_index(foll.t, [f * period for f in frames])
        (x0, x1), (y0, y1) = ctx.arena
        xs, ys = np.arange(x0, x1 + 1e-9, self.grid_step), np.arange(y0, y1 + 1e-9, self.grid_step)
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


# ---------------------------------------------------------------------------- perception closeness
@dataclass(kw_only=True)
class PerceptionCloseness(Scenario):
    initial_conditions: Points = field(default_factory=lambda: [[-37.0, -17.0]])
    maps: ClassVar[tuple[str, ...]] = ("clean",)
    errormaps: ClassVar[tuple[str, ...]] = ("clean",)

    def compute(self, ctx: Context) -> Results:
        x0 = np.asarray(self.initial_conditions, float)
        res = ctx.simulate(ctx.controller("hybrid"), x0, measure=ctx.camera_measure("clean"))
        err = np.hypot(*(res.m - res.p).transpose(2, 0, 1))
        eps, source = ctx.eps_perception("clean", "none")
        table = pd.DataFrame([{"eps": eps, "eps_source": source, "max_error_on_run": float(err.max()),
                               "mean_error_on_run": float(err.mean()), "inside_tube": float((err <= eps).mean()),
                               "success": bool(res.metrics["success"][0])}])
        return Results({"closeness": table}, {"p": res.p[:, 0], "m": res.m[:, 0]}, {"eps": eps})


# ------------------------------------------------------------------------------- robustness sweep
@dataclass(kw_only=True)
class RobustnessSweep(Scenario):
    eps: list[float] = field(default_factory=lambda: [0.0, 0.1, 0.25, 0.5, 1.0, 1.5])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial", "alternating"])
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_agents: int = 200      # initial conditions within eps of K per cell
    min_band: float = 0.1    # at eps = 0 the starts are within this band of K
    a_range: list[float] = field(default_factory=lambda: [-45.0, -15.0])
    time_model: str = "continuous"  # the paper's hybrid arcs (true state)

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": list(self.disturbances), "occlusions": []}

    def sweep(self, ctx: Context, scene, label: str) -> pd.DataFrame:
        n = ctx.n(self.n_agents)
        rows = []
        for dist in self.disturbances:
            for eps in self.eps:
                band = max(eps, self.min_band)
                x0 = initial_conditions({"mode": "near_k", "n": n, "seed": ctx.seed, "band": band,
                                         "a_range": list(self.a_range)}, scene)
                for ctrl in self.controllers:
                    d = ctx.disturbance(dist, eps=eps) if eps > 0 else None
                    res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, disturbance=d, record=False,
                                       model=self.time_model)
                    s, c = int(res.metrics["success"].sum()), int(res.metrics["collision"].sum())
                    sp = int(practical_success(res, ctx.delta, eps).sum())
                    lo, hi = wilson(s, n)
                    plo, phi = wilson(sp, n)
                    rows.append({"scene": label, "disturbance": dist, "eps": eps, "controller": ctrl, "n": n,
                                 "success_rate": s / n, "success_lo": float(lo), "success_hi": float(hi),
                                 "practical_success_rate": sp / n, "practical_lo": float(plo),
                                 "practical_hi": float(phi), "collision_rate": c / n,
                                 "stalled": float(np.mean(res.metrics["outcome"] == "stalled")),
                                 "mean_jumps": float(res.metrics["jumps"].mean())})
        return pd.DataFrame(rows)

    def compute(self, ctx: Context) -> Results:
        return Results({"sweep": self.sweep(ctx, ctx.scene, "default")}, {}, {})


# ------------------------------------------------------------------------------------ Monte Carlo
@dataclass(kw_only=True)
class MonteCarlo(Scenario):
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    sigma: float = 0.5
    p_fail: float = 0.5
    occlusion: str = "heavy"
    camera: bool = True          # include the camera-in-the-loop occlusion conditions (one per map)
    n_agents: int = 300          # random initial conditions, true-state conditions
    n_agents_camera: int = 100   # random initial conditions, camera conditions (each frame renders + infers them all)
    delta_practical: float = 3.0  # success also within this distance (about the perception error near the target)

    @property
    def maps(self) -> tuple[str, ...]:  # type: ignore[override]
        return ("clean", "occluded") if self.camera else ()

    def uses(self):
        return {"controllers": list(self.controllers), "disturbances": ["gaussian"],
                "occlusions": [self.occlusion] if self.camera else []}

    def conditions(self, ctx: Context, camera: bool):
        noise = ctx.disturbance("gaussian", sigma=self.sigma)
        conds = [("none", {}), (f"gaussian σ={self.sigma}", {"disturbance": noise}),
                 (f"gaussian σ={self.sigma} + {self.p_fail:.0%} failure", {"disturbance": noise, "p_fail": self.p_fail})]
        if camera:
            for kind in ("clean", "occluded"):
                conds.append((f"{self.occlusion} occlusion, {kind} map", {"camera": (kind, self.occlusion)}))
        return conds

    def metrics(self, ctx: Context, scene, label: str, camera: bool) -> pd.DataFrame:
        n = ctx.n(self.n_agents)
        n_cam = ctx.n(self.n_agents_camera)
        x0_all = initial_conditions({"mode": "random", "n": max(n, n_cam), "seed": ctx.seed, "margin": 2.0},
                                    scene, ctx.scene_cfg)
        frames = []
        for cond, kw in self.conditions(ctx, camera):
            kw = dict(kw)
            measure, x0 = None, x0_all[:n]
            if "camera" in kw:
                kind, level = kw.pop("camera")
                measure, x0 = ctx.camera_measure(kind, level), x0_all[:n_cam]
            for ctrl in self.controllers:
                res = ctx.simulate(ctx.controller(ctrl, scene=scene), x0, scene=scene, measure=measure, record=False, **kw)
                frames.append(_agent_rows(res, scene=label, condition=cond))
        return pd.concat(frames, ignore_index=True)

    def compute(self, ctx: Context) -> Results:
        metrics = self.metrics(ctx, ctx.scene, "default", camera=self.camera)
        table = summarise(metrics, ["condition", "controller"], seed=ctx.seed, delta_practical=self.delta_practical)
        return Results({"metrics": metrics, "summary": table}, {}, {})


# ---------------------------------------------------------------------------------- authors' scene
@dataclass(kw_only=True)
class AuthorsCode(Scenario):
    """The authors' released-code scene (composed as `other_scene`: r = 8, apex 1.5 r, log barrier) side by side
    with the default, through the true-state scenarios (the maps are trained on the default scene's images)."""

    eps: list[float] = field(default_factory=lambda: [0.0, 0.25, 0.5, 1.0])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial"])
    controllers: list[str] = field(default_factory=lambda: ["hybrid", "smooth", "cbf"])
    n_agents: int = 200
    min_band: float = 0.1
    a_range: list[float] = field(default_factory=lambda: [-45.0, -15.0])
    sigma: float = 0.5
    p_fail: float = 0.5
    time_model: str = "continuous"  # of the sweep (the Monte Carlo has camera failures: sampled)

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

    chi: list[float] = field(default_factory=lambda: [1.05, 1.1, 1.2, 1.4, 1.8])
    lam: list[float] = field(default_factory=lambda: [0.01, 0.03, 0.09, 0.2, 0.4])
    disturbances: list[str] = field(default_factory=lambda: ["adversarial", "alternating"])
    n_agents: int = 100          # starts near K (a < -c, |b| < band), the same in every cell
    band: float = 0.5
    a_range: list[float] = field(default_factory=lambda: [-45.0, -15.0])
    success: float = 0.99        # a cell is robust at ε when this share of the starts reaches the target
    eps_max: float = 12.0        # bisection bracket [0, eps_max]
    tol: float = 0.02            # bisection stops when the bracket is this narrow
    paper_cell: list[float] = field(default_factory=lambda: [1.1, 0.09])
    time_model: str = "continuous"  # the paper's hybrid arcs (true state)

    def validate(self) -> None:
        super().validate()
        if not (0 < self.success <= 1):
            raise ConfigError("experiment.success", f"must be in (0, 1], got {self.success}")
        if not (self.eps_max > 0 and 0 < self.tol < self.eps_max):
            raise ConfigError("experiment.tol", f"needs 0 < tol < eps_max, got tol={self.tol}, eps_max={self.eps_max}")
        if not self.chi or any(c <= 1 for c in self.chi):
            raise ConfigError("experiment.chi", f"must be a non-empty list of values > 1, got {self.chi}")
        if not self.lam or any(v <= 0 for v in self.lam):
            raise ConfigError("experiment.lam", f"must be a non-empty list of values > 0, got {self.lam}")
        if not self.cells():
            raise ConfigError("experiment.lam", "no (chi, lam) cell with lam < chi - 1")

    def uses(self):
        return {"controllers": ["hybrid"], "disturbances": list(self.disturbances), "occlusions": []}

    def cells(self) -> list[tuple[float, float]]:
        return [(c, v) for c in self.chi for v in self.lam if v < c - 1]

    def starts(self, ctx: Context) -> np.ndarray:
        return initial_conditions({"mode": "near_k", "n": ctx.n(self.n_agents), "seed": ctx.seed, "band": self.band,
                                   "a_range": list(self.a_range)}, ctx.scene)

    def success_rate(self, ctx: Context, x0, chi: float, lam: float, dist: str, eps: float) -> float:
        """Share of starts that get past the obstacle to the target up to the disturbance: |p - p_T| <= delta + ε
        at the horizon, never in N (a biased measurement moves the equilibrium by up to ε, so the strict
        |p - p_T| <= delta is lost at ε >= delta by every controller, whatever its hysteresis)."""
        d = ctx.disturbance(dist, eps=eps) if eps > 0 else None
        res = ctx.simulate(ctx.controller("hybrid", chi=chi, lam=lam), x0, disturbance=d, record=False,
                           model=self.time_model)
        return float(np.mean(practical_success(res, ctx.delta, eps)))

    def margin(self, ctx: Context, x0, chi: float, lam: float, dist: str) -> tuple[float, float, int]:
        """(largest robust ε found, smallest failing ε found, simulations): bisection on [0, eps_max]."""
        lo, hi, sims = 0.0, self.eps_max, 1
        if self.success_rate(ctx, x0, chi, lam, dist, 0.0) < self.success:
            return float("nan"), 0.0, sims
        sims += 1
        if self.success_rate(ctx, x0, chi, lam, dist, hi) >= self.success:
            return hi, float("inf"), sims
        while hi - lo > self.tol:
            mid = 0.5 * (lo + hi)
            sims += 1
            if self.success_rate(ctx, x0, chi, lam, dist, mid) >= self.success:
                lo = mid
            else:
                hi = mid
        return lo, hi, sims

    def compute(self, ctx: Context) -> Results:
        x0 = self.starts(ctx)
        rows = []
        for dist in self.disturbances:
            for chi, lam in self.cells():
                lo, hi, sims = self.margin(ctx, x0, chi, lam, dist)
                rows.append({"disturbance": dist, "chi": chi, "lam": lam, "eps_margin": lo, "eps_fails": hi,
                             "n_starts": len(x0), "simulations": sims})
        return Results({"margin": pd.DataFrame(rows)}, {"x0": x0}, {"paper_cell": list(self.paper_cell)})


# ------------------------------------------------------------------------------------- the scheme
@dataclass(kw_only=True)
class Scheme(Scenario):
    """Fig. 4: the closed loop's block diagram, drawn from code (nothing to compute)."""

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

    initial_conditions: Points = field(default_factory=lambda: [[-12.0, 2.0], [-45.0, 0.3], [-37.0, -17.0],
                                                                [-30.0, 20.0], [10.0, 25.0]])
    limit_dt: float = 0.0005

    def validate(self) -> None:
        super().validate()
        if not self.limit_dt > 0:
            raise ConfigError("experiment.limit_dt", f"must be > 0, got {self.limit_dt}")

    def compute(self, ctx: Context) -> Results:
        from pipeline.sim import simulate

        x0 = np.asarray(self.initial_conditions, float)
        runs = {"sampled": ctx.simulate(ctx.controller("hybrid"), x0, model="sampled", record_every=1),
                "continuous": ctx.simulate(ctx.controller("hybrid"), x0, model="continuous", record_every=1),
                "limit": simulate(ctx.scene, ctx.controller("hybrid"), x0, dt=self.limit_dt, horizon=ctx.horizon,
                                  delta=ctx.delta, camera_period=self.limit_dt, record=False)}
        df = pd.DataFrame({"x0": x0[:, 0], "y0": x0[:, 1]})
        for name, res in runs.items():
            df[f"t_{name}"] = res.metrics["time_to_target"]
            df[f"jumps_{name}"] = res.metrics["jumps"]
            df[f"path_{name}"] = res.metrics["path_length"]
        for name in ("sampled", "continuous"):
            df[f"err_{name}_%"] = 100 * (df[f"t_{name}"] - df["t_limit"]) / df["t_limit"]
        arrays = {"sampled_p": runs["sampled"].p[:, 0], "continuous_p": runs["continuous"].p[:, 0]}
        return Results({"sample_and_hold": df}, arrays, {"period": ctx.frame_period})
