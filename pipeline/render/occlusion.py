"""Occlusion ("clouds", SPEC §1): seeded, semi-opaque blobs drawn over the camera image.

A level (conf/occlusion/*.yaml) sets the probability that an image is occluded and the ranges of blob
count, radius (px), opacity, aspect ratio and edge softness. Rendering many images fast:

- once per (level, image size), a seeded **bank** of `bank` cloud fields is built. Each field is a
  periodic (torus) opacity map of one image period holding `blobs` soft elliptic blobs with radii,
  opacities, aspects and orientations drawn from the level's ranges; opacities of overlapping blobs
  combine as `1 - prod(1 - a_i)`;
- each occluded image shows one field at a random cyclic shift (`bank * H * W` distinct layouts:
  ~1.5 M for 256 fields at 60 x 100), so the per-image work is one gather and one blend, batched.

`occluded_frac` of an image is the mean cloud opacity over the image (0 = clear, 1 = fully covered),
which is shift-invariant and therefore the mean of its field.
"""

from __future__ import annotations

import functools
import math
import threading
from collections.abc import Mapping
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from pipeline.errors import ConfigError


@dataclass(frozen=True)
class CloudSample:
    """Per-image cloud choices: occluded or not, which bank field, and its cyclic shift (rows, cols)."""

    mask: np.ndarray
    field: np.ndarray
    dy: np.ndarray
    dx: np.ndarray

    def __len__(self) -> int:
        return len(self.mask)

    def __getitem__(self, key) -> CloudSample:
        return CloudSample(self.mask[key], self.field[key], self.dy[key], self.dx[key])


def _range(cfg: Mapping, key: str, lo: float, hi: float, default, integer: bool = False) -> tuple:
    value = cfg.get(key, default)
    try:
        a, b = (int(x) if integer else float(x) for x in value)
        if integer and any(float(x) != int(x) for x in value):
            raise ValueError
    except (TypeError, ValueError):
        kind = "integers" if integer else "numbers"
        raise ConfigError(f"occlusion.{key}", f"must be a pair of {kind} [min, max], got {value!r}") from None
    if not (lo <= a <= b <= hi):
        raise ConfigError(f"occlusion.{key}", f"needs {lo:g} <= min <= max <= {hi:g}, got {value!r}")
    return a, b


@dataclass(frozen=True)
class Occlusion:
    """A cloud level. `Occlusion()` (or level `none`) draws nothing."""

    name: str = "none"
    probability: float = 0.0
    blobs: tuple[int, int] = (0, 0)
    radius: tuple[float, float] = (4.0, 8.0)
    opacity: tuple[float, float] = (0.5, 0.5)
    aspect: tuple[float, float] = (0.6, 1.0)
    softness: float = 0.5
    color: tuple[int, int, int] = (185, 205, 255)
    bank: int = 256
    seed: int = 0
    cluster: float | None = None

    KEYS = ("name", "probability", "blobs", "radius", "opacity", "aspect", "softness", "color", "bank", "seed",
            "cluster")

    @property
    def active(self) -> bool:
        return self.probability > 0 and self.blobs[1] > 0 and self.opacity[1] > 0

    @classmethod
    def from_config(cls, cfg) -> Occlusion:
        """From a level mapping (conf/occlusion/*.yaml); every value is validated."""
        from pipeline.tracking import to_plain

        cfg = dict(to_plain(cfg) or {})
        unknown = set(cfg) - set(cls.KEYS)
        if unknown:
            raise ConfigError("occlusion", f"unknown key(s) {sorted(unknown)}; known: {list(cls.KEYS)}")
        d = cls()
        p = cfg.get("probability", d.probability)
        if not isinstance(p, int | float) or not 0 <= p <= 1:
            raise ConfigError("occlusion.probability", f"must be in [0, 1], got {p!r}")
        soft = cfg.get("softness", d.softness)
        if not isinstance(soft, int | float) or not 0 < soft <= 1:
            raise ConfigError("occlusion.softness", f"must be in (0, 1] (fraction of the radius), got {soft!r}")
        bank = cfg.get("bank", d.bank)
        if not isinstance(bank, int) or isinstance(bank, bool) or not 1 <= bank <= 4096:
            raise ConfigError("occlusion.bank", f"must be an integer in [1, 4096], got {bank!r}")
        seed = cfg.get("seed", d.seed)
        if not isinstance(seed, int) or isinstance(seed, bool) or seed < 0:
            raise ConfigError("occlusion.seed", f"must be an integer >= 0, got {seed!r}")
        cluster = cfg.get("cluster", d.cluster)
        if cluster is not None and (isinstance(cluster, bool) or not isinstance(cluster, int | float) or not cluster > 0):
            raise ConfigError("occlusion.cluster", f"must be > 0 px (or null: blobs anywhere), got {cluster!r}")
        color = cfg.get("color", d.color)
        try:
            col = tuple(int(c) for c in color)
        except (TypeError, ValueError):
            col = ()
        if len(col) != 3 or not all(0 <= c <= 255 for c in col):
            raise ConfigError("occlusion.color", f"must be an RGB triple of integers in [0, 255], got {color!r}")
        return cls(
            name=str(cfg.get("name", "custom")),
            probability=float(p),
            blobs=_range(cfg, "blobs", 0, 64, d.blobs, integer=True),
            radius=_range(cfg, "radius", 0.5, 1e6, d.radius),
            opacity=_range(cfg, "opacity", 0.0, 1.0, d.opacity),
            aspect=_range(cfg, "aspect", 0.05, 1.0, d.aspect),
            softness=float(soft),
            color=col,
            bank=bank,
            seed=seed,
            cluster=None if cluster is None else float(cluster),
        )

    def config(self) -> dict:
        """Plain mapping (for manifests and ids); `Occlusion.from_config(o.config()) == o`."""
        out = asdict(self)
        if out["cluster"] is None:  # levels without clustering keep the mapping (and ids) they had
            del out["cluster"]
        return {k: list(v) if isinstance(v, tuple) else v for k, v in out.items()}

    # ------------------------------------------------------------------------------------ sampling
    def sample(self, n: int, rng: np.random.Generator, shape: tuple[int, int]) -> CloudSample:
        """Per-image choices for `n` images of size `shape = (H, W)` (draw order fixed: mask, field, dy, dx)."""
        h, w = shape
        mask = rng.random(n) < self.probability
        field = rng.integers(0, self.bank, n)
        dy = rng.integers(0, h, n)
        dx = rng.integers(0, w, n)
        return CloudSample(mask, field, dy, dx)

    def fields(self, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
        """The bank: opacity fields `uint8 (bank, 2H, 2W)` (one period tiled 2x2) and their means in [0, 1]."""
        return _bank(self, tuple(int(s) for s in shape))

    def mean_fraction(self, shape: tuple[int, int] = (60, 100)) -> float:
        """Expected `occluded_frac` of an image (probability x mean field opacity)."""
        if not self.active:
            return 0.0
        return float(self.probability * self.fields(shape)[1].mean())

    # ------------------------------------------------------------------------------------- drawing
    def apply(self, images: np.ndarray, clouds: CloudSample, leader_uv: np.ndarray | None = None):
        """Blend clouds over `images (n, H, W, 3)` in place; returns (occluded_frac, leader_alpha), float32 (n,).

        `leader_alpha` is the field's opacity at the pixel under `leader_uv` (0 when out of view).
        """
        n, h, w, _ = images.shape
        frac = np.zeros(n, dtype=np.float32)
        lead = np.zeros(n, dtype=np.float32)
        idx = np.flatnonzero(clouds.mask)
        if idx.size == 0 or not self.active:
            return frac, lead
        bank, means = self.fields((h, w))
        k, dy, dx = clouds.field[idx], clouds.dy[idx], clouds.dx[idx]
        windows = np.lib.stride_tricks.sliding_window_view(bank, (h, w), axis=(1, 2))
        m = idx.size
        whole = m == n
        sub = images if whole else images[idx]
        tall = sub.reshape(m * h, w, 3)
        a3 = _workspace(m * h, w)
        # gathers of the shifted fields, then a premultiplied blend in uint8 (OpenCV SIMD):
        # out = img * (1 - a) + colour * a, each term rounded (colour * a precomputed per field)
        cv2.cvtColor(windows[k, dy, dx].reshape(m * h, w), cv2.COLOR_GRAY2RGB, dst=a3)
        cv2.bitwise_not(a3, dst=a3)
        cv2.multiply(tall, a3, dst=tall, scale=1 / 255)
        cv2.add(tall, _tint_windows(self, (h, w))[k, dy, dx].reshape(m * h, w, 3), dst=tall)
        if not whole:
            images[idx] = sub
        frac[idx] = means[k]
        if leader_uv is not None:
            uv = np.asarray(leader_uv)[idx]
            ok = np.all(np.isfinite(uv), axis=1)
            c = np.where(ok, np.floor(np.nan_to_num(uv[:, 0], nan=-1)), -1).astype(np.int64)
            r = np.where(ok, np.floor(np.nan_to_num(uv[:, 1], nan=-1)), -1).astype(np.int64)
            inside = (r >= 0) & (r < h) & (c >= 0) & (c < w)
            vals = bank[k, dy + np.clip(r, 0, h - 1), dx + np.clip(c, 0, w - 1)] / np.float32(255)
            lead[idx] = np.where(inside, vals, 0.0)
        return frac, lead


_WORK = threading.local()


def _workspace(rows: int, w: int) -> np.ndarray:
    """A reused per-thread buffer for `apply` (fresh multi-MB arrays per chunk would cost page faults)."""
    buf = getattr(_WORK, "buf", None)
    if buf is None or buf.shape[1] != w or len(buf) < rows:
        buf = _WORK.buf = np.empty((rows, w, 3), dtype=np.uint8)
    return buf[:rows]


@functools.lru_cache(maxsize=16)
def _tint_windows(occ: Occlusion, shape: tuple[int, int]) -> np.ndarray:
    """`colour * a` of every bank field, as a read-only view `(bank, H+1, W+1, H, W*3)` of shifted windows."""
    h, w = shape
    bank, _ = _bank(occ, shape)
    col = np.asarray(occ.color, dtype=np.float32) / 255.0
    tint = np.floor(bank[..., None].astype(np.float32) * col + 0.5).astype(np.uint8)
    s = tint.strides
    return np.lib.stride_tricks.as_strided(tint, (len(bank), h + 1, w + 1, h, w * 3), (s[0], s[1], s[2], s[1], 1),
                                           writeable=False)


@functools.lru_cache(maxsize=16)
def _bank(occ: Occlusion, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    h, w = shape
    r_max = occ.radius[1]
    if r_max > min(h, w) / 2:
        raise ConfigError("occlusion.radius", f"max {r_max:g} px exceeds half the image ({min(h, w) / 2:g} px)")
    rng = np.random.default_rng(occ.seed)
    b = occ.bank
    lo, hi = occ.blobs
    counts = rng.integers(lo, hi + 1, b)
    yy = np.arange(h, dtype=np.float32)[:, None] + 0.5
    xx = np.arange(w, dtype=np.float32)[None, :] + 0.5
    transmit = np.ones((b, h, w), dtype=np.float32)
    if occ.cluster is not None:  # every field's blobs within +-cluster px of one random centre (the authors')
        centre_y, centre_x = rng.uniform(0, h, b), rng.uniform(0, w, b)
    for slot in range(hi):  # a handful of blob slots, each vectorised over the whole bank
        cy, cx = rng.uniform(0, h, b), rng.uniform(0, w, b)
        if occ.cluster is not None:
            cy = (centre_y + (cy / h * 2 - 1) * occ.cluster) % h
            cx = (centre_x + (cx / w * 2 - 1) * occ.cluster) % w
        rad = rng.uniform(*occ.radius, b)
        opa = rng.uniform(*occ.opacity, b)
        asp = rng.uniform(*occ.aspect, b)
        ang = rng.uniform(0, math.pi, b)
        live = counts > slot
        if not live.any():
            continue
        sel = np.flatnonzero(live)
        cy, cx, rad, opa, asp, ang = (x[sel].astype(np.float32)[:, None, None] for x in (cy, cx, rad, opa, asp, ang))
        dv = (yy - cy + h / 2) % h - h / 2  # torus offsets: fields are periodic
        du = (xx - cx + w / 2) % w - w / 2
        ca, sa = np.cos(ang), np.sin(ang)
        along = (du * ca + dv * sa) / rad
        across = (-du * sa + dv * ca) / (rad * asp)
        d = np.sqrt(along * along + across * across)
        t = np.clip((1.0 - d) / np.float32(occ.softness), 0.0, 1.0)
        alpha = opa * t * t * (3.0 - 2.0 * t)  # smoothstep edge
        transmit[sel] *= 1.0 - alpha
    fields = np.floor((1.0 - transmit) * 255.0 + 0.5).astype(np.uint8)
    means = fields.mean(axis=(1, 2)) / 255.0
    tiled = np.ascontiguousarray(np.tile(fields, (1, 2, 2)))
    tiled.setflags(write=False)
    means.setflags(write=False)
    return tiled, means


# ------------------------------------------------------------------------------------------ levels
def occlusion_level(*, name: str, probability: float = 0.0, blobs=(0, 0), radius=(4.0, 8.0), opacity=(0.5, 0.5),
                    aspect=(0.6, 1.0), softness: float = 0.5, color=(185, 205, 255), bank: int = 256,
                    seed: int = 0, cluster: float | None = None) -> Occlusion:
    """`_target_` of conf/occlusion/*.yaml: a validated :class:`Occlusion` level."""
    return Occlusion.from_config({"name": name, "probability": probability, "blobs": blobs, "radius": radius,
                                  "opacity": opacity, "aspect": aspect, "softness": softness, "color": color,
                                  "bank": bank, "seed": seed, "cluster": cluster})


def default_levels():
    """The `occlusions` config group as composed by Hydra (for APIs, benches and tests; stages pass the
    `occlusions` node of their own composed config instead)."""
    from pipeline.config import compose

    return compose("occlusions/all").occlusions


def occlusion_levels(levels=None) -> list[str]:
    """Names of the levels of an `occlusions` config node (default: the composed `occlusions` group)."""
    return list((levels if levels is not None else default_levels()).keys())


def load_occlusion(level, levels=None, field: str = "occlusion") -> Occlusion:
    """An :class:`Occlusion` from a level name of the `occlusions` node `levels`, a mapping, or an Occlusion.

    `levels` is the run's composed `occlusions` node (default: the config group as Hydra composes it). An
    unknown name raises `ConfigError(field, ...)` listing the known levels.
    """
    if isinstance(level, Occlusion):
        return level
    if level is None:
        return Occlusion()
    if isinstance(level, str):
        levels = levels if levels is not None else default_levels()
        if level not in levels:
            raise ConfigError(field, f"unknown occlusion level {level!r}; known: {', '.join(levels.keys())}")
        from pipeline.config import build

        try:
            return build(levels[level], f"occlusions.{level}")
        except ConfigError as err:  # a key that follows another level (heavy_mix: ${..heavy.opacity}): name that one
            key = err.field.rsplit(".", 1)[-1]
            from omegaconf import OmegaConf

            raw = (OmegaConf.to_container(levels[level], resolve=False) or {}).get(key)
            if isinstance(raw, str) and raw.startswith("${..") and raw.endswith("}"):
                raise ConfigError(f"occlusions.{raw[4:-1]}", f"{err.reason} (used by occlusions.{level})") from None
            raise
    from pipeline.tracking import to_plain

    return Occlusion.from_config({k: v for k, v in (to_plain(level) or {}).items() if k != "_target_"})
