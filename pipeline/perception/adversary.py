"""Attacks on the image as disturbances of the closed loop (issue 20): SPEC §3.5's Proposition-1 attack moved
from the measured state into the camera.

The config nodes `conf/disturbance/pixel_attack.yaml` and `conf/disturbance/worst_cloud.yaml` are composed under
`disturbances.` beside the state disturbances; their `_target_`s, :class:`PixelAttack` and :class:`WorstCloud`,
are typed dataclasses whose fields are the schema (a bad key or value is one line, exit 2). A state disturbance
is *added* to the measurement (`m = l(h(p)) + e`); an attack *replaces* it: `attack.measure(camera, map,
direction_fn, ...)` is the closed loop's measurement hook (:class:`AttackedCamera`), built by the experiments'
`Context.camera_measure(kind, level, attack=...)` with the perception map and camera the loop really uses.

The objective, per agent and frame, with `d = -sign(b(p)) e_b` (the direction of SPEC §3.5's attack, from the
true position `p`, in the frame of the obstacle nearest to it; :func:`proposition1_direction`):

    pixel:  max_delta  d . l(x + delta)       s.t. |delta|_inf <= kappa (intensity levels), 0 <= x + delta <= 255
    cloud:  max_k      d . (l(x_k) - p)       over `candidates` cloud layouts x_k drawn from the level's ranges

(`l` the perception map on the rendered image `x`): the estimate is pushed across the line `b = 0` behind the
obstacle, where the smooth baselines stall. `AttackedCamera` reports the error it induces per frame.

This module imports no torch (the attacks' functions are imported when a frame is attacked).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import ClassVar, Literal

import numpy as np

from pipeline.perception.measure import OracleMap, check_gate
from pipeline.schema import Kappa, Name, Positive, PositiveInt, check_fields
from pipeline.sim.disturbances import Adversarial

ATTACKS = ("pixel", "cloud")


def proposition1_direction(scene) -> Callable[[np.ndarray], np.ndarray]:
    """`direction_fn(p) -> (N, 2)`: `-sign(b(p)) e_b` of SPEC §3.5 for a `pipeline.control.Scene` (duck-typed:
    `scene.to_frame(p) -> (a, b)` and `scene.e_b`), with `sign(0) = +1` as in `sim.disturbances.Adversarial`;
    a scene with several obstacles (`n_obstacles > 1`) uses the frame of the obstacle nearest to each `p`, as
    `Adversarial` does (SPEC §3.6)."""

    def direction(p: np.ndarray) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        if getattr(scene, "n_obstacles", 1) > 1:
            return Adversarial(eps=1.0)(p, 0, None, scene)
        _, b = scene.to_frame(p)
        sign = np.where(np.asarray(b) >= 0, 1.0, -1.0)
        return -sign[:, None] * np.asarray(scene.e_b, dtype=np.float64)[None, :]

    return direction


# ------------------------------------------------------------------------------------------ config nodes
@dataclass
class PixelAttack:
    """`conf/disturbance/pixel_attack.yaml`: an L-infinity bounded perturbation of every frame, `kappa` intensity
    levels (of 255) per channel and pixel, found by `steps` projected sign-gradient steps of `step_size` levels
    (null: `2.5 kappa / steps`) through the perception map's inference network; `random_start`: PGD from a
    uniform point of the ball (else from the clean image); `batch_size`: images per gradient batch."""

    kappa: Kappa = 4.0
    steps: PositiveInt = 2  # 0 would deliver the clean frame (or noise) while the tables report an attack
    step_size: Positive | None = None
    random_start: bool = False
    batch_size: PositiveInt = 512

    kind: ClassVar[str] = "pixel"
    name: ClassVar[str] = "pixel_attack"
    budget_key: ClassVar[str] = "kappa"

    def __post_init__(self):
        check_fields(self, "disturbance")  # the declared ranges, also when built from Python

    def label(self) -> str:
        return f"pixel κ={self.kappa:g}"

    def measure(self, camera, perception_map, direction_fn, *, occlusion=None, gate=None, flag_gate=None,
                keep_clouds: bool = False) -> AttackedCamera:
        return AttackedCamera(camera, perception_map, direction_fn, attack="pixel", occlusion=occlusion,
                              kappa=self.kappa, steps=self.steps, step_size=self.step_size,
                              random_start=self.random_start, batch_size=self.batch_size, gate=gate,
                              flag_gate=flag_gate)


@dataclass
class WorstCloud:
    """`conf/disturbance/worst_cloud.yaml`: each frame, the worst of `candidates` cloud layouts per agent, drawn
    from the cloud level `level` (a name of `occlusions`: the budget is the level's ranges); `always`: every
    candidate has clouds (else the level's own probability draws which do); `chunk`: images rendered and
    inferred per batch."""

    level: Name = "heavy"  # checked against `occlusions` where the attack is built (`Context.attack`)
    candidates: PositiveInt = 8
    always: bool = True
    chunk: PositiveInt = 4096

    kind: ClassVar[str] = "cloud"
    name: ClassVar[str] = "worst_cloud"
    budget_key: ClassVar[str] = "level"

    def __post_init__(self):
        check_fields(self, "disturbance")

    def label(self) -> str:
        return f"worst of {self.candidates} {self.level} clouds"

    def measure(self, camera, perception_map, direction_fn, *, occlusion=None, gate=None, flag_gate=None,
                keep_clouds: bool = False) -> AttackedCamera:
        """`occlusion`: the loaded level `self.level` (the adversary's budget)."""
        return AttackedCamera(camera, perception_map, direction_fn, attack="cloud", occlusion=occlusion,
                              candidates=self.candidates, always=self.always, chunk=self.chunk, gate=gate,
                              flag_gate=flag_gate, keep_clouds=keep_clouds)


def is_attack(obj) -> bool:
    return isinstance(obj, PixelAttack | WorstCloud)


# ------------------------------------------------------------------------------------- closed-loop hook
ROW_COLUMNS = ("frame", "agent", "x", "y", "along", "norm", "error_along", "predicted_error", "flagged", "gated")


@dataclass
class AttackedCamera:
    """`measure(p (n, 2), idx, frame, rng) -> estimates (n, 2)`: the camera in the loop, under attack.

    Each frame: `direction_fn(p)` gives the attack direction per agent from the true positions (normally
    `proposition1_direction(scene)`); then
    - `attack="pixel"`: render with `occlusion` (clouds drawn from `rng`, as `CameraMeasure` does) and run
      :func:`pipeline.perception.attacks.pixel_attack` through `net` (default `perception_map.net`, the
      predictor's eager folded network: the map and input scaling the loop uses) on `perception_map.device`;
    - `attack="cloud"`: :func:`pipeline.perception.attacks.worst_cloud` over `candidates` layouts of `occlusion`
      (the adversary's level), drawn from `rng`, inferred with the perception map.
    The estimate is the map's on the attacked image. A map with an uncertainty head also gives its predicted
    error there: frames above `flag_gate` (default: `gate`) are counted as flagged; with `gate` (`camera.gate`)
    they come back as NaN rows (held by the simulator, never on frame 0), as `CameraMeasure` does. A perfect map
    (`OracleMap`) reads no image: the measurement is the true state and the induced error 0.

    Statistics: `frames`, `images`, `flagged`, `gated`; per image, :meth:`table` (`ROW_COLUMNS`: the frame, the
    agent, its true position, the induced error `attacked - clean` along the direction and in norm, the
    attacked estimate's error along the direction, the predicted error, flagged, gated); `mean_along`,
    `mean_norm` over all images; with `keep_clouds`, the chosen cloud layouts per image (`clouds`: rows of
    mask, field, dy, dx, in the order of :meth:`table`).
    """

    camera: object
    perception_map: object
    direction_fn: Callable[[np.ndarray], np.ndarray]
    attack: Literal["pixel", "cloud"] = "pixel"
    occlusion: object | None = None
    kappa: Kappa = 4.0
    steps: PositiveInt = 2  # 0 would deliver the clean frame (or noise) while the tables report an attack
    step_size: Positive | None = None
    random_start: bool = False
    batch_size: PositiveInt = 512
    candidates: int = 8
    always: bool = True
    chunk: int = 4096
    gate: float | None = None
    flag_gate: float | None = None
    keep_clouds: bool = False
    net: object | None = None
    frames: int = 0
    images: int = 0
    flagged: int = 0
    gated: int = 0
    rows: list = field(default_factory=list)
    clouds: list = field(default_factory=list)

    def __post_init__(self):
        check_fields(self, "attack")  # built from Python (by the config nodes above): its fields as declared
        check_gate(self.perception_map, self.gate)
        if self.flag_gate is None:
            self.flag_gate = self.gate
        self.oracle = isinstance(self.perception_map, OracleMap)
        self.uncertain = bool(getattr(self.perception_map, "has_uncertainty", False))

    def _attack(self, p, direction, rng):
        from pipeline.perception.attacks import pixel_attack, worst_cloud  # torch: when a frame is attacked

        pm = self.perception_map
        if self.attack == "pixel":
            imgs = self.camera.render(p, None, occlusion=self.occlusion, rng=rng)
            net = self.net if self.net is not None else pm.net
            return pixel_attack(net, imgs, direction, kappa=self.kappa, steps=self.steps, step_size=self.step_size,
                                device=getattr(pm, "device", "cpu"), batch_size=self.batch_size,
                                rng=rng if self.random_start else None)
        predict = (lambda x: np.column_stack(pm.predict_with_sigma(x))) if self.uncertain else pm.predict
        return worst_cloud(self.camera, self.occlusion, p, direction, predict, candidates=self.candidates, rng=rng,
                           always=self.always, chunk=self.chunk, keep_images=False)

    def __call__(self, p: np.ndarray, idx: np.ndarray, frame: int, rng: np.random.Generator) -> np.ndarray:
        p = np.asarray(p, dtype=np.float64).reshape(-1, 2)
        n = len(p)
        direction = np.asarray(self.direction_fn(p), dtype=np.float64).reshape(n, 2)
        if self.oracle:
            est, along, norm, sigma = p.copy(), np.zeros(n), np.zeros(n), np.full(n, np.nan)
        else:
            res = self._attack(p, direction, rng)
            est, along, norm = res.attacked.copy(), res.along, res.norm
            extra = res.extra
            sigma = np.hypot(extra[:, 0], extra[:, 1]) if self.uncertain and extra is not None and \
                extra.shape[1] >= 2 else np.full(n, np.nan)
            if self.keep_clouds and res.clouds is not None:
                c = res.clouds
                self.clouds.append(np.column_stack([c.mask, c.field, c.dy, c.dx]).astype(np.int64))
        unit = direction / np.maximum(np.hypot(direction[:, 0], direction[:, 1]), 1e-300)[:, None]
        err_along = np.einsum("ij,ij->i", est - p, unit)
        flagged = (sigma > self.flag_gate) if self.flag_gate is not None else np.zeros(n, dtype=bool)
        gated = (sigma > self.gate) if (self.gate is not None and frame > 0) else np.zeros(n, dtype=bool)
        est[gated] = np.nan
        self.frames += 1
        self.images += n
        self.flagged += int(flagged.sum())
        self.gated += int(gated.sum())
        agent = np.arange(n) if idx is None else np.asarray(idx).reshape(n)
        self.rows.append(np.column_stack([np.full(n, frame), agent, p, along, norm, err_along, sigma, flagged,
                                          gated]))
        return est

    def table(self):
        """Per attacked image: `ROW_COLUMNS` (a pandas DataFrame)."""
        import pandas as pd

        data = np.concatenate(self.rows) if self.rows else np.empty((0, len(ROW_COLUMNS)))
        df = pd.DataFrame(data, columns=list(ROW_COLUMNS))
        for k in ("frame", "agent"):
            df[k] = df[k].astype(np.int64)
        for k in ("flagged", "gated"):
            df[k] = df[k].astype(bool)
        return df

    @property
    def mean_along(self) -> float:
        """Mean induced error along the direction over all attacked images (world units)."""
        return float(np.concatenate(self.rows)[:, 4].mean()) if self.rows else 0.0

    @property
    def mean_norm(self) -> float:
        """Mean norm of the induced error over all attacked images (world units)."""
        return float(np.concatenate(self.rows)[:, 5].mean()) if self.rows else 0.0
