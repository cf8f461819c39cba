"""Shared machinery of the paper scenarios: context (scene, controllers, maps, camera), simulation helpers,
confidence intervals, and writers for figures (PNG + PDF), tables (CSV + Markdown + LaTeX) and the index."""

from __future__ import annotations

import functools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd
from omegaconf import OmegaConf

from pipeline import tracking
from pipeline.cli import CONF_DIR
from pipeline.control import Scene
from pipeline.errors import ConfigError
from pipeline.experiments.measure import CameraMeasure, FollowerTarget, LeaderTrack, OracleMap
from pipeline.sim import Gaussian, simulate
from pipeline.sim.build import arena_bounds, build_controller, build_disturbance, build_scene
from pipeline.sim.simulator import true_state


# --------------------------------------------------------------------------------------- results
@dataclass
class Results:
    """What a scenario computes (cached): tables, arrays and small facts (JSON)."""

    tables: dict[str, pd.DataFrame] = field(default_factory=dict)
    arrays: dict[str, np.ndarray] = field(default_factory=dict)
    info: dict = field(default_factory=dict)

    def save(self, folder: Path) -> None:
        for name, df in self.tables.items():
            df.to_csv(folder / f"{name}.csv", index=False)
        if self.arrays:
            np.savez_compressed(folder / "arrays.npz", **self.arrays)
        (folder / "info.json").write_text(json.dumps(self.info, indent=2, default=_json_default) + "\n")

    @classmethod
    def load(cls, folder: Path) -> Results:
        info = json.loads((folder / "info.json").read_text())
        tables = {p.stem: pd.read_csv(p) for p in sorted(folder.glob("*.csv"))}
        arrays = {}
        if (folder / "arrays.npz").is_file():
            with np.load(folder / "arrays.npz", allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        return cls(tables, arrays, info)


def _json_default(o):
    if isinstance(o, np.integer | np.floating | np.bool_):
        return o.item()
    if isinstance(o, np.ndarray):
        return o.tolist()
    return str(o)


# ---------------------------------------------------------------------------------------- context
class Context:
    """Everything a scenario needs, built from the resolved config; maps are loaded lazily."""

    def __init__(self, cfg):
        self.cfg = cfg
        self.exp = tracking.to_plain(cfg.experiment)
        self.scene_cfg = tracking.to_plain(cfg.scene)
        self.scene: Scene = build_scene(cfg.scene)
        self.arena = arena_bounds(cfg.scene)
        self.scale = float(cfg.get("scale", 1.0))
        if not self.scale > 0:
            raise ConfigError("scale", f"must be > 0, got {self.scale}")
        self.perception = str(cfg.get("perception", "cnn"))
        if self.perception not in ("cnn", "oracle"):
            raise ConfigError("perception", f"must be cnn or oracle (a perfect map), got {self.perception!r}")
        self.dt, self.horizon, self.delta = float(cfg.sim.dt), float(cfg.sim.horizon), float(cfg.sim.delta)
        self.frame_period = cfg.camera.period
        self.seed = int(cfg.sim.seed)
        self.used: dict[str, str] = {}  # inputs used (map/dataset/error-map ids), for the index

    # sizes -------------------------------------------------------------------------------------
    def n(self, count: int, minimum: int = 2) -> int:
        return max(minimum, int(round(count * self.scale)))

    def param(self, key: str, default=None):
        return self.exp.get(key, default)

    # controllers -------------------------------------------------------------------------------
    def controller(self, name: str = "hybrid", scene: Scene | None = None, **overrides):
        """`hybrid` uses the run's `controller` group (chi, lam, ...); smooth/cbf their own YAML."""
        scene = scene or self.scene
        if name == self.cfg.controller.get("name"):
            node = OmegaConf.create(tracking.to_plain(self.cfg.controller))
        else:
            path = CONF_DIR / "controller" / f"{name}.yaml"
            if not path.is_file():
                raise ConfigError("experiment.controllers", f"unknown controller {name!r}")
            node = OmegaConf.load(path)
        for k, v in overrides.items():
            node[k] = v
        return build_controller(node, scene)

    def disturbance(self, name: str, **params):
        node = OmegaConf.load(CONF_DIR / "disturbance" / f"{name}.yaml")
        for k, v in params.items():
            node[k] = v
        return build_disturbance(node)

    # perception ------------------------------------------------------------------------------
    @functools.cache  # noqa: B019 - one context per run
    def perception_map(self, kind: str = "clean"):
        if self.perception == "oracle":
            self.used[f"map:{kind}"] = "oracle (perfect map)"
            return OracleMap()
        from pipeline.train import load_perception_map

        ref = tracking.to_plain(self.cfg.maps).get(kind)
        if ref is None:
            raise ConfigError(f"maps.{kind}", "no perception map configured")
        pm = load_perception_map(ref, models_dir=self.cfg.paths.models_dir)
        self.used[f"map:{kind}"] = f"{pm.name}-{pm.id} (dataset {pm.manifest.get('dataset_name')}-{pm.manifest.get('dataset_id')})"
        return pm

    def map_ids(self, kinds) -> dict:
        """Ids of the maps a scenario will use (part of its cache key)."""
        if self.perception == "oracle":
            return {k: "oracle" for k in kinds}
        return {k: self.perception_map(k).id for k in kinds}

    @functools.cache  # noqa: B019
    def camera(self):
        from pipeline.render import Camera

        pm = self.perception_map("clean")
        if isinstance(pm, OracleMap):
            return Camera.from_config(self.cfg.render, self.scene_cfg)
        return pm.camera()

    def occlusion(self, level: str | None):
        if level in (None, "none"):
            return None
        from pipeline.render import load_occlusion

        return load_occlusion(level, field="experiment.occlusion")

    def eps_perception(self, kind: str = "clean", level: str = "none") -> tuple[float | None, str]:
        """ε of the error map of a perception map at an occlusion level (p95 over the operational set)."""
        if self.perception == "oracle":
            return 0.0, "oracle"
        try:
            from pipeline.errormap.stage import load_error_map

            pm = self.perception_map(kind)
            s = load_error_map(pm.name, errormaps_dir=self.cfg.paths.errormaps_dir)
        except Exception:  # noqa: BLE001 - no error map yet: the caller falls back to measured errors
            return None, "none"
        if s.get("model", {}).get("id") != pm.id or level not in s.get("levels", {}):
            return None, "none"
        self.used[f"errormap:{kind}"] = f"{s['path'].name}"
        return float(s["levels"][level]["p95"]), s["path"].name

    # simulation ------------------------------------------------------------------------------
    def simulate(self, controller, x0, *, scene: Scene | None = None, disturbance=None, measure=None,
                 target_fn=None, p_fail: float = 0.0, seed: int | None = None, record: bool = True,
                 record_every: int | None = None, horizon: float | None = None):
        return simulate(
            scene or self.scene, controller, np.asarray(x0, float), dt=self.dt, horizon=horizon or self.horizon,
            delta=self.delta, camera_period=self.frame_period, p_fail=p_fail, disturbance=disturbance,
            measure=measure, target_fn=target_fn, seed=self.seed if seed is None else seed,
            record_every=record_every or int(self.cfg.sim.record_every), record=record,
            stop_on_success=bool(self.cfg.sim.stop_on_success),
            progress=len(x0) >= 2000 and sys.stderr.isatty(),
        )

    def camera_measure(self, kind: str = "clean", level: str | None = None):
        pm = self.perception_map(kind)
        if isinstance(pm, OracleMap):
            return true_state
        return CameraMeasure(self.camera(), pm, self.occlusion(level))

    def leader_follower(self, leader_x0, follower_x0, *, kind: str = "clean", level: str | None = None,
                        sigma: float = 0.0, p_fail: float = 0.0, seed: int | None = None,
                        follower_controller: str = "hybrid"):
        """Leader: hybrid on its own noisy state towards p_T. Follower: its own noisy state, target = the
        leader's position seen by its camera through the map (failures hold the last estimate)."""
        seed = self.seed if seed is None else seed
        noise = Gaussian(sigma=sigma) if sigma > 0 else None
        every = max(1, round((self.frame_period or self.dt) / self.dt))
        lead = self.simulate(self.controller("hybrid"), leader_x0, disturbance=noise, seed=seed,
                             record_every=every)
        track = LeaderTrack(lead.t, lead.p)
        pm = self.perception_map(kind)
        target = FollowerTarget(track, None if isinstance(pm, OracleMap) else self.camera(), pm,
                                self.occlusion(level))
        foll = self.simulate(self.controller(follower_controller), follower_x0, disturbance=noise,
                             target_fn=target, p_fail=p_fail, seed=seed + 1, record_every=every)
        return lead, foll, track


# -------------------------------------------------------------------------------------- statistics
def wilson(successes: np.ndarray | int, n: np.ndarray | int, z: float = 1.96):
    """95% Wilson score interval of a binomial proportion (works for 0 and n successes)."""
    s, n = np.asarray(successes, float), np.asarray(n, float)
    p = np.where(n > 0, s / np.maximum(n, 1), np.nan)
    denom = 1 + z**2 / n
    centre = (p + z**2 / (2 * n)) / denom
    half = z * np.sqrt(p * (1 - p) / n + z**2 / (4 * n**2)) / denom
    return centre - half, centre + half


def mean_ci(x: np.ndarray, z: float = 1.96):
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return math.nan, math.nan, math.nan
    m = float(x.mean())
    h = float(z * x.std(ddof=1) / math.sqrt(len(x))) if len(x) > 1 else math.nan
    return m, m - h, m + h


def median_ci(x: np.ndarray, rng: np.random.Generator, n_boot: int = 1000):
    """Median with a 95% bootstrap interval (vectorised resampling)."""
    x = np.asarray(x, float)
    x = x[np.isfinite(x)]
    if len(x) == 0:
        return math.nan, math.nan, math.nan
    boot = np.median(x[rng.integers(0, len(x), (n_boot, len(x)))], axis=1)
    return float(np.median(x)), float(np.percentile(boot, 2.5)), float(np.percentile(boot, 97.5))


def summarise(metrics: pd.DataFrame, by: list[str], seed: int = 0) -> pd.DataFrame:
    """Monte Carlo table: success/collision rates with Wilson CIs, median time (bootstrap CI), min
    clearance and mean jumps, one row per group."""
    rng = np.random.default_rng(seed)
    rows = []
    for key, g in metrics.groupby(by, sort=False):
        key = key if isinstance(key, tuple) else (key,)
        n = len(g)
        s, c = int(g["success"].sum()), int(g["collision"].sum())
        s_lo, s_hi = wilson(s, n)
        c_lo, c_hi = wilson(c, n)
        t_med, t_lo, t_hi = median_ci(g.loc[g["success"].astype(bool), "time_to_target"].to_numpy(), rng)
        j_mean, j_lo, j_hi = mean_ci(g["jumps"].to_numpy())
        rows.append({**dict(zip(by, key)), "n": n, "success_rate": s / n, "success_lo": float(s_lo),
                     "success_hi": float(s_hi), "collision_rate": c / n, "collision_lo": float(c_lo),
                     "collision_hi": float(c_hi), "median_time": t_med, "median_time_lo": t_lo,
                     "median_time_hi": t_hi, "final_error_median": float(g["final_error"].median()),
                     "min_clearance": float(g["min_clearance"].min()),
                     "mean_jumps": j_mean, "mean_jumps_lo": j_lo, "mean_jumps_hi": j_hi})
    return pd.DataFrame(rows)


# ----------------------------------------------------------------------------------------- writers
def _fmt(v) -> str:
    if isinstance(v, float | np.floating):
        if not np.isfinite(v):
            return "–"
        return f"{v:.3g}" if abs(v) < 1e4 else f"{v:.0f}"
    return str(v)


def markdown_table(df: pd.DataFrame) -> str:
    head = "| " + " | ".join(map(str, df.columns)) + " |"
    sep = "|" + "|".join("---" for _ in df.columns) + "|"
    body = ["| " + " | ".join(_fmt(v) for v in row) + " |" for row in df.itertuples(index=False)]
    return "\n".join([head, sep, *body]) + "\n"


def latex_table(df: pd.DataFrame, caption: str, label: str) -> str:
    esc = lambda s: str(s).replace("_", r"\_").replace("%", r"\%").replace("&", r"\&")  # noqa: E731
    lines = [r"\begin{table}[t]", r"\centering", rf"\caption{{{esc(caption)}}}", rf"\label{{tab:{label}}}",
             r"\begin{tabular}{" + "l" * len(df.columns) + "}", r"\toprule",
             " & ".join(esc(c) for c in df.columns) + r" \\", r"\midrule"]
    lines += [" & ".join(esc(_fmt(v)) for v in row) + r" \\" for row in df.itertuples(index=False)]
    lines += [r"\bottomrule", r"\end{tabular}", r"\end{table}"]
    return "\n".join(lines) + "\n"


class Outputs:
    """Writes a scenario's figures and tables into the paper folder and records them for index.md."""

    def __init__(self, paper_dir: Path, exp_id: str):
        self.dir = Path(paper_dir)
        self.dir.mkdir(parents=True, exist_ok=True)
        self.exp_id = exp_id
        self.items: list[dict] = []

    def figure(self, fig, stem: str, caption: str) -> list[Path]:
        from pipeline.viz import save

        paths = [Path(p) for p in save(fig, self.dir / stem, formats=("png", "pdf"))]
        self.items.append({"kind": "figure", "files": [p.name for p in paths], "caption": caption})
        return paths

    def table(self, df: pd.DataFrame, stem: str, caption: str) -> list[Path]:
        paths = [self.dir / f"{stem}.{ext}" for ext in ("csv", "md", "tex")]
        df.to_csv(paths[0], index=False)
        paths[1].write_text(f"**{caption}**\n\n" + markdown_table(df))
        paths[2].write_text(latex_table(df, caption, stem))
        self.items.append({"kind": "table", "files": [p.name for p in paths], "caption": caption})
        return paths


def write_index(paper_dir: Path) -> Path:
    """index.md from every experiment's entry in `<paper_dir>/index/*.json`."""
    paper_dir = Path(paper_dir)
    entries = [json.loads(p.read_text()) for p in sorted((paper_dir / "index").glob("*.json"))]
    lines = ["# Regenerated figures and tables", "",
             "Made by `make paper` (or each experiment alone with the command shown). Ids name the tracked",
             "datasets, perception maps and error maps each result used.", ""]
    for e in entries:
        lines += [f"## {e['id']} — {e['title']}", "", f"- command: `{e['command']}`",
                  f"- reproduces: {e.get('paper', '–')}"]
        for k, v in sorted(e.get("inputs", {}).items()):
            lines.append(f"- {k}: `{v}`")
        lines.append(f"- results cache: `{e.get('cache', '–')}`")
        lines.append("")
        for it in e["items"]:
            files = ", ".join(f"[{f}]({f})" for f in it["files"])
            lines.append(f"- {it['kind']}: {it['caption']} — {files}")
        lines.append("")
    path = paper_dir / "index.md"
    path.write_text("\n".join(lines))
    return path


def draw_frame(ax, scene: Scene, arena, diamond: bool = True):
    from pipeline.viz import draw_scene

    draw_scene(ax, scene, arena, diamond=diamond)
    ax.set_xlim(*arena[0])
    ax.set_ylim(*arena[1])
    ax.set_aspect("equal")
