"""`certified_error_bound`: sound bounds of the perception error `e = l(h(p)) - p` over cells (SPEC §5.1-5.2)."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import torch

from pipeline.certify.cone import concretize, forward, gather, pad
from pipeline.certify.crown import backward
from pipeline.certify.deployed import Deployed, Static, deployed, static_pass
from pipeline.certify.heading import heading_box, heading_error
from pipeline.certify.keypoint import keypoint_range
from pipeline.certify.renderer import pixel_window

MODES = ("ibp", "forward", "crown")
KEYPOINT_CHUNK = 4  # cells per backward pass through a keypoint head (6 per window neuron each; small is fastest)


@dataclass
class Prepared:
    """A map and camera ready to bound: the deployed network and the static image's activations at `kappa`."""

    net: Deployed
    static: Static
    camera: object
    kappa: float
    # a map of the renderer's pixel window (its forms in float64) before the network reads it, e.g. one cloud
    # layout over the image (:mod:`.clouds`; `static` then the static image under that layout); None: as rendered
    pixels: Callable | None = None
    # world units added to every bound on each side (:func:`certified_error_bound`, the gate's `gate_range`): the
    # deployed float32 network's own rounding and the bound's float arithmetic, which the relaxation (exact
    # arithmetic on the weights) does not see; the stages pass their `float_margin` (docs/certify.md, "Float32")
    float_margin: float = 0.0


def prepare(model, camera, kappa: float = 0.0, dtype: torch.dtype = torch.float32,
            float_margin: float = 0.0) -> Prepared:
    """The deployed form of `model` (differentiable in its parameters) and its static pass on `camera`'s
    static image. Rebuild it after the weights change. `float_margin`: :attr:`Prepared.float_margin` (0: the bound
    of the network in exact arithmetic)."""
    if not float_margin >= 0:
        raise ValueError(f"float_margin must be >= 0 (world units), got {float_margin!r}")
    net = model if isinstance(model, Deployed) else deployed(model, dtype)
    background = torch.as_tensor(camera.background, device=net.head_w.device)
    return Prepared(net, static_pass(net, background, float(kappa)), camera, float(kappa),
                    float_margin=float(float_margin))


@dataclass
class ErrorBound:
    """Per cell and coordinate: `lower <= e <= upper` for every position of the cell (`(N, 2)`, world units); a
    cell of poses: `heading (N,)`, the largest wrapped heading error (radians) over it."""

    lower: torch.Tensor
    upper: torch.Tensor
    heading: torch.Tensor | None = None

    @property
    def eps(self) -> torch.Tensor:
        """The Euclidean bound `max |e|` over the cell from the per-coordinate bounds `(N,)`."""
        worst = torch.maximum(self.lower.abs(), self.upper.abs())
        return torch.sqrt((worst ** 2).sum(-1))


def _head(prep: Prepared, cone):
    """The head's weights on the feature window `(N, 2, C, pr, pc)` and the rest's contribution `(N, 2)` as
    lower / upper constants (bias included)."""
    net, st = prep.net, prep.static
    size = tuple(cone.lo.shape[-2:])
    w = net.head_w
    win = gather(pad(w.flatten(0, 1)), cone.origin, size).unflatten(1, w.shape[:2])
    f_lo, f_hi = st.inputs_lo[-1], st.inputs_hi[-1]
    total_lo = (w.clamp(min=0) * f_lo + w.clamp(max=0) * f_hi).flatten(1).sum(-1)
    total_hi = (w.clamp(min=0) * f_hi + w.clamp(max=0) * f_lo).flatten(1).sum(-1)
    s_lo, s_hi = gather(pad(f_lo), cone.origin, size)[:, None], gather(pad(f_hi), cone.origin, size)[:, None]
    in_lo = (win.clamp(min=0) * s_lo + win.clamp(max=0) * s_hi).flatten(2).sum(-1)
    in_hi = (win.clamp(min=0) * s_hi + win.clamp(max=0) * s_lo).flatten(2).sum(-1)
    return win, net.head_b + total_lo - in_lo, net.head_b + total_hi - in_hi


def _error_range(prep: Prepared, cells: torch.Tensor, z_lo: torch.Tensor, z_hi: torch.Tensor):
    """Bounds of `e = clamp(z) * half_range + center - p` from forms of `z` `(N, 2, S)` over the cells."""
    net = prep.net
    half, center = net.half_range, net.center
    c = torch.stack([(cells[:, 0] + cells[:, 1]) / 2, (cells[:, 2] + cells[:, 3]) / 2], 1)
    h = torch.stack([(cells[:, 1] - cells[:, 0]) / 2, (cells[:, 3] - cells[:, 2]) / 2], 1)

    def err_range(z):  # half * z + center - p as a form in t (p = c + h t), and its range
        e = z * half[:, None]
        const = e[..., 0] + center - c
        coef = -torch.diag_embed(h)  # (N, 2, 2): in (t_x, t_y); a pose cell's t_θ moves only z
        coef = torch.cat([coef, coef.new_zeros((*coef.shape[:2], max(z.shape[-1] - 3, 0)))], -1)
        if z.shape[-1] > 1:
            coef = coef + e[..., 1:]
        form = torch.cat([const[..., None], coef], -1).movedim(-1, 1)
        return concretize(form, form)

    d_lo, _ = err_range(z_lo)
    _, d_hi = err_range(z_hi)
    if not net.clamp:
        return d_lo, d_hi
    p_lo, p_hi = c - h, c + h
    a_lo, b_lo = half + center - p_hi, -half + center - p_hi
    lower = torch.minimum(a_lo, torch.maximum(b_lo, d_lo))
    a_hi, b_hi = -half + center - p_lo, half + center - p_lo
    upper = torch.maximum(a_hi, torch.minimum(b_hi, d_hi))
    return lower, upper


def certified_error_bound(prep: Prepared, cells: torch.Tensor, mode: str = "crown") -> ErrorBound:
    """Sound bounds of `e = l(h(p)) - p` over each cell `cells (N, 4) = (x0, x1, y0, y1)` (world units; a pose
    map's `(N, 6)`, the heading interval `th0, th1` last, with the heading error too) for every image the camera
    renders there (uint8 rounding included; under `prep.kappa`, every image within
    `kappa` levels of it). `mode`: `ibp` (intervals), `forward` (linear forms in the position, forward only),
    `crown` (forward, then the backward pass; the tightest). A keypoint head (:mod:`.keypoint`) is bounded from
    the intervals of its outputs on the last block's window (`crown`: the tighter of the forward and the backward
    bounds of each). Each side moved out by `prep.float_margin`."""
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    net = prep.net
    if net.keypoint is not None and mode == "crown" and len(cells) > KEYPOINT_CHUNK:  # a backward pass per output
        parts = [certified_error_bound(prep, c, mode) for c in torch.as_tensor(cells).split(KEYPOINT_CHUNK)]
        heading = None if parts[0].heading is None else torch.cat([b.heading for b in parts])
        return ErrorBound(torch.cat([b.lower for b in parts]), torch.cat([b.upper for b in parts]), heading)
    dtype = net.head_w.dtype
    cells = torch.as_tensor(cells)
    if (cells.shape[1] == 6) != (net.heading is not None):
        raise ValueError("a pose map's cells carry a heading interval (N, 6), a position map's do not (N, 4)")
    pw = pixel_window(prep.camera, cells, prep.kappa, symbolic=mode != "ibp")
    if prep.pixels is not None:
        pw = prep.pixels(pw)
    lo, hi = pw.lo.to(dtype), pw.hi.to(dtype)
    cone = forward(net, prep.static, pw.origin, lo, hi, ibp=mode == "ibp")
    if net.keypoint is not None:
        z_lo, z_hi, scores = keypoint_range(net, prep.static, cone, (lo, hi) if mode == "crown" else None)
        heading = None
        if net.heading is not None:
            box = heading_box(net, prep.static, cone, scores, (lo, hi) if mode == "crown" else None)
            heading = heading_error(*box, cells[:, 4], cells[:, 5])
        lower, upper = _error_range(prep, cells.to(z_lo.dtype), z_lo[..., None], z_hi[..., None])
        return ErrorBound(lower - prep.float_margin, upper + prep.float_margin, heading)
    win, out_lo, out_hi = _head(prep, cone)
    wp, wn = win.clamp(min=0)[:, :, None], win.clamp(max=0)[:, :, None]  # (N, 2, 1, C, pr, pc)
    z_lo = (wp * cone.lo[:, None] + wn * cone.hi[:, None]).flatten(3).sum(-1)  # (N, 2, S)
    z_hi = (wp * cone.hi[:, None] + wn * cone.lo[:, None]).flatten(3).sum(-1)
    z_lo = torch.cat([z_lo[..., :1] + out_lo[..., None], z_lo[..., 1:]], -1)
    z_hi = torch.cat([z_hi[..., :1] + out_hi[..., None], z_hi[..., 1:]], -1)
    cells = cells.to(dtype)
    lower, upper = _error_range(prep, cells, z_lo, z_hi)
    if mode == "crown":
        forms = backward(net, cone, torch.cat([win, -win], 1), torch.cat([out_lo, -out_hi], 1), lo, hi)
        c_lo, c_hi = _error_range(prep, cells, forms[:, :2], -forms[:, 2:])
        lower, upper = torch.maximum(lower, c_lo), torch.minimum(upper, c_hi)
    return ErrorBound(lower - prep.float_margin, upper + prep.float_margin)
