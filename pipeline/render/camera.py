"""The camera `theta = h(p)` of SPEC §1: batched top-down images of the arena.

Pixel convention (one function, :func:`world_to_pixel`): continuous image coordinates `(u, v)` with
`u = (x - x_min) * W / (x_max - x_min)` (column) and `v = (y_max - y) * H / (y_max - y_min)` (row);
pixel `(r, c)` covers `u in [c, c+1)`, `v in [r, r+1)`, so its centre is `(c + 0.5, r + 0.5)`.
Default: 1 world unit = 1 px, row 0 at `y = +30`, 60 x 100 px.

Images are `uint8 (N, H, W, 3)` in **RGB** order. The static part (background, obstacle disc, target
marker) is rendered once per camera with supersampled anti-aliasing; each batch copies it and draws the
robots as filled squares with exact-area coverage (the separable overlap of the square with each pixel),
so the intensity centroid of a robot is its true sub-pixel position. Clouds (:mod:`.occlusion`) go on top.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass

import cv2
import numpy as np

from pipeline.errors import ConfigError
from pipeline.render.occlusion import CloudSample, Occlusion

Arena = tuple[tuple[float, float], tuple[float, float]]
DEFAULT_ARENA: Arena = ((-50.0, 50.0), (-30.0, 30.0))
DEFAULT_COLORS = {
    "background": (22, 26, 34),
    "obstacle": (200, 64, 52),
    "target": (255, 186, 0),
    "leader": (255, 255, 255),
    "follower": (40, 220, 80),
}
_SUPERSAMPLE = 8  # sub-samples per pixel side for the static background
_CHUNK = 512  # images per internal block: keeps the full-image passes in cache


# ------------------------------------------------------------------------------------- coordinates
def _arena(arena) -> Arena:
    (x0, x1), (y0, y1) = arena
    return (float(x0), float(x1)), (float(y0), float(y1))


def world_to_pixel(points, arena: Arena = DEFAULT_ARENA, shape: tuple[int, int] = (60, 100)) -> np.ndarray:
    """World points `(N, 2)` -> continuous pixel coordinates `(N, 2)` as `(u, v)` = (column, row).

    `u = (x - x_min) * W / (x_max - x_min)`, `v = (y_max - y) * H / (y_max - y_min)`; pixel `(r, c)` covers
    `[c, c+1) x [r, r+1)` in `(u, v)`.
    """
    (x0, x1), (y0, y1) = _arena(arena)
    h, w = shape
    p = np.asarray(points, dtype=np.float64)
    out = np.empty(p.shape, dtype=np.float64)
    out[..., 0] = (p[..., 0] - x0) * (w / (x1 - x0))
    out[..., 1] = (y1 - p[..., 1]) * (h / (y1 - y0))
    return out


def pixel_to_world(uv, arena: Arena = DEFAULT_ARENA, shape: tuple[int, int] = (60, 100)) -> np.ndarray:
    """Inverse of :func:`world_to_pixel`."""
    (x0, x1), (y0, y1) = _arena(arena)
    h, w = shape
    q = np.asarray(uv, dtype=np.float64)
    out = np.empty(q.shape, dtype=np.float64)
    out[..., 0] = x0 + q[..., 0] * ((x1 - x0) / w)
    out[..., 1] = y1 - q[..., 1] * ((y1 - y0) / h)
    return out


# ------------------------------------------------------------------------------------------ result
@dataclass
class RenderResult:
    """Images and per-image cloud statistics.

    `occluded_frac`: mean cloud opacity over the image (0 = clear sky, 1 = fully covered);
    `leader_alpha`: cloud opacity over the pixel under the leader's centre (0 when clear or out of view).
    """

    images: np.ndarray
    occluded_frac: np.ndarray
    leader_alpha: np.ndarray


def _color(value, field: str) -> np.ndarray:
    try:
        arr = np.asarray(value, dtype=float).reshape(-1)
    except (TypeError, ValueError):
        arr = np.zeros(0)
    if arr.shape != (3,) or not np.all((arr >= 0) & (arr <= 255)):
        raise ConfigError(field, f"must be an RGB triple of numbers in [0, 255], got {value!r}")
    return arr


# ------------------------------------------------------------------------------------------ camera
class Camera:
    """Batched renderer of the arena of a :class:`pipeline.control.Scene`.

    `robot_size` is the side of the robot's square in pixels; `target_radius` the outer radius of the
    target ring in pixels (ring width 1 px). Colours are RGB triples (see ``DEFAULT_COLORS``).
    """

    def __init__(
        self,
        scene,
        arena: Arena = DEFAULT_ARENA,
        height: int = 60,
        width: int = 100,
        robot_size: float = 3.0,
        target_radius: float = 2.5,
        colors: Mapping | None = None,
        target_ring_width: float | None = 1.0,
    ):
        try:
            (x0, x1), (y0, y1) = _arena(arena)
        except (TypeError, ValueError):
            raise ConfigError("render.arena", f"needs [[x_min, x_max], [y_min, y_max]], got {arena!r}") from None
        if not (x0 < x1 and y0 < y1):
            raise ConfigError("render.arena", f"needs x_min < x_max and y_min < y_max, got {arena!r}")
        for field, v in (("render.height", height), ("render.width", width)):
            if not isinstance(v, int | np.integer) or isinstance(v, bool) or not 8 <= v <= 4096:
                raise ConfigError(field, f"must be an integer number of pixels in [8, 4096], got {v!r}")
        height, width = int(height), int(width)
        sx, sy = width / (x1 - x0), height / (y1 - y0)
        if not math.isclose(sx, sy, rel_tol=1e-9):
            want = (y1 - y0) * sx
            hint = f"height {want:g} for width {width}" if float(want).is_integer() else "a size with that aspect"
            raise ConfigError(
                "render.height",
                f"{height} x {width} px does not match the arena's aspect ({x1 - x0:g} x {y1 - y0:g} units; "
                f"pixels must be square): use {hint}, or change scene.arena",
            )
        if not (isinstance(robot_size, int | float) and 0 < robot_size <= min(height, width) / 4):
            raise ConfigError("render.robot_size", f"must be in (0, {min(height, width) / 4:g}] px, got {robot_size!r}")
        if not (isinstance(target_radius, int | float) and 0 <= target_radius <= min(height, width) / 4):
            raise ConfigError("render.target_radius", f"must be in [0, {min(height, width) / 4:g}] px, got {target_radius!r}")
        cols = dict(DEFAULT_COLORS)
        unknown = set(colors or {}) - set(cols)
        if unknown:
            raise ConfigError("render.colors", f"unknown key(s) {sorted(unknown)}; known: {sorted(cols)}")
        cols.update(dict(colors or {}))
        self.colors = {k: _color(v, f"render.colors.{k}") for k, v in cols.items()}
        self.scene = scene
        self.arena: Arena = ((x0, x1), (y0, y1))
        self.height, self.width = height, width
        self.scale = sx  # pixels per world unit
        self.robot_size = float(robot_size)
        self.target_radius = float(target_radius)
        if target_ring_width is not None and not (isinstance(target_ring_width, int | float) and target_ring_width > 0):
            raise ConfigError("render.target_ring_width", f"must be > 0 px (or null: a filled disc), got {target_ring_width!r}")
        self.target_ring_width = None if target_ring_width is None else float(target_ring_width)
        self.background = self._render_background()
        self._bg_flat = self.background.reshape(-1, 3)

    # ---------------------------------------------------------------------------------- factories
    @classmethod
    def from_config(cls, render_cfg, scene, arena=None) -> Camera:
        """From the `render` config group (conf/render/*.yaml) and a Scene.

        The arena comes from `render.arena` (default config: `${scene.arena}`), else `arena`, else
        `scene.arena` when `scene` is a scene config mapping, else the default arena.
        """
        from pipeline.tracking import to_plain

        cfg = to_plain(render_cfg) or {}
        scene_obj = scene
        if isinstance(scene, Mapping) or hasattr(scene, "keys"):
            from pipeline.control import Scene

            scene_plain = to_plain(scene)
            arena = arena or scene_plain.get("arena")
            scene_obj = Scene.from_config(scene_plain)
        a = cfg.get("arena") or arena or DEFAULT_ARENA
        if isinstance(a, Mapping):
            a = (a.get("x"), a.get("y"))
        known = {"height", "width", "robot_size", "target_radius", "target_ring_width", "colors", "arena", "name"}
        unknown = set(cfg) - known
        if unknown:
            raise ConfigError("render", f"unknown key(s) {sorted(unknown)}; known: {sorted(known)}")
        return cls(
            scene_obj, arena=a, height=cfg.get("height", 60), width=cfg.get("width", 100),
            robot_size=cfg.get("robot_size", 3.0), target_radius=cfg.get("target_radius", 2.5),
            colors=cfg.get("colors"), target_ring_width=cfg.get("target_ring_width", 1.0),
        )

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def world_to_pixel(self, points) -> np.ndarray:
        return world_to_pixel(points, self.arena, self.shape)

    def pixel_to_world(self, uv) -> np.ndarray:
        return pixel_to_world(uv, self.arena, self.shape)

    # --------------------------------------------------------------------------------- background
    def _render_background(self) -> np.ndarray:
        """Background + obstacle disc + target ring, anti-aliased by supersampling (once per camera)."""
        h, w, s = self.height, self.width, _SUPERSAMPLE
        offs = (np.arange(s) + 0.5) / s
        u = (np.arange(w)[:, None] + offs).reshape(-1)  # sub-sample centres, pixel units
        v = (np.arange(h)[:, None] + offs).reshape(-1)

        def coverage(inside) -> np.ndarray:  # (h*s, w*s) bool -> (h, w) area fraction
            return inside.reshape(h, s, w, s).mean(axis=(1, 3))

        img = np.broadcast_to(self.colors["background"], (h, w, 3)).astype(np.float64)
        layers = []
        if self.scene is not None:
            (cu, cv), = self.world_to_pixel([self.scene.obstacle_center])
            rad = float(self.scene.obstacle_radius) * self.scale
            d2 = (u[None, :] - cu) ** 2 + (v[:, None] - cv) ** 2
            layers.append((coverage(d2 <= rad * rad), self.colors["obstacle"]))
            if self.target_radius > 0:
                (tu, tv), = self.world_to_pixel([self.scene.target])
                d = np.sqrt((u[None, :] - tu) ** 2 + (v[:, None] - tv) ** 2)
                inner = 0.0 if self.target_ring_width is None else max(self.target_radius - self.target_ring_width, 0.0)
                ring = (d <= self.target_radius) & (d >= inner)
                layers.append((coverage(ring), self.colors["target"]))
        for cov, col in layers:
            img += cov[..., None] * (col - img)
        return np.ascontiguousarray(np.floor(img + 0.5), dtype=np.uint8)

    # ------------------------------------------------------------------------------------- robots
    def _draw_squares(self, flat: np.ndarray, centres: np.ndarray, color: np.ndarray) -> None:
        """Alpha-blend filled squares (exact-area coverage) into `flat` (images as (N*H*W, 3))."""
        ok = np.all(np.isfinite(centres), axis=1)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return
        h, w = self.height, self.width
        uv = self.world_to_pixel(centres[idx])
        half = self.robot_size / 2
        k = int(math.ceil(self.robot_size)) + 1  # pixels an interval of this length can touch
        lo = uv - half
        hi = uv + half
        start = np.floor(lo).astype(np.int64)
        steps = np.arange(k)
        rows = start[:, 1, None] + steps  # (n, k)
        cols = start[:, 0, None] + steps
        # exact overlap of [lo, hi] with each pixel interval [i, i+1): separable, so area = product
        cov_r = np.clip(np.minimum(rows + 1, hi[:, 1, None]) - np.maximum(rows, lo[:, 1, None]), 0.0, 1.0)
        cov_c = np.clip(np.minimum(cols + 1, hi[:, 0, None]) - np.maximum(cols, lo[:, 0, None]), 0.0, 1.0)
        cov_r[(rows < 0) | (rows >= h)] = 0.0
        cov_c[(cols < 0) | (cols >= w)] = 0.0
        alpha = cov_r[:, :, None] * cov_c[:, None, :]  # (n, k, k)
        sel = alpha > 0
        pix = (idx[:, None, None] * h + rows[:, :, None]) * w + cols[:, None, :]
        pix = pix[sel]
        a = alpha[sel][:, None]
        old = flat[pix].astype(np.float64)
        flat[pix] = np.floor(old + a * (color - old) + 0.5).astype(np.uint8)

    # ------------------------------------------------------------------------------------- render
    def render(
        self,
        leader,
        follower=None,
        occlusion: Occlusion | None = None,
        rng: np.random.Generator | None = None,
        *,
        clouds: CloudSample | None = None,
        out: np.ndarray | None = None,
        return_info: bool = False,
    ):
        """Images of the leader at `leader (N, 2)` (world units) and optionally the follower.

        - `follower`: `(N, 2)` or None; rows with NaN mean "no follower in this image".
          Rows of `leader` with NaN draw no leader.
        - `occlusion`: clouds drawn over everything (None or level `none`: no clouds). The per-image
          cloud choices come from `clouds` when given (see :meth:`Occlusion.sample`), else are drawn from
          `rng` (None: `np.random.default_rng(0)`, so calls without an rng are reproducible).
        - `out`: optional preallocated `uint8 (N, H, W, 3)` array (e.g. a memory-mapped shard).
        - Returns the images, or a :class:`RenderResult` with `return_info=True`.

        Same inputs and rng state -> identical bytes.
        """
        leader = np.asarray(leader, dtype=np.float64).reshape(-1, 2)
        n = len(leader)
        if follower is not None:
            follower = np.asarray(follower, dtype=np.float64).reshape(-1, 2)
            if len(follower) != n:
                raise ValueError(f"follower has {len(follower)} rows, leader {n}")
        h, w = self.height, self.width
        if out is None:
            out = np.empty((n, h, w, 3), dtype=np.uint8)
        elif out.shape != (n, h, w, 3) or out.dtype != np.uint8:
            raise ValueError(f"out must be uint8 {(n, h, w, 3)}, got {out.dtype} {out.shape}")
        active = occlusion is not None and occlusion.active
        if active and clouds is None:
            clouds = occlusion.sample(n, rng if rng is not None else np.random.default_rng(0), self.shape)
        if active and len(clouds) != n:
            raise ValueError(f"clouds has {len(clouds)} rows, leader {n}")
        frac = np.zeros(n, dtype=np.float32)
        lead_alpha = np.zeros(n, dtype=np.float32)
        for s in range(0, n, _CHUNK):
            e = min(s + _CHUNK, n)
            block = out[s:e]
            np.copyto(block, self.background)
            flat = block.reshape(-1, 3)
            if follower is not None:
                self._draw_squares(flat, follower[s:e], self.colors["follower"])
            self._draw_squares(flat, leader[s:e], self.colors["leader"])
            if active:
                f, la = occlusion.apply(block, clouds[s:e], self.world_to_pixel(leader[s:e]))
                frac[s:e], lead_alpha[s:e] = f, la
        if return_info:
            return RenderResult(out, frac, lead_alpha)
        return out

    def preview_grid(self, images: np.ndarray, cols: int = 8, pad: int = 2) -> np.ndarray:
        """Tile images `(N, H, W, 3)` into one RGB image with white gutters (for preview.png)."""
        n = len(images)
        rows = max(1, math.ceil(n / cols))
        h, w = self.height, self.width
        tiles = np.full((rows * cols, h + pad, w + pad, 3), 255, dtype=np.uint8)
        tiles[:n, pad:, pad:] = images
        grid = tiles.reshape(rows, cols, h + pad, w + pad, 3).transpose(0, 2, 1, 3, 4)
        grid = grid.reshape(rows * (h + pad), cols * (w + pad), 3)
        return np.pad(grid, ((0, pad), (0, pad), (0, 0)), constant_values=255)


def save_png(path, rgb: np.ndarray, upscale: int = 2) -> None:
    """Write an RGB image as PNG (nearest-neighbour upscaled so the pixels stay visible)."""
    img = cv2.resize(rgb, None, fx=upscale, fy=upscale, interpolation=cv2.INTER_NEAREST) if upscale > 1 else rgb
    if not cv2.imwrite(str(path), cv2.cvtColor(img, cv2.COLOR_RGB2BGR)):
        raise OSError(f"could not write {path}")
