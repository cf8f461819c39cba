"""The camera inside the bound (SPEC §5.1): linear bounds in the position of every pixel the robot can touch.

A cell `P = [x0, x1] x [y0, y1]` is parametrised by `t in [-1, 1]^2`, `p = c + h * t` (`c` its centre, `h` its
half-sides). The renderer (:meth:`pipeline.render.Camera._draw_squares`) draws the robot, a square of side `L`
px centred at `(u, v)` (continuous pixel coordinates, :func:`pipeline.render.world_to_pixel`), with the exact
overlap area as coverage: `alpha = alpha_x(u) alpha_y(v)`, each factor the overlap of an interval of length `L`
with a pixel's unit interval, `max(0, min(1, L, c + 1 + L/2 - u, u + L/2 - c))`: a trapezoid (piecewise linear
with four breakpoints) in `u`, and `u` is affine in `t_x` (`v` in `t_y`, decreasing in `y`).

- **Factors.** Over the cell each factor gets its chord's slope and the offsets of the largest and smallest
  deviation from the chord at the endpoints and the breakpoints inside: sound linear lower/upper bounds
  (exact where the factor is linear on the cell), and its exact range.
- **Product.** `alpha_x alpha_y`: McCormick's planes with the factors' linear bounds substituted (every
  coefficient is a non-negative range end, so the substitution is sound), the best of them at the cell's
  centre, and the constants `0` / `max alpha_x max alpha_y`.
- **Pixel.** `floor(s + alpha (c_robot - s) + 0.5)` per channel over the static image `s`: the blend's bounds
  plus a rounding term `±0.5` level wherever the coverage can be fractional on the cell (`0 < alpha < 1`
  somewhere, and `c_robot != s`); a pixel-attack budget `kappa` adds `±kappa` levels. Pixels outside the image
  are the convolution's zero padding.

A form is a tensor `(..., S, ...)` whose slot 0 is the constant and slots 1, 2 the coefficients of `t_x, t_y`;
`S = 1` (intervals: the forms concretised) is the IBP mode. A pose cell's (the unicycle's triangle marker,
:func:`marker_coverage`) has a slot 3 for `t_θ`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from pipeline.render.marker import MARKER_REACH, heading_marker, polygon_coverage


@dataclass
class PixelWindow:
    """The pixels the robot can touch from each cell: window origin `(row, col)` `(N, 2)` (int64), the
    window's lower / upper forms `(N, S, 3, Kr, Kc)` in levels `[0, 255]`."""

    origin: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor


def _factor(a: torch.Tensor, b: torch.Tensor, idx: torch.Tensor, size: float):
    """Bounds of the overlap of `[w - size/2, w + size/2]` with `[idx, idx + 1]` for `w in [a, b]` (`(N,)`),
    per pixel index `idx (N, K)`, as forms in `s in [-1, 1]` (`w = (a + b)/2 + (b - a)/2 s`):
    `(lo0, lo1, hi0, hi1, min, max)`, each `(N, K)`."""
    m = min(1.0, size)
    a, b = a[:, None], b[:, None]

    def f(w, i=idx):
        return torch.clamp(torch.minimum(i + 1 + size / 2 - w, w + size / 2 - i), max=m, min=0.0)

    breaks = torch.stack([idx - size / 2, idx - size / 2 + m, idx + 1 + size / 2 - m, idx + 1 + size / 2], -1)
    pts = torch.cat([torch.minimum(torch.maximum(breaks, a[..., None]), b[..., None]),
                     a[..., None].expand_as(breaks[..., :1]), b[..., None].expand_as(breaks[..., :1])], -1)
    fa, fb = f(a), f(b)
    half = (b - a) / 2
    slope = (fb - fa) / torch.clamp(b - a, min=1e-300)  # per unit of w
    vals = f(pts, idx[..., None])
    dev = vals - (fa[..., None] + slope[..., None] * (pts - a[..., None]))
    mid = fa + slope * half  # the chord at the centre
    return (mid + dev.min(-1).values, slope * half, mid + dev.max(-1).values, slope * half,
            vals.min(-1).values, vals.max(-1).values)


def _product(fx, fy):
    """Forms `(N, 3, Kr, Kc)` (const, t_x, t_y) bounding `alpha_x alpha_y` (McCormick, see the module doc)."""
    lx0, lx1, ux0, ux1, xl, xu = (t[:, None, :] for t in fx)  # (N, 1, Kc): in t_x
    ly0, ly1, uy0, uy1, yl, yu = (t[:, :, None] for t in fy)  # (N, Kr, 1): in t_y
    zero = torch.zeros_like(xl * yl)
    lowers = [  # (xl y + yl x - xl yl) and (xu y + yu x - xu yu), factors' lower forms substituted; and 0
        torch.stack([xl * ly0 + yl * lx0 - xl * yl, yl * lx1 + zero, xl * ly1 + zero]),
        torch.stack([xu * ly0 + yu * lx0 - xu * yu, yu * lx1 + zero, xu * ly1 + zero]),
        torch.stack([zero, zero, zero]),
    ]
    uppers = [  # (xu y + yl x - xu yl) and (xl y + yu x - xl yu), upper forms substituted; and xu yu
        torch.stack([xu * uy0 + yl * ux0 - xu * yl, yl * ux1 + zero, xu * uy1 + zero]),
        torch.stack([xl * uy0 + yu * ux0 - xl * yu, yu * ux1 + zero, xl * uy1 + zero]),
        torch.stack([xu * yu, zero, zero]),
    ]
    lo_all, hi_all = torch.stack(lowers), torch.stack(uppers)  # (3 candidates, 3 slots, N, Kr, Kc)
    pick_lo = lo_all[:, 0].argmax(0, keepdim=True)[:, None].expand(1, 3, *lo_all.shape[2:])
    pick_hi = hi_all[:, 0].argmin(0, keepdim=True)[:, None].expand(1, 3, *hi_all.shape[2:])
    lo = lo_all.gather(0, pick_lo)[0].movedim(0, 1)
    hi = hi_all.gather(0, pick_hi)[0].movedim(0, 1)
    frac = (xu > 0) & (yu > 0) & ~((xl >= 1) & (yl >= 1))  # coverage can be fractional on the cell
    return lo, hi, (xl * yl).expand_as(frac), (xu * yu).expand_as(frac), frac


def pixel_window(camera, cells: torch.Tensor, kappa: float = 0.0, symbolic: bool = True) -> PixelWindow:
    """The robot's pixels from each cell `cells (N, 4) = (x0, x1, y0, y1)` (world units), as forms (see the
    module doc; `symbolic=False`: intervals, `S = 1`). Computed in float64. A cell with a heading interval,
    `(N, 6) = (x0, x1, y0, y1, th0, th1)`, is a unicycle's: its marker's window (:func:`marker_coverage`)."""
    cells = torch.as_tensor(cells).to(torch.float64)
    if cells.shape[1] == 6:
        rows, cols, a_lo, a_hi, frac, amin, amax = marker_coverage(camera, cells)
        r0, c0 = rows[:, 0], cols[:, 0]
    else:
        (ax0, _), (_, ay1) = camera.arena
        k = float(camera.scale)
        size = float(camera.robot_size)
        ua, ub = (cells[:, 0] - ax0) * k, (cells[:, 1] - ax0) * k
        va, vb = (ay1 - cells[:, 3]) * k, (ay1 - cells[:, 2]) * k
        c0 = torch.floor(ua - size / 2).long()
        r0 = torch.floor(va - size / 2).long()
        kc = int((torch.floor(ub + size / 2).long() - c0).max()) + 1
        kr = int((torch.floor(vb + size / 2).long() - r0).max()) + 1
        cols = c0[:, None] + torch.arange(kc)
        rows = r0[:, None] + torch.arange(kr)
        fx = _factor(ua, ub, cols.double(), size)
        fy = list(_factor(va, vb, rows.double(), size))
        fy[1], fy[3] = -fy[1], -fy[3]  # v decreases with t_y
        a_lo, a_hi, amin, amax, frac = _product(fx, fy)
    inside = ((rows >= 0) & (rows < camera.height))[:, :, None] & ((cols >= 0) & (cols < camera.width))[:, None, :]
    bg = torch.as_tensor(camera.background, dtype=torch.float64)  # (H, W, 3)
    s = bg[rows.clamp(0, camera.height - 1)[:, :, None], cols.clamp(0, camera.width - 1)[:, None, :]]
    s = (s * inside[..., None]).permute(0, 3, 1, 2)  # (N, 3, Kr, Kc)
    d = torch.as_tensor(camera.colors["leader"], dtype=torch.float64).view(1, 3, 1, 1) - s
    if not symbolic:
        a_lo, a_hi = amin[:, None], amax[:, None]
    a_lo, a_hi = (t * inside[:, None] for t in (a_lo, a_hi))  # (N, S slots, Kr, Kc)
    dp, dn = d.clamp(min=0)[:, None], d.clamp(max=0)[:, None]  # (N, 1, 3 channels, Kr, Kc)
    lo = dp * a_lo[:, :, None] + dn * a_hi[:, :, None]
    hi = dp * a_hi[:, :, None] + dn * a_lo[:, :, None]
    slack = 0.5 * ((frac & inside)[:, None] & (d != 0)) + kappa * inside[:, None]  # (N, 3, Kr, Kc)
    lo[:, 0] += s - slack
    hi[:, 0] += s + slack
    if kappa:
        lo[:, 0] = torch.where(inside[:, None], lo[:, 0], 0.0)
        hi[:, 0] = torch.where(inside[:, None], hi[:, 0], 0.0)
    if not symbolic:
        lo, hi = lo[:, :1], hi[:, :1]
    return PixelWindow(torch.stack([r0, c0], 1), lo, hi)


COVERAGE_SLACK = 1e-9  # the exact-area coverage's float rounding, added on both sides of its interval


def _incircle(verts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Incentre `(N, 2)` and inradius `(N,)` of triangles `(N, 3, 2)`."""
    a = np.linalg.norm(verts[:, 1] - verts[:, 2], axis=-1)
    b = np.linalg.norm(verts[:, 2] - verts[:, 0], axis=-1)
    c = np.linalg.norm(verts[:, 0] - verts[:, 1], axis=-1)
    centre = (a[:, None] * verts[:, 0] + b[:, None] * verts[:, 1] + c[:, None] * verts[:, 2]) / (a + b + c)[:, None]
    e1, e2 = verts[:, 1] - verts[:, 0], verts[:, 2] - verts[:, 0]
    area = 0.5 * np.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    return centre, 2 * area / (a + b + c)


def _parallel(camera, c: np.ndarray, outer: bool) -> np.ndarray:
    """The outer (`outer`) or inner parallel triangle `(N, 3, 2)` of each pose cell's centre marker at the distance
    `rho` every marker of the cell stays within (see :func:`marker_coverage`; an empty inner one: a point)."""
    L = float(camera.robot_size)
    centre = np.column_stack([(c[:, 0] + c[:, 1]) / 2, (c[:, 2] + c[:, 3]) / 2])
    uv = np.asarray(camera.world_to_pixel(centre), dtype=np.float64)
    corner = np.asarray(camera.world_to_pixel(c[:, [1, 3]]), dtype=np.float64)  # (x1, y1): (u, v) of a corner
    rho = np.hypot(*(corner - uv).T) + 2 * np.sin(np.minimum((c[:, 5] - c[:, 4]) / 2, np.pi) / 2) * MARKER_REACH * L
    verts = heading_marker(uv, (c[:, 4] + c[:, 5]) / 2, L)  # (N, 3, 2)
    inc, r = _incircle(verts)
    scale = (r + rho) / r if outer else np.maximum(0.0, (r - rho) / r)
    return inc[:, None] + (verts - inc[:, None]) * scale[:, None, None]


SUBCELLS = (3, 3, 4)  # sub-cells per axis (x, y, heading) of a pose cell for the linear forms' deviation


def _subcells(mid: np.ndarray, half: np.ndarray):
    """Per sub-cell of the `SUBCELLS` grid: its centre `t_j` in `[-1, 1]^3` and its pose cells `(N, 6)`."""
    m = np.asarray(SUBCELLS, dtype=float)
    axes = [(2 * np.arange(k) + 1) / k - 1 for k in SUBCELLS]
    for t in np.stack(np.meshgrid(*axes, indexing="ij"), -1).reshape(-1, 3):
        lo, hi = mid + half * (t - 1 / m), mid + half * (t + 1 / m)
        yield t, np.stack([lo, hi], -1).reshape(len(mid), 6)


def marker_coverage(camera, cells: torch.Tensor):
    """The unicycle marker's coverage of each pixel over cells of poses `(N, 6) = (x0, x1, y0, y1, th0, th1)`:
    `rows (N, K)`, `cols (N, K)` of the window, forms `(N, 4, K, K)` (slots: constant, `t_x`, `t_y`, `t_θ`) of its
    lower and upper coverage, where it can be fractional `(N, K, K)`, and its range (lower, upper) `(N, K, K)`.

    **Intervals.** Every point of the marker at a pose of a cell lies within `rho` px of its place at the cell's
    centre pose (`rho`: the centre's distance to the cell's corner, plus `2 sin(w/2) |m|` for a rotation by at
    most the half interval `w` of a point `m` at most `MARKER_REACH L` from the position). So every marker of the
    cell contains the centre marker's inner parallel triangle at distance `rho` (its homothety about the incentre
    by `(r - rho)/r`, empty when `rho >= r`) and lies in its outer one (`(r + rho)/r`): their exact-area
    coverages (:func:`pipeline.render.marker.polygon_coverage`, as the camera draws) bound the pixel's. No marker
    leaves the disc of radius `MARKER_REACH L` plus the corner's distance around the centre position: the window is
    the outer triangle's box within that disc's.

    **Linear forms.** `l(t) = a(0) + g t` with `g` the central differences of the exact coverage across the cell's
    faces; over each of the `SUBCELLS` sub-cells `j` (centre `t_j`) the coverage lies in that sub-cell's interval
    and `l` within `sum_i |g_i| / m_i` of `l(t_j)`, so the deviation `a - l` lies between the smallest and the
    largest of those differences: `l` plus them are sound lower and upper forms (the interval's constants where
    they are tighter at the centre)."""
    c = cells.numpy()
    outer = _parallel(camera, c, True)
    # the window: the outer triangle's box within the disc every marker of the cell lies in (the reach around the
    # centre position, plus the centre's distance to the cell's corner)
    uv = np.asarray(camera.world_to_pixel(np.column_stack([(c[:, 0] + c[:, 1]) / 2, (c[:, 2] + c[:, 3]) / 2])))
    corner = np.asarray(camera.world_to_pixel(c[:, [1, 3]]))
    disc = (np.hypot(*(corner - uv).T) + MARKER_REACH * float(camera.robot_size))[:, None]
    first, last = np.maximum(outer.min(1), uv - disc), np.minimum(outer.max(1), uv + disc)
    start = np.floor(first).astype(np.int64)  # (N, 2): (u, v) of the window's first pixel
    steps = np.arange(int((np.floor(last).astype(np.int64) - start).max()) + 1)
    rows, cols = start[:, 1, None] + steps, start[:, 0, None] + steps
    cover = lambda cl, out: polygon_coverage(_parallel(camera, cl, out), rows, cols)  # noqa: E731
    lo_c, hi_c = cover(c, False), cover(c, True)
    mid = np.column_stack([(c[:, 0] + c[:, 1]) / 2, (c[:, 2] + c[:, 3]) / 2, (c[:, 4] + c[:, 5]) / 2])
    half = np.column_stack([(c[:, 1] - c[:, 0]) / 2, (c[:, 3] - c[:, 2]) / 2, (c[:, 5] - c[:, 4]) / 2])
    at = lambda t: cover(np.repeat(mid + half * t, 2, axis=1), True)  # noqa: E731 - a cell of one pose: exact
    a0 = at(np.zeros(3))
    g = np.stack([(at(e) - at(-e)) / 2 for e in np.eye(3)], 1)  # (N, 3, K, K)
    reach = np.einsum("nikl,i->nkl", np.abs(g), 1.0 / np.asarray(SUBCELLS, dtype=float))
    d_lo, d_hi = np.full_like(a0, np.inf), np.full_like(a0, -np.inf)
    for t, sub in _subcells(mid, half):
        l_j = a0 + np.einsum("nikl,i->nkl", g, t)
        d_lo = np.minimum(d_lo, cover(sub, False) - l_j - reach)
        d_hi = np.maximum(d_hi, cover(sub, True) - l_j + reach)
    frac = (hi_c > COVERAGE_SLACK) & (lo_c < 1 - COVERAGE_SLACK)
    con_lo, con_hi = np.clip(lo_c - COVERAGE_SLACK, 0.0, 1.0), np.clip(hi_c + COVERAGE_SLACK, 0.0, 1.0)
    form = lambda v, slopes: np.concatenate([v[:, None], slopes], 1)  # noqa: E731
    lin_lo, lin_hi = form(a0 + d_lo - COVERAGE_SLACK, g), form(a0 + d_hi + COVERAGE_SLACK, g)
    lo = np.where((lin_lo[:, :1] > con_lo[:, None]), lin_lo, form(con_lo, 0 * g))
    hi = np.where((lin_hi[:, :1] < con_hi[:, None]), lin_hi, form(con_hi, 0 * g))
    return tuple(torch.as_tensor(v) for v in (rows, cols, lo, hi, frac, con_lo, con_hi))


def window_reach(cell_size: float, robot_size: float) -> int:
    """Pixels per side a cell of `cell_size` px can touch with a robot of `robot_size` px (an upper bound)."""
    return int(math.ceil(cell_size + robot_size)) + 1
