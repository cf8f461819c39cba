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
from dataclasses import asdict, dataclass
from typing import Annotated

import cv2
import numpy as np
from omegaconf import OmegaConf

from pipeline.config import build, compose
from pipeline.errors import ConfigError
from pipeline.schema import Ascending, NonNegativeInt, Positive, Range, Share, checked


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


def _span(tp, lo: float, hi: float):
    """A `[min, max]` range with `lo <= min <= max <= hi`."""
    return Annotated[tuple[tp, tp], Range(ge=lo, le=hi), Ascending(strict=False)]


Blobs, Radius, Opacity, Aspect = _span(int, 0, 64), _span(float, 0.5, 1e6), _span(float, 0, 1), _span(float, 0.05, 1)


@checked("occlusion")
@dataclass(frozen=True)
class Occlusion:
    """A cloud level (`conf/occlusion/*.yaml`, its `_target_`). `Occlusion()` (or level `none`) draws nothing.

    `probability`: share of images with clouds; ranges `[min, max]` of the blobs per field, their radius (px),
    peak opacity and aspect; `softness`: the fraction of the radius over which an edge fades; `color` RGB; `bank`
    distinct fields (each shown at a random cyclic shift) drawn from `seed`; `cluster` (px): every field's blobs
    within that distance of one random centre (the authors' clouds), null: anywhere.
    """

    name: str = "none"
    probability: Share = 0.0
    blobs: Blobs = (0, 0)
    radius: Radius = (4.0, 8.0)
    opacity: Opacity = (0.5, 0.5)
    aspect: Aspect = (0.6, 1.0)
    softness: Annotated[float, Range(gt=0, le=1)] = 0.5  # fraction of the radius
    color: Annotated[tuple[int, int, int], Range(ge=0, le=255)] = (185, 205, 255)
    bank: Annotated[int, Range(ge=1, le=4096)] = 256
    seed: NonNegativeInt = 0
    cluster: Positive | None = None  # px; null: blobs anywhere

    def __post_init__(self):
        set_ = lambda k, v: object.__setattr__(self, k, v)  # noqa: E731 (frozen dataclass)
        set_("blobs", tuple(int(v) for v in self.blobs))
        for k in ("radius", "opacity", "aspect"):
            set_(k, tuple(float(v) for v in getattr(self, k)))
        set_("color", tuple(int(c) for c in self.color))
        set_("probability", float(self.probability))
        set_("softness", float(self.softness))
        set_("cluster", None if self.cluster is None else float(self.cluster))

    @property
    def active(self) -> bool:
        return self.probability > 0 and self.blobs[1] > 0 and self.opacity[1] > 0

    def config(self) -> dict:
        """Plain mapping (for manifests and ids); `Occlusion(**o.config()) == o`."""
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
def default_levels():
    """The `occlusions` config group as composed by Hydra (for APIs, benches and tests; stages pass the
    `occlusions` node of their own composed config instead)."""
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
        try:
            return build(levels[level], f"occlusions.{level}")
        except ConfigError as err:  # a key that follows another level (heavy_mix: ${..heavy.opacity}): name that one
            key = err.field.rsplit(".", 1)[-1]
            raw = (OmegaConf.to_container(levels[level], resolve=False) or {}).get(key)
            if isinstance(raw, str) and raw.startswith("${..") and raw.endswith("}"):
                raise ConfigError(f"occlusions.{raw[4:-1]}", f"{err.reason} (used by occlusions.{level})") from None
            raise
    return Occlusion(**{k: v for k, v in dict(level).items() if k != "_target_"})
