"""Bounds through a pose map's heading (`heading_head: attention`, :mod:`pipeline.perception.heading`).

The head reads the attention-weighted mean of the last block's ReLU map `g` (the keypoint head's weights
`a = softmax(s)`) through an MLP `W2 relu(W1 m + b1) + b2 = (cos θ, sin θ)`, `θ = atan2`. Since the weights sum
to one, `W1 m = sum_c a_c (W1 g_c)`: the first layer is applied to the window's linear forms of `g` first (the
position moves every channel together), concretized per place, and each hidden unit's weighted mean is bounded
exactly over the score and value intervals (:func:`.keypoint.softmax_mean_max`); then intervals through the ReLU
and the last layer. :func:`heading_error` turns the `(cos, sin)` box and the cell's heading interval into the
largest wrapped heading error (`π` when the box holds the origin: no direction is excluded).
"""

from __future__ import annotations

import math

import torch

from pipeline.certify.cone import concretize
from pipeline.certify.keypoint import conv1x1, on_grid, softmax_mean_max, window_crown

HEADING_PLACES = 4  # window places per cell whose first layer is bounded by backward passes (64 hidden units each)
CHUNK = 64  # cells per weighted-mean bound (its sort is `(cells x hidden units x grid)`)


def _linear(lo, hi, w, b):
    mid, rad = (lo + hi) / 2, (hi - lo) / 2
    c, r = mid @ w.T + b, rad @ w.abs().T
    return c - r, c + r


def heading_box(net, static, cone, scores, pixels=None) -> tuple[torch.Tensor, torch.Tensor]:
    """Lower and upper bounds `(N, 2)` (float64) of the head's `(cos θ, sin θ)` outputs over each cell, from the
    cone's window of the last ReLU map and the scores of :func:`.keypoint.keypoint_range`; `pixels` (the
    pixel forms `lo, hi`): the first layer at the `HEADING_PLACES` places of largest upper score also by backward
    passes (the tighter side of each)."""
    w1, b1, w2, b2 = (t.double() for t in net.heading)
    origin, f_lo, f_hi = cone.g
    st_lo, st_hi = conv1x1(w1, static.post_lo[-1].double(), static.post_hi[-1].double())  # (K, H, W)
    win_lo, win_hi = concretize(*conv1x1(w1, f_lo.double(), f_hi.double()))  # (N, K, h, w)
    s_lo, s_hi, window_score = scores
    if pixels is not None:
        c_lo, c_hi = window_crown(net, cone, *pixels, window_score, net.heading[0], HEADING_PLACES)
        win_lo, win_hi = torch.maximum(win_lo, c_lo.double()), torch.minimum(win_hi, c_hi.double())
    out_lo, out_hi = [], []
    for i in range(0, len(win_lo), CHUNK):
        u_lo, u_hi = on_grid(st_lo, st_hi, origin[i:i + CHUNK], win_lo[i:i + CHUNK], win_hi[i:i + CHUNK])
        n, k = u_lo.shape[:2]
        a_lo, a_hi = (t[i:i + CHUNK, None].expand(n, k, -1).reshape(n * k, -1) for t in (s_lo, s_hi))
        m_hi = softmax_mean_max(a_lo, a_hi, u_hi.flatten(2).reshape(n * k, -1)).view(n, k)
        m_lo = -softmax_mean_max(a_lo, a_hi, -u_lo.flatten(2).reshape(n * k, -1)).view(n, k)
        h_lo, h_hi = (torch.relu(t + b1) for t in (m_lo, m_hi))
        lo, hi = _linear(h_lo, h_hi, w2, b2)
        out_lo.append(lo)
        out_hi.append(hi)
    return torch.cat(out_lo), torch.cat(out_hi)


def heading_error(lo: torch.Tensor, hi: torch.Tensor, th0: torch.Tensor, th1: torch.Tensor) -> torch.Tensor:
    """The largest `|wrap(atan2(s, c) - θ)|` (radians, `(N,)`) over `(c, s)` in the box `[lo, hi]` `(N, 2)` and `θ`
    in `[th0, th1]`. A box off the origin sees an arc of directions narrower than `π`, spanned by its corners and
    holding its centre's direction `φ`; relative to the interval's middle the error lies in
    `[φ - mid + min δ - w, φ - mid + max δ + w]` (`δ`: the corners' directions from `φ`, `w`: the half interval),
    and its wrapped size is at most the larger end's size, and at most `π`."""
    lo, hi = lo.double(), hi.double()
    th0, th1 = th0.double(), th1.double()
    holds_origin = (lo <= 0).all(-1) & (hi >= 0).all(-1)
    centre = (lo + hi) / 2
    phi = torch.atan2(centre[:, 1], centre[:, 0])
    cs = torch.stack([torch.stack([lo[:, 0], hi[:, 0], lo[:, 0], hi[:, 0]], 1),
                      torch.stack([lo[:, 1], lo[:, 1], hi[:, 1], hi[:, 1]], 1)], -1)  # (N, 4 corners, 2)
    wrap = lambda a: torch.remainder(a + math.pi, 2 * math.pi) - math.pi  # noqa: E731
    delta = wrap(torch.atan2(cs[..., 1], cs[..., 0]) - phi[:, None])
    mid, half = (th0 + th1) / 2, (th1 - th0) / 2
    base = wrap(phi - mid)
    worst = torch.maximum((base + delta.min(-1).values - half).abs(), (base + delta.max(-1).values + half).abs())
    return torch.where(holds_origin, math.pi, worst.clamp(max=math.pi))
