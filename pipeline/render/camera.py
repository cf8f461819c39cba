"""The camera `theta = h(p)` of SPEC §1: batched top-down images of the arena.

Pixel convention (one function, :func:`world_to_pixel`): continuous image coordinates `(u, v)` with
`u = (x - x_min) * W / (x_max - x_min)` (column) and `v = (y_max - y) * H / (y_max - y_min)` (row);
pixel `(r, c)` covers `u in [c, c+1)`, `v in [r, r+1)`, so its centre is `(c + 0.5, r + 0.5)`.
Default: 1 world unit = 1 px, row 0 at `y = +30`, 60 x 100 px.

Images are `uint8 (N, H, W, 3)` in **RGB** order. The static part (background, obstacle disc, target
marker) is rendered once per camera with supersampled anti-aliasing; each batch copies it and draws the
robots as filled squares with exact-area coverage (the separable overlap of the square with each pixel),
so the intensity centroid of a robot is its true sub-pixel position. Clouds (:mod:`.occlusion`) go on top.

Several obstacles (SPEC §1, §3.6): a scene with an `obstacles` list (items with `.center` and `.radius`)
has every disc drawn (their union, one layer); otherwise the single `obstacle_center` / `obstacle_radius`.

Unicycle (SPEC §1, §3.7): with `heading` the leader is an oriented isosceles triangle instead of the square
(:func:`heading_marker`): with `L = robot_size` px, apex `4/3 L` ahead of the position along the heading,
base `2/3 L` behind it, base width `L` (length `2 L`, area `L^2` = the square's area). Its area centroid is
the position, so the intensity centroid stays the position; its coverage is the exact triangle-pixel
overlap area, so the image's second and third moments carry the heading.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass

import cv2
import numpy as np

from pipeline.errors import ConfigError
from pipeline.render.marker import MARKER_REACH, heading_marker, polygon_coverage
from pipeline.render.occlusion import CloudSample, Occlusion
from pipeline.schema import RGB, NonNegative, Positive, checked

Arena = tuple[tuple[float, float], tuple[float, float]]
DEFAULT_ARENA: Arena = ((-50.0, 50.0), (-30.0, 30.0))


@checked("render.colors")
@dataclass(frozen=True)
class Colors:
    """The colours of the image, RGB (`render.colors`: any of them)."""

    background: RGB = (22, 26, 34)
    obstacle: RGB = (200, 64, 52)
    target: RGB = (255, 186, 0)
    leader: RGB = (255, 255, 255)
    follower: RGB = (40, 220, 80)


DEFAULT_COLORS = asdict(Colors())
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


def _field(obj, name: str):
    """`obj.name`, or `obj[name]` for a mapping (obstacle items may be either)."""
    if isinstance(obj, Mapping):
        return obj[name]
    return getattr(obj, name)


# ------------------------------------------------------------------------------------------ marker
# The unicycle's marker, in units of L = robot_size px, in the vehicle frame (x ahead, y to the left):
# apex (4/3, 0), base corners (-2/3, +-1/2). Area L^2 (the square's); area centroid at the origin.
# ------------------------------------------------------------------------------------------ camera
@checked("render")
class Camera:
    """Batched renderer of the arena of a :class:`pipeline.control.Scene`.

    `robot_size` is the side of the robot's square in pixels; `target_radius` the outer radius of the
    target ring in pixels (ring width 1 px). Colours are RGB triples (see ``DEFAULT_COLORS``).
    """

    def __init__(self, scene=None, px_per_unit: Positive = 1.0, robot_size: Positive = 3.0,
                 target_radius: NonNegative = 2.5, colors: Colors | None = None,
                 target_ring_width: Positive | None = 1.0):
        arena = scene.bounds if hasattr(scene, "bounds") else DEFAULT_ARENA
        (x0, x1), (y0, y1) = _arena(arena)
        h, w = (y1 - y0) * px_per_unit, (x1 - x0) * px_per_unit
        if not (float(h).is_integer() and float(w).is_integer() and 8 <= h <= 4096 and 8 <= w <= 4096):
            raise ConfigError("render.px_per_unit", f"{px_per_unit:g} px per unit makes a {h:g} x {w:g} px image of "
                                                    f"the {y1 - y0:g} x {x1 - x0:g} arena: it needs whole numbers "
                                                    "of pixels in [8, 4096] (square pixels)")
        height, width = int(h), int(w)
        for key, size in (("robot_size", robot_size), ("target_radius", target_radius)):  # a marker fits the image
            if size > min(height, width) / 4:
                raise ConfigError(f"render.{key}", f"must be <= {min(height, width) / 4:g} px (a quarter of the "
                                                   f"{height} x {width} image), got {size!r}")
        given = asdict(colors) if isinstance(colors, Colors) else dict(colors or {})
        self.colors = {k: np.asarray(v, dtype=float) for k, v in {**DEFAULT_COLORS, **given}.items()}
        self.scene = scene
        self.arena: Arena = ((x0, x1), (y0, y1))
        self.height, self.width = height, width
        self.scale = width / (x1 - x0)  # pixels per world unit
        self.robot_size = float(robot_size)
        self.target_radius = float(target_radius)
        self.target_ring_width = None if target_ring_width is None else float(target_ring_width)
        self.background = self._render_background()
        self._bg_flat = self.background.reshape(-1, 3)

    @property
    def shape(self) -> tuple[int, int]:
        return self.height, self.width

    def world_to_pixel(self, points) -> np.ndarray:
        return world_to_pixel(points, self.arena, self.shape)

    def pixel_to_world(self, uv) -> np.ndarray:
        return pixel_to_world(uv, self.arena, self.shape)

    # --------------------------------------------------------------------------------- background
    def _obstacle_discs(self) -> list[tuple[float, float, float]]:
        """`(u, v, radius)` in pixels of every obstacle disc of the scene."""
        obstacles = getattr(self.scene, "obstacles", None)
        if obstacles is None:
            items = [(self.scene.obstacle_center, self.scene.obstacle_radius)]
        else:
            items = [(_field(o, "center"), _field(o, "radius")) for o in obstacles]
        discs = []
        for center, radius in items:
            (cu, cv), = self.world_to_pixel([center])
            discs.append((float(cu), float(cv), float(radius) * self.scale))
        return discs

    def _render_background(self) -> np.ndarray:
        """Background + obstacle discs + target ring, anti-aliased by supersampling (once per camera).

        The discs are one layer: a sub-sample is obstacle when it lies in any disc (overlapping discs do not
        darken). Only the pixels of each disc's bounding box are tested, so many discs in a large arena stay
        cheap; the result is the same bytes as testing every sub-sample of the image.
        """
        h, w, s = self.height, self.width, _SUPERSAMPLE
        offs = (np.arange(s) + 0.5) / s
        u = (np.arange(w)[:, None] + offs).reshape(-1)  # sub-sample centres, pixel units
        v = (np.arange(h)[:, None] + offs).reshape(-1)

        def coverage(inside) -> np.ndarray:  # (h*s, w*s) bool -> (h, w) area fraction
            return inside.reshape(h, s, w, s).mean(axis=(1, 3))

        img = np.broadcast_to(self.colors["background"], (h, w, 3)).astype(np.float64)
        layers = []
        if self.scene is not None:
            inside = np.zeros((h * s, w * s), dtype=bool)
            for cu, cv, rad in self._obstacle_discs():
                # pixels whose sub-samples can lie in the disc (one spare pixel each side)
                c0, c1 = max(int(math.floor(cu - rad)) - 1, 0), min(int(math.floor(cu + rad)) + 2, w)
                r0, r1 = max(int(math.floor(cv - rad)) - 1, 0), min(int(math.floor(cv + rad)) + 2, h)
                if c0 >= c1 or r0 >= r1:
                    continue
                uu, vv = u[c0 * s : c1 * s], v[r0 * s : r1 * s]
                d2 = (uu[None, :] - cu) ** 2 + (vv[:, None] - cv) ** 2
                inside[r0 * s : r1 * s, c0 * s : c1 * s] |= d2 <= rad * rad
            layers.append((coverage(inside), self.colors["obstacle"]))
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

    def _draw_triangles(self, flat: np.ndarray, centres: np.ndarray, heading: np.ndarray, color: np.ndarray) -> None:
        """Alpha-blend the oriented unicycle markers (exact-area coverage) into `flat` (images as (N*H*W, 3))."""
        ok = np.all(np.isfinite(centres), axis=1)
        idx = np.flatnonzero(ok)
        if idx.size == 0:
            return
        h, w = self.height, self.width
        uv = self.world_to_pixel(centres[idx])
        verts = heading_marker(uv, heading[idx], self.robot_size)
        reach = MARKER_REACH * self.robot_size
        k = int(math.ceil(2 * reach)) + 1  # pixels an interval of this length can touch
        start = np.floor(verts.min(axis=1)).astype(np.int64)  # (n, 2): the bounding box's first pixel
        steps = np.arange(k)
        rows = start[:, 1, None] + steps  # (n, k)
        cols = start[:, 0, None] + steps
        alpha = polygon_coverage(verts, rows, cols)  # (n, k, k)
        alpha[((rows < 0) | (rows >= h))[:, :, None] | ((cols < 0) | (cols >= w))[:, None, :]] = 0.0
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
        heading=None,
        clouds: CloudSample | None = None,
        out: np.ndarray | None = None,
        return_info: bool = False,
    ):
        """Images of the leader at `leader (N, 2)` (world units) and optionally the follower.

        - `follower`: `(N, 2)` or None; rows with NaN mean "no follower in this image".
          Rows of `leader` with NaN draw no leader.
        - `heading`: `(N,)` world-frame headings in radians (a unicycle): the leader is drawn as the oriented
          triangle of :func:`heading_marker` instead of the square (same colour, dimensions from
          `robot_size`). A finite leader row needs a finite heading. The follower stays a square.
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
        if heading is not None:
            heading = np.asarray(heading, dtype=np.float64).reshape(-1)
            if len(heading) != n:
                raise ValueError(f"heading has {len(heading)} rows, leader {n}")
            bad = np.all(np.isfinite(leader), axis=1) & ~np.isfinite(heading)
            if bad.any():
                raise ValueError(f"heading is not finite for {int(bad.sum())} drawn leader(s), e.g. row {int(np.argmax(bad))}")
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
            if heading is None:
                self._draw_squares(flat, leader[s:e], self.colors["leader"])
            else:
                self._draw_triangles(flat, leader[s:e], heading[s:e], self.colors["leader"])
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
