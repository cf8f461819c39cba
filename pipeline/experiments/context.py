"""What a scenario computes with (cached results depend on this code, not on the drawing code): the context
built from the run's composed config (scene, the controllers, disturbances and cloud levels under
comparison, perception maps pinned by id, camera), results, and statistics."""

from __future__ import annotations

import functools
import json
import math
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pandas as pd

from pipeline import lineage, tracking
from pipeline.config import build, settings
from pipeline.control import Scene
from pipeline.errormap.read import load_error_map
from pipeline.errors import ConfigError, DatasetError, ModelError
from pipeline.experiments.settings import ExperimentSettings
from pipeline.perception.adversary import is_attack, proposition1_direction
from pipeline.perception.measure import CameraMeasure, FollowerTarget, LeaderTrack, OracleMap
from pipeline.plants import SingleIntegrator
from pipeline.render import load_occlusion
from pipeline.sim import frame_steps, simulate, true_state
from pipeline.sim.metrics import summarise_agents, wilson  # noqa: F401 - wilson: for the scenarios
from pipeline.sim.settings import check_vehicle, run_keywords


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


class Context:
    """Everything a scenario needs, built from the composed config; maps are loaded lazily, by id, with
    `load_map(folder, models_dir=, device=)` (the stage passes `pipeline.perception.maps.load_perception_map`; a
    preflight check passes none: it loads no map and imports no torch)."""

    def __init__(self, cfg, load_map=None):
        self.cfg = cfg
        self._load_map = load_map
        self.settings: ExperimentSettings = settings(cfg, ExperimentSettings)
        self.scene_cfg = tracking.to_plain(cfg.scene)
        self.scene: Scene = build(cfg.scene, "scene")
        self.arena = self.scene.bounds
        self.scale = self.settings.scale
        self.perception = self.settings.perception
        self.camera_settings = build(cfg.camera, "camera")
        self.sim = build(cfg.sim, "sim")
        # the plant of every run (`vehicle`, SPEC §3.7): controllers steer its steered point in its steering scene
        self.vehicle = build(cfg.vehicle, "vehicle") if cfg.get("vehicle") is not None else SingleIntegrator()
        check_vehicle(self.vehicle, self.sim)
        self.dt, self.horizon, self.delta = self.sim.dt, self.sim.horizon, self.sim.delta
        frame_steps(self.dt, self.camera_settings.period)
        self.frame_period = self.camera_settings.period
        self.gate = self.camera_settings.gate  # camera.gate: doubtful frames of a map with an uncertainty head are failures
        self.seed = self.sim.seed
        self.used: dict[str, str] = {}  # inputs used (map/dataset/error-map ids), for the index
        self._maps: dict = {}
        self.bar = None  # the stage's progress (pipeline.progress): one step per simulation (a batch of agents)
        self.label = ""  # what the scenario is at (a sweep's cell), shown with each step

    # sizes -------------------------------------------------------------------------------------
    def n(self, count: int, minimum: int = 2) -> int:
        return max(minimum, int(round(count * self.scale)))

    def expect(self, runs: int) -> None:
        """How many simulations the scenario will run (the total of the stage's progress), when it knows it."""
        if self.bar is not None:
            self.bar.total = int(runs)

    def advance(self, runs: int = 1, what: str = "") -> None:
        """`runs` simulations done (or skipped: a bisection that stopped early), `what` the last one."""
        if self.bar is not None:
            if what:
                self.bar.set_postfix_str(what, refresh=False)
            self.bar.update(runs)

    # composed objects --------------------------------------------------------------------------
    def _node(self, group: str, name: str):
        """The node `<group>.<name>` a scenario names (in `experiment.<group>`)."""
        nodes = self.cfg[group]
        if name not in nodes:
            raise ConfigError(f"experiment.{group}", f"unknown {group[:-1]} {name!r}; known: {', '.join(nodes)}")
        return nodes[name]

    def controller(self, name: str = "hybrid", scene: Scene | None = None, **params):
        """The controller `controllers.<name>` of the composed config (hybrid: the run's `controller`), on the
        vehicle's steering scene of `scene` (the unicycle's look-ahead point: every disc inflated, SPEC §3.7)."""
        node = self._node("controllers", name)
        node = node if not params else {**tracking.to_plain(node), **params}
        ctrl = build(node, "controller" if name == "hybrid" else f"controllers.{name}",
                     scene=self.vehicle.steering_scene(scene or self.scene))
        ctrl.name = name
        return ctrl

    def disturbance(self, name: str, **params):
        """The disturbance `disturbances.<name>`; `params` set what the scenario sweeps (eps, sigma)."""
        return build(self._node("disturbances", name), f"disturbances.{name}", **params)

    def attack(self, name: str, **params):
        """The camera attack `disturbances.<name>` (pixel_attack, worst_cloud; docs/attacks.md); `params` set what
        the scenario sweeps (kappa, level). The worst cloud's level is checked here (a name of `occlusions`)."""
        att = self.disturbance(name)
        if not is_attack(att):
            raise ConfigError("experiment.attack", f"{name!r} is a state disturbance, not an attack through the camera "
                                                   "(pixel_attack, worst_cloud)")
        if att.kind == "cloud":  # the node's own level too (a sweep sets another): every key's bad value is caught
            load_occlusion(att.level, self.cfg.occlusions, field=f"disturbances.{name}.level")
        att = self.disturbance(name, **params) if params else att
        if att.kind == "cloud":
            load_occlusion(att.level, self.cfg.occlusions, field="experiment.levels")
        return att

    def occlusion(self, level: str | None):
        if level is None:
            return None
        occ = load_occlusion(level, self.cfg.occlusions, field="experiment.occlusion")
        return occ if occ.active else None

    def other_scene(self) -> tuple[str, Scene]:
        node = self.cfg.get("other_scene")
        if node is None:
            raise ConfigError("other_scene", "this experiment needs a second scene (defaults: /scene@other_scene)")
        return str(node.get("name", "other")), build(node, "other_scene")

    # perception ------------------------------------------------------------------------------
    def map_folder(self, kind: str = "clean"):
        """The folder of map `kind` (`maps.<kind>`: resolved by id, not loaded); None with a perfect map."""
        if self.perception == "oracle":
            return None
        ref = (tracking.to_plain(self.cfg.maps) or {}).get(kind)
        if ref is None:
            raise ConfigError(f"maps.{kind}", "no perception map configured")
        try:
            return lineage.resolve_map(ref, self.cfg.paths.models_dir, field=f"maps.{kind}",
                                       overrides=lineage.debug_overrides(self.cfg))
        except DatasetError as err:  # unknown name/id: the map's error, as load_perception_map reports it
            raise ModelError(str(err)) from None

    def perception_map(self, kind: str = "clean"):
        if kind in self._maps:
            return self._maps[kind]
        if self.perception == "oracle":
            self.used[f"map:{kind}"] = "oracle (perfect map)"
            self._maps[kind] = OracleMap()
            return self._maps[kind]
        if self._load_map is None:
            raise RuntimeError("this Context loads no perception map (built for a preflight check)")
        pm = self._load_map(self.map_folder(kind), models_dir=self.cfg.paths.models_dir, device=self.settings.device)
        self.used[f"map:{kind}"] = f"{pm.name}-{pm.id} (dataset {pm.manifest.get('dataset_name')}-{pm.manifest.get('dataset_id')})"
        self._maps[kind] = pm
        return pm

    def map_ids(self, kinds) -> dict:
        """Ids of the maps a scenario will use (part of its cache key), from their folders."""
        out = {}
        for k in kinds:
            folder = self.map_folder(k)
            out[k] = "oracle" if folder is None else folder.name.rsplit("-", 1)[1]
        return out

    @functools.cache  # noqa: B019
    def error_map(self, kind: str = "clean") -> dict | None:
        """Summary of the error map of map `kind` (`errormaps.<kind>`: an id, or null for the one the current
        errormap config computes for the map); None with a perfect map."""
        folder = self.map_folder(kind)
        if folder is None:
            return None
        map_id = folder.name.rsplit("-", 1)[1]
        ref = (tracking.to_plain(self.cfg.get("errormaps")) or {}).get(kind)
        em = lineage.resolve_errormap(ref, self.cfg.paths.errormaps_dir, folder, lineage.debug_overrides(self.cfg))
        s = load_error_map(em)
        if s.get("model", {}).get("id") != map_id:
            raise ConfigError(f"errormaps.{kind}", f"{em.name} is the error map of map {s['model'].get('id')}, "
                                                   f"not of {folder.name}")
        self.used[f"errormap:{kind}"] = em.name
        return s

    def eps_perception(self, kind: str = "clean", level: str = "none") -> tuple[float, str]:
        """ε of the error map of a perception map at an occlusion level (p95 over the operational set)."""
        s = self.error_map(kind)
        if s is None:
            return 0.0, "oracle"
        if level not in s.get("levels", {}):
            raise ConfigError("errormaps", f"{s['path'].name} has no occlusion level {level!r}")
        return float(s["levels"][level]["p95"]), s["path"].name

    @functools.cache  # noqa: B019
    def camera(self, kind: str = "clean"):
        """The camera that rendered map `kind`'s training images (a perfect map: the composed render config)."""
        folder = self.map_folder(kind)
        if folder is None:
            return build(self.cfg.render, "render", scene=self.scene)
        m = tracking.read_manifest(folder)
        return build(m["render"], "render", scene=build(m["scene"], "scene"))

    def map_scene(self, kind: str = "clean") -> Scene | None:
        """The scene map `kind`'s training images show (from its manifest; None with a perfect map)."""
        folder = self.map_folder(kind)
        return None if folder is None else build(tracking.read_manifest(folder)["scene"], "scene")

    # simulation ------------------------------------------------------------------------------
    def simulate(self, controller, x0, *, scene: Scene | None = None, disturbance=None, measure=None,
                 target_fn=None, p_fail: float | None = None, seed: int | None = None, record: bool = True,
                 record_every: int | None = None, horizon: float | None = None, model: str | None = None,
                 stop_on_success: bool | None = None):
        """One batched run; `model` (sampled | continuous) overrides `sim.model` (the camera is sampled-only),
        `stop_on_success` overrides `sim.stop_on_success`, `p_fail` (a scenario's failure condition) overrides
        `camera.p_fail`."""
        kw = run_keywords(self.sim, self.camera_settings)
        if p_fail is not None:
            kw["p_fail"] = p_fail
        if (model or self.sim.model) == "continuous" and kw["p_fail"] > 0:
            raise ConfigError("camera.p_fail", f"a continuous-time run takes no camera failures, got {kw['p_fail']} "
                                               "(camera.p_fail=0, or the scenario's sampled time model)")
        kw.update(seed=self.seed if seed is None else seed, record=record,
                  record_every=record_every or self.sim.record_every, horizon=horizon or self.horizon,
                  model=model or self.sim.model,
                  stop_on_success=self.sim.stop_on_success if stop_on_success is None else bool(stop_on_success))
        scene = scene or self.scene
        x0 = np.asarray(x0, float)
        res = simulate(scene, controller, x0, disturbance=disturbance, measure=measure, target_fn=target_fn,
                       progress=len(x0) >= 2000 and sys.stderr.isatty(), plant=self.vehicle,
                       heading0=self.vehicle.initial_heading(x0, scene), **kw)
        what = f"{getattr(controller, 'name', 'controller')}, {len(x0)} agents"
        self.advance(1, f"{self.label}: {what}" if self.label else what)
        return res

    def check_heading(self, kind: str = "clean") -> None:
        """A vehicle with a heading read from the camera (`camera.heading: camera`) needs a pose map: one line
        otherwise (read from the map's manifest: no map loaded)."""
        if not self.vehicle.heading or self.camera_settings.heading != "camera":
            return
        folder = self.map_folder(kind)
        if folder is None:  # a perfect map returns the true pose
            return
        outputs = (tracking.read_manifest(folder).get("model") or {}).get("outputs", "position")
        if outputs != "pose":
            raise ConfigError("camera.heading", f"'camera' needs a pose map, and {folder.name} (maps.{kind}) predicts no "
                                                "heading: train one (python -m pipeline.train data=unicycle model=pose) "
                                                "or read it from an onboard sensor (camera.heading=imu)")

    def map_gate(self, kind: str = "clean") -> float | None:
        """Map `kind`'s own flag threshold in world units: the clean-image gate its training fitted
        (`calibration.clean_gate_px`, docs/train.md) over its pixels per unit; None without an uncertainty head."""
        pm = self.perception_map(kind)
        px = (getattr(pm, "manifest", {}).get("metrics", {}).get("calibration") or {}).get("clean_gate_px")
        if px is None or not getattr(pm, "has_uncertainty", False):
            return None
        return float(px) / float(pm.px_per_unit)

    def camera_measure(self, kind: str = "clean", level: str | None = None, attack=None, *, gate="camera",
                       flag_gate: float | None = None, keep_clouds: bool = False):
        """The camera in the loop with map `kind` on `level` clouds; `gate`: "camera" (`camera.gate`), a number or
        None. With `attack` (`ctx.attack(...)`): the attacked camera (`pipeline.perception.adversary`), pushing
        the estimate along `-sign(b(p)) e_b` (SPEC §3.5) with the map and camera the loop uses; a worst cloud
        draws its candidates from its own level (`level` is then unused); `flag_gate` counts flagged frames."""
        pm = self.perception_map(kind)
        gate = self.gate if gate == "camera" else gate
        if attack is None:
            if isinstance(pm, OracleMap):
                return true_state
            self.check_heading(kind)
            cs = self.camera_settings
            return CameraMeasure(self.camera(kind), pm, self.occlusion(level), gate=gate, heading=cs.heading,
                                 heading_noise=cs.heading_noise)
        occ = self.occlusion(attack.level if attack.kind == "cloud" else level)
        cam = self.camera(kind) if not isinstance(pm, OracleMap) else None
        return attack.measure(cam, pm, proposition1_direction(self.scene), occlusion=occ, gate=gate,
                              flag_gate=flag_gate, keep_clouds=keep_clouds)

    def leader_follower(self, leader_x0, follower_x0, *, kind: str = "clean", level: str | None = None,
                        sigma: float = 0.0, p_fail: float | None = None, seed: int | None = None,
                        follower_controller: str = "hybrid"):
        """Leader: hybrid on its own noisy state towards p_T. Follower: its own noisy state, target = the
        leader's position seen by its camera through the map (failures, `p_fail` or else `camera.p_fail`, hold the
        last estimate; the leader reads its own state, not a camera: it has none).

        The leader never stops on success: it is the follower's target, and it keeps regulating to p_T after
        it first comes within delta. (Frozen on the delta-circle, it would leave the follower's own success,
        |p - p_T| <= delta, to the side of the circle the perception error pushes the follower to.)"""
        seed = self.seed if seed is None else seed
        noise = self.disturbance("gaussian", sigma=sigma) if sigma > 0 else None
        every = max(1, round((self.frame_period or self.dt) / self.dt))
        lead = self.simulate(self.controller("hybrid"), leader_x0, disturbance=noise, seed=seed, p_fail=0.0,
                             record_every=every, stop_on_success=False)
        track = LeaderTrack(lead.t, lead.p)
        pm = self.perception_map(kind)
        target = FollowerTarget(track, None if isinstance(pm, OracleMap) else self.camera(kind), pm,
                                self.occlusion(level), gate=self.gate)
        foll = self.simulate(self.controller(follower_controller), follower_x0, disturbance=noise,
                             target_fn=target, p_fail=p_fail, seed=seed + 1, record_every=every)
        return lead, foll, track


# -------------------------------------------------------------------------------------- statistics
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


def summarise(metrics: pd.DataFrame, by: list[str], seed: int = 0, delta_practical: float | None = None) -> pd.DataFrame:
    """Monte Carlo table (`pipeline.sim.metrics.summarise_agents`: success/collision with Wilson CIs, outcome
    classes, clearance median/p05/min, final-distance quantiles, practical success) plus a bootstrap CI of the
    median time to target and a CI of the mean jump count."""
    table = summarise_agents(metrics, by, delta_practical=delta_practical)
    rng = np.random.default_rng(seed)
    extra = []
    for _, g in metrics.groupby(by, sort=False):
        _, t_lo, t_hi = median_ci(g.loc[g["success"].astype(bool), "time_to_target"].to_numpy(), rng)
        _, j_lo, j_hi = mean_ci(g["jumps"].to_numpy())
        extra.append({"median_time_lo": t_lo, "median_time_hi": t_hi, "mean_jumps_lo": j_lo, "mean_jumps_hi": j_hi})
    return pd.concat([table, pd.DataFrame(extra)], axis=1)


