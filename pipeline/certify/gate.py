"""The gate under clouds (issue 44): sound bounds of the map's predicted error over a cell and a layout.

The closed loop drops a frame whose predicted error exceeds `camera.gate` (:func:`pipeline.perception.measure.
gated_predict`): `err = hypot(sx, sy)`, `s = exp(0.5 clamp(v, LOGVAR_RANGE)) half_range sigma_scale` per
coordinate, `v = W2 relu(W1 [f, thumb] + b1) + b2` the variance head on the last block's pooled features `f` and
the image's thumbnail `thumb = (avgpool(img) / 255 - 0.5) THUMB_SCALE` (:class:`pipeline.perception.network.
FoldedPerceptionNet`). :func:`gate_range` bounds `err` over every position of a cell, for every frame the camera
renders there (a layout's blend included: the pixels are the bound's, :attr:`.bounds.Prepared.pixels`):

- `f`: the cone's forward pass (:func:`.cone.forward`, the same as the error bound's) gives the pooled window's
  forms in the position `t`; outside the window `f` is the static image's (under the layout);
- `thumb`: average pooling is linear with non-negative weights, so the pixels' forms pool to forms of the
  thumbnail (outside the window: the static image's thumbnail, exact);
- `W1 [f, thumb]`: both parts are forms in the same `t`, summed, then concretized (no interval loss between them);
  then IBP through the ReLU and `W2`, and the monotone map `v -> err` (increasing in each coordinate).

A verdict per (cell, layout) at an `eps` and a gate `g` (:func:`verdicts`): `certified` (`eps_bar <= eps`),
`flagged` (the lower bound of `err` above `g`: every frame at every position of the cell is dropped, and a dropped
frame is no error: the bracket's lost frames), else `undecided`. :func:`eps_delta_gated`: the Clopper-Pearson
`eps_bar_delta` of `X = eps_bar(P, L)` with `X = 0` on flagged layouts (i.i.d. over layouts, so the order
statistic argument of :func:`.clouds.eps_delta` holds as it is): with confidence `1 - beta`, a frame at a position
of `P` under a fresh layout is either dropped or within it with probability `>= 1 - delta`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pipeline.certify.bounds import Prepared
from pipeline.certify.clouds import cell_points, eps_delta, over_layouts
from pipeline.certify.cone import MARGIN, concretize, forward, gather, pad
from pipeline.certify.renderer import pixel_window
from pipeline.perception.network import LOGVAR_RANGE, THUMB_SCALE

CHUNK = 64  # cells per pass (the hidden layer's window weights are `(N, 64, C, pr, pc)`)
CERTIFIED, FLAGGED, UNDECIDED = 0, 1, 2


@dataclass
class VarHead:
    """The variance head split along what it reads (float64): `w1f (H, C, h, w)` on the pooled features,
    `w1t (H, 3, th, tw)` on the thumbnail, `b1`, `w2 (2, H)`, `b2`; the pooling matrices `rows (th, H_img + 2M)`,
    `cols (tw, W_img + 2M)` (zero on the MARGIN padding); `scale (2,)`: `half_range sigma_scale`."""

    w1f: torch.Tensor
    w1t: torch.Tensor
    b1: torch.Tensor
    w2: torch.Tensor
    b2: torch.Tensor
    rows: torch.Tensor
    cols: torch.Tensor
    scale: torch.Tensor

    def __post_init__(self):
        self.w1f_padded = pad(self.w1f.flatten(0, 1))  # once: `(H C, h + 2M, w + 2M)`, gathered per cell and layout


def pool_matrix(n: int, m: int) -> torch.Tensor:
    """`adaptive_avg_pool` along one axis of `n` to `m` bins as a matrix `(m, n + 2 MARGIN)` (bins `[floor(i n /
    m), ceil((i + 1) n / m))`, PyTorch's), padded with zero columns."""
    a = torch.zeros(m, n + 2 * MARGIN, dtype=torch.float64)
    for i in range(m):
        s, e = (i * n) // m, -((-(i + 1) * n) // m)
        a[i, MARGIN + s:MARGIN + e] = 1.0 / (e - s)
    return a


def var_head(model) -> VarHead:
    """The variance head of `model` (a `PerceptionNet` with `uncertainty: gaussian`); ValueError without one."""
    if getattr(model, "var_head", None) is None:
        raise ValueError("the map has no uncertainty head (model.uncertainty=gaussian): there is no gate to bound")
    lin = [m for m in model.var_head if isinstance(m, nn.Linear)]
    (th, tw), (h, w, _) = model.thumb_size, model.image_shape
    w1 = lin[0].weight.detach().double()
    n_thumb = 3 * th * tw
    c_last = [m for m in model.features if isinstance(m, nn.Conv2d)][-1].out_channels
    w1f = w1[:, :-n_thumb].reshape(len(w1), c_last, *_grid(model))
    scale = (model.half_range.detach().double() * model.sigma_scale.detach().double())
    return VarHead(w1f, w1[:, -n_thumb:].reshape(len(w1), 3, th, tw), lin[0].bias.detach().double(),
                   lin[1].weight.detach().double(), lin[1].bias.detach().double(), pool_matrix(h, th),
                   pool_matrix(w, tw), scale)


def _grid(model) -> tuple[int, int]:
    h, w, _ = model.image_shape
    for m in model.features:
        if isinstance(m, nn.MaxPool2d):
            h, w = h // 2, w // 2
    return h, w


def predicted_error(v: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
    """The gate's statistic from log variances `v (..., 2)`: `hypot` of the calibrated sigmas (world units)."""
    s = torch.exp(0.5 * v.clamp(*LOGVAR_RANGE)) * scale
    return torch.sqrt((s ** 2).sum(-1))


def _forms(vh: VarHead, prep: Prepared, cells: torch.Tensor, mode: str):
    """Lower / upper forms `(N, S, H)` of the variance head's hidden pre-activations over the cells."""
    pw = pixel_window(prep.camera, cells, prep.kappa, symbolic=mode != "ibp")
    if prep.pixels is not None:
        pw = prep.pixels(pw)
    dtype = prep.net.head_w.dtype
    cone = forward(prep.net, prep.static, pw.origin, pw.lo.to(dtype), pw.hi.to(dtype), ibp=mode == "ibp")
    st = prep.static
    f_st, img = st.inputs_lo[-1].double(), st.inputs_lo[0].double()  # kappa 0: lo is hi
    thumb_st = (torch.einsum("ik,ckl,jl->cij", vh.rows[:, MARGIN:-MARGIN], img, vh.cols[:, MARGIN:-MARGIN])
                / 255.0 - 0.5) * THUMB_SCALE
    total = vh.b1 + (vh.w1f * f_st).flatten(1).sum(-1) + (vh.w1t * thumb_st).flatten(1).sum(-1)  # (H,)
    # the features' window: its forms replace the static values there
    lo, hi = cone.lo.double(), cone.hi.double()
    size = tuple(lo.shape[-2:])
    win = gather(vh.w1f_padded, cone.origin, size).unflatten(1, vh.w1f.shape[:2])  # (N, H, C, pr, pc)
    s_win = gather(pad(f_st), cone.origin, size)  # (N, C, pr, pc)
    const = total - (win * s_win[:, None]).flatten(2).sum(-1)  # (N, H)
    wp, wn = win.clamp(min=0), win.clamp(max=0)
    mul = lambda w, t: torch.einsum("nhcij,nscij->nsh", w, t)  # noqa: E731
    y_lo, y_hi = mul(wp, lo) + mul(wn, hi), mul(wp, hi) + mul(wn, lo)  # (N, S, H)
    # the thumbnail: the window's pixels minus the static ones, pooled (non-negative weights keep the sides)
    p_lo, p_hi = pw.lo.double(), pw.hi.double()
    kr, kc = p_lo.shape[-2:]
    static_px = gather(pad(img), pw.origin, (kr, kc))  # (N, 3, Kr, Kc)
    p_lo = torch.cat([p_lo[:, :1] - static_px[:, None], p_lo[:, 1:]], 1)
    p_hi = torch.cat([p_hi[:, :1] - static_px[:, None], p_hi[:, 1:]], 1)
    r = vh.rows[:, pw.origin[:, 0, None] + MARGIN + torch.arange(kr)].movedim(1, 0)  # (N, th, Kr)
    c = vh.cols[:, pw.origin[:, 1, None] + MARGIN + torch.arange(kc)].movedim(1, 0)  # (N, tw, Kc)
    t_lo, t_hi = (torch.einsum("nik,nsckl,njl->nscij", r, p, c) * (THUMB_SCALE / 255.0) for p in (p_lo, p_hi))
    tp, tn = vh.w1t.clamp(min=0), vh.w1t.clamp(max=0)  # (H, 3, th, tw)
    y_lo = y_lo + torch.einsum("hcij,nscij->nsh", tp, t_lo) + torch.einsum("hcij,nscij->nsh", tn, t_hi)
    y_hi = y_hi + torch.einsum("hcij,nscij->nsh", tp, t_hi) + torch.einsum("hcij,nscij->nsh", tn, t_lo)
    y_lo[:, 0] += const
    y_hi[:, 0] += const
    return y_lo, y_hi


def gate_range(vh: VarHead, prep: Prepared, cells, mode: str = "crown") -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds `(N,)` of the predicted error (the gate's statistic, world units) over each cell
    `cells (N, 4)`, for every frame rendered there (under `prep`'s layout, if any). `mode`: `ibp` (intervals) or
    else the forms of the forward pass (`forward`, `crown`: the same). Each side moved out by `prep.float_margin`."""
    if prep.kappa != 0:
        raise ValueError("the gate's bound covers kappa = 0")
    cells = torch.as_tensor(cells).to(torch.float64)
    out_lo, out_hi = [], []
    for part in cells.split(CHUNK):
        y_lo, y_hi = _forms(vh, prep, part, mode)
        a_lo, a_hi = (t.clamp(min=0) for t in concretize(y_lo, y_hi))  # (N, H): after the ReLU
        w2p, w2n = vh.w2.clamp(min=0), vh.w2.clamp(max=0)
        v_lo = a_lo @ w2p.T + a_hi @ w2n.T + vh.b2
        v_hi = a_hi @ w2p.T + a_lo @ w2n.T + vh.b2
        out_lo.append(predicted_error(v_lo, vh.scale) - prep.float_margin)
        out_hi.append(predicted_error(v_hi, vh.scale) + prep.float_margin)
    return torch.cat(out_lo), torch.cat(out_hi)


def layout_gate(model, prep: Prepared, cells: np.ndarray, layouts, mode: str = "crown", tick=None):
    """`(lower, upper) (C, L)`: the gate statistic's bounds for every cell and layout (clear layouts: the clean
    bound, once), as :func:`.clouds.layout_bounds` goes over them (`tick()` after each layout)."""
    vh = var_head(model)
    return over_layouts(prep, layouts, lambda p: [t.numpy() for t in gate_range(vh, p, cells, mode)], (len(cells),),
                        tick)


def verdicts(eps: np.ndarray, gate_lower: np.ndarray, at: float, gate: float) -> np.ndarray:
    """Per (cell, layout): CERTIFIED (`eps <= at`), else FLAGGED (`gate_lower > gate`), else UNDECIDED."""
    return np.where(eps <= at, CERTIFIED, np.where(gate_lower > gate, FLAGGED, UNDECIDED))


def eps_delta_gated(eps: np.ndarray, gate_lower: np.ndarray, gate: float, delta: float = 0.01,
                    confidence: float = 0.95) -> np.ndarray:
    """Per cell the smallest `e` whose CP upper bound on `Pr(neither eps_bar <= e nor flagged)` is `<= delta`."""
    return eps_delta(np.where(gate_lower > gate, 0.0, eps), delta, confidence)


def shares(eps: np.ndarray, gate_lower: np.ndarray, at: float, gate: float) -> dict:
    """Per cell `(C,)`: the shares of layouts flagged and undecided at `eps = at` (the rest are certified)."""
    v = verdicts(eps, gate_lower, at, gate)
    return {"flagged_share": (v == FLAGGED).mean(1), "undecided_share": (v == UNDECIDED).mean(1)}


def gate_sampled_check(predicted_error_fn, camera, occ, cells: np.ndarray, lower, upper, layouts, samples: int,
                       seed: int = 0, stream: int = 0):
    """Positions drawn in each cell, rendered with each layout through the camera: how many predicted errors
    (`predicted_error_fn(images) -> (est, err)`, the loop's) leave the layout's gate bounds, and the largest
    relative excess."""
    rng = np.random.default_rng([seed, 4405, stream])
    bad, worst = 0, -np.inf
    for j in range(len(layouts)):
        p = cell_points(rng, cells, samples)
        err = np.asarray(predicted_error_fn(camera.render(p, occlusion=occ, clouds=layouts.clouds[np.full(len(p), j)]))[1],
                         np.float64).reshape(len(cells), samples)
        excess = np.maximum(lower[:, j, None] - err, err - upper[:, j, None]) / np.maximum(upper[:, j, None], 1e-12)
        bad, worst = bad + int((excess > 0).sum()), max(worst, float(excess.max()))
    return bad, worst


def gate_fresh_check(predicted_error_fn, camera, occ, cells: np.ndarray, eps_gated: np.ndarray, gate: float,
                     frames: int, seed: int, stream: int = 0) -> dict:
    """Frames at uniform positions of each cell under fresh layouts (the loop's draw, as
    :func:`.clouds.fresh_check`): the share whose error exceeds `eps_bar_delta_gated` and that the gate keeps
    (to sit under `delta`, up to sampling), and the share dropped."""
    rng = np.random.default_rng([seed, 4406, stream])
    p = cell_points(rng, cells, frames)
    est, err = predicted_error_fn(camera.render(p, occlusion=occ, rng=rng))
    e = np.linalg.norm(np.asarray(est, np.float64)[:, :2] - p, axis=-1).reshape(len(cells), frames)
    kept = (np.asarray(err) <= gate).reshape(len(cells), frames)
    above = (e > eps_gated[:, None]) & kept
    return {"frames": int(above.size), "above": int(above.sum()), "rate": float(above.mean()),
            "worst_cell_rate": float(above.mean(1).max()), "dropped": float(1 - kept.mean())}
