"""The run helpers of a scenario: agent counts at the run's scale, the stage's progress, one batched simulation with
the run's `sim` and `camera` settings, the camera in the loop, and the leader-follower pair."""

from __future__ import annotations

import sys
from dataclasses import replace

import numpy as np

from pipeline.control import Scene
from pipeline.errors import ConfigError
from pipeline.perception.adversary import proposition1_direction
from pipeline.perception.measure import CameraMeasure, FollowerTarget, LeaderTrack, OracleMap
from pipeline.plants import steering_warnings
from pipeline.sim import simulate, true_state


class Runs:
    """The run helpers of `Context` (its `sim`, `camera_settings`, `vehicle`, `scene`, `scale`, `bar` and `label`
    set by it; the maps and composed objects from `MapsById` and `Composed`)."""

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

    # simulation ------------------------------------------------------------------------------
    def simulate(self, controller, x0, *, scene: Scene | None = None, disturbance=None, measure=None,
                 target_fn=None, p_fail: float | None = None, seed: int | None = None, record: bool = True,
                 record_every: int | None = None, horizon: float | None = None, model: str | None = None,
                 stop_on_success: bool | None = None, innovation: bool = True):
        """One batched run with the run's `sim` and `camera` settings; `model` (sampled | continuous), `horizon`,
        `record_every` and `stop_on_success` replace the `sim` keys of those names, `p_fail` (a scenario's failure
        condition) `camera.p_fail`, for this run; `innovation=False`: this run uses every frame it is delivered
        (`camera.innovation` off: the paper's loop beside a defended one)."""
        over = {"model": model, "horizon": horizon, "record_every": record_every,
                "stop_on_success": None if stop_on_success is None else bool(stop_on_success)}
        over = {k: v for k, v in over.items() if v is not None and v != getattr(self.sim, k)}
        sim = replace(self.sim, **over) if over else self.sim
        cs = self.camera_settings
        camera = replace(cs, p_fail=p_fail) if p_fail is not None and p_fail != cs.p_fail else cs
        if not innovation and camera.innovation is not None:
            camera = replace(camera, innovation=None)
        if sim.model == "continuous" and camera.p_fail > 0:
            raise ConfigError("camera.p_fail", f"a continuous-time run takes no camera failures, got {camera.p_fail} "
                                               "(camera.p_fail=0, or the scenario's sampled time model)")
        scene = scene or self.scene
        x0 = np.asarray(x0, float)
        for line in steering_warnings(self.vehicle, controller):  # valid, but the unicycle cannot follow it
            if line not in self.warned:
                self.warned.add(line)
                print(f"warning: {line}", file=sys.stderr)
        res = simulate(scene, controller, x0, sim=sim, camera=camera, disturbance=disturbance, measure=measure,
                       target_fn=target_fn, seed=self.seed if seed is None else seed, record=record,
                       progress=len(x0) >= 2000 and sys.stderr.isatty(), plant=self.vehicle,
                       heading0=self.vehicle.initial_heading(x0, scene))
        what = f"{getattr(controller, 'name', 'controller')}, {len(x0)} agents"
        self.advance(1, f"{self.label}: {what}" if self.label else what)
        return res

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
