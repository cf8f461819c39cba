"""Bounds through the keypoint head (`model.position_head: keypoint`, :mod:`pipeline.perception.keypoint`).

The head reads the last block's ReLU map `g` before its pooling: a 1x1 convolution gives per cell a score `s_c` and
an offset, and the position is the softmax-weighted mean `z = sum_c a_c v_c` of the cells' centres plus offsets
`v_c`. The 1x1 convolution of the cone's linear forms of `g` (in the position, over the cell; the static image's
values elsewhere), concretized, gives intervals `s_c in [l_c, u_c]`, `v_c in [vl_c, vu_c]`, and since `a_c >= 0`,
`z <= max_{s in box} sum_c softmax(s)_c vu_c`. That maximum is exact (:func:`softmax_mean_max`): at the optimum
`z*` every cell with `vu_c > z*` has its largest score and every other its smallest, so it is one of the `n`
threshold assignments of the cells sorted by `vu`. The lower bound is the same on `-vl`.
"""

from __future__ import annotations

import torch

from pipeline.certify.cone import MARGIN, concretize, pad
from pipeline.certify.crown import backward_from_relu


def softmax_mean_max(s_lo: torch.Tensor, s_hi: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """`max sum_c softmax(s)_c v_c` over `s_lo <= s <= s_hi` (`(N, n)` each -> `(N,)`), computed in float64."""
    s_lo, s_hi, v = s_lo.double(), s_hi.double(), v.double()
    order = v.argsort(-1, descending=True)
    v, lo, hi = v.gather(-1, order), s_lo.gather(-1, order), s_hi.gather(-1, order)
    m = hi.amax(-1, keepdim=True)
    eu, el = torch.exp(hi - m), torch.exp(lo - m)
    top_w, top_v = eu.cumsum(-1), (eu * v).cumsum(-1)  # the first k cells at their largest score
    rest_w = el.sum(-1, keepdim=True) - el.cumsum(-1)  # the others at their smallest
    rest_v = (el * v).sum(-1, keepdim=True) - (el * v).cumsum(-1)
    vals = (top_v + rest_v) / (top_w + rest_w)
    return torch.nan_to_num(vals, nan=float("-inf")).amax(-1).clamp(max=v[:, 0])  # never above the largest v


CROWN_PLACES = 12  # window places per cell bounded by backward passes: those of the largest forward upper scores


def window_crown(net, cone, pix_lo, pix_hi, score_hi, w, places: int = CROWN_PLACES):
    """The window's 1x1 outputs `w g` (`w (K, C)`: the keypoint head's score, dx, dy, or a heading head's first
    layer) bounded by backward passes from each of them to the pixels (:func:`.crown.backward_from_relu`) at the
    `places` places of each cell's window with the largest forward upper score `score_hi (N, h, w)` (where the
    attention can go; elsewhere `-inf, inf`): `(N, K, h, w)` lower and upper, bias excluded."""
    _, f_lo, _ = cone.g
    n, _, c, h, wd = f_lo.shape
    k = min(places, h * wd)
    nk = w.shape[0]
    top = score_hi.flatten(1).topk(k, -1).indices  # (N, k)
    w = w.to(f_lo.dtype)
    at = torch.eye(h * wd, dtype=w.dtype, device=w.device)[top].view(n, 1, k, 1, h, wd)
    lam = (w.view(1, nk, 1, c, 1, 1) * at).flatten(1, 2)  # (N, nk k, C, h, wd): one output at one place
    lam = torch.cat([lam, -lam], 1)
    forms = backward_from_relu(net, cone, lam, lam.new_zeros(lam.shape[:2]), pix_lo, pix_hi)
    low = forms[..., 0] - forms[..., 1:].abs().sum(-1)  # (N, P): each lower-bound form's minimum over the cell
    half = lam.shape[1] // 2
    lo = torch.full((n, nk, h * wd), float("-inf"), dtype=low.dtype, device=low.device)
    hi = torch.full_like(lo, float("inf"))
    idx = top[:, None].expand(n, nk, k)
    lo.scatter_(2, idx, low[:, :half].view(n, nk, k))
    hi.scatter_(2, idx, -low[:, half:].view(n, nk, k))
    return lo.view(n, nk, h, wd), hi.view(n, nk, h, wd)


def conv1x1(w: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Bounds of the 1x1 convolution `w (K, C)` (no bias) of values between `lo` and `hi` (channels on dim -3)."""
    wp, wn = w.clamp(min=0), w.clamp(max=0)
    return (torch.einsum("kc,...chw->...khw", wp, lo) + torch.einsum("kc,...chw->...khw", wn, hi),
            torch.einsum("kc,...chw->...khw", wp, hi) + torch.einsum("kc,...chw->...khw", wn, lo))


def on_grid(static_lo, static_hi, origin, win_lo, win_hi) -> tuple[torch.Tensor, torch.Tensor]:
    """The window's intervals `(N, C, h, w)` at `origin (N, 2)` written over the static map's `(C, H, W)`:
    `(N, C, H, W)` lower and upper."""
    n, _, h, wd = win_lo.shape
    height, width = static_lo.shape[-2:]
    rows = (origin[:, 0, None] + MARGIN + torch.arange(h))[:, :, None]
    cols = (origin[:, 1, None] + MARGIN + torch.arange(wd))[:, None, :]
    idx = torch.arange(n)[:, None, None]
    g_lo, g_hi = (pad(t).expand(n, -1, -1, -1).clone() for t in (static_lo, static_hi))
    g_lo[idx, :, rows, cols] = win_lo.permute(0, 2, 3, 1).to(g_lo.dtype)
    g_hi[idx, :, rows, cols] = win_hi.permute(0, 2, 3, 1).to(g_hi.dtype)
    crop = (slice(None), slice(None), slice(MARGIN, MARGIN + height), slice(MARGIN, MARGIN + width))
    return g_lo[crop], g_hi[crop]


def keypoint_range(net, static, cone, pixels=None):
    """Lower and upper bounds `(N, 2)` (float64) of the keypoint head's normalised position over each cell, and the
    scores (what a pose map's heading head weighs with): their intervals on the grid `(N, h w)` and the upper bounds
    on the cone's window `(N, h', w')`; `pixels` (the pixel forms `lo, hi`): the window's outputs also by backward
    passes (the tighter side of each)."""
    w, b, cx, cy, cell = net.keypoint
    origin, f_lo, f_hi = cone.g  # the window's ReLU outputs, forms (N, S, C, h, wd)
    bias = b.view(-1, 1, 1)
    st_lo, st_hi = (t + bias for t in conv1x1(w, static.post_lo[-1], static.post_hi[-1]))  # (3, H, W): static
    # the window's outputs: the convolution on the forms first (the position `t` moves every channel together),
    # then their range over the cell
    win_lo, win_hi = concretize(*conv1x1(w, f_lo, f_hi))  # (N, 3, h, wd)
    if pixels is not None:
        c_lo, c_hi = window_crown(net, cone, *pixels, win_hi[:, 0], w)
        win_lo, win_hi = torch.maximum(win_lo, c_lo), torch.minimum(win_hi, c_hi)
    k_lo, k_hi = on_grid(st_lo, st_hi, origin, win_lo + bias, win_hi + bias)
    height, width = st_lo.shape[-2:]
    s_lo, s_hi = k_lo[:, 0].flatten(1), k_hi[:, 0].flatten(1)
    out_lo, out_hi = [], []
    for axis, centre in ((0, cx.view(1, width)), (1, cy.view(height, 1))):
        a, c = k_lo[:, 1 + axis] * cell[axis], k_hi[:, 1 + axis] * cell[axis]
        v_lo, v_hi = (centre + torch.minimum(a, c)).flatten(1), (centre + torch.maximum(a, c)).flatten(1)
        out_hi.append(softmax_mean_max(s_lo, s_hi, v_hi))
        out_lo.append(-softmax_mean_max(s_lo, s_hi, -v_lo))
    # float64: no rounding below the bound
    return torch.stack(out_lo, 1), torch.stack(out_hi, 1), (s_lo, s_hi, win_hi[:, 0] + b[0])
