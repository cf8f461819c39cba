"""Forward bounds through the cone of changing activations (SPEC §5.1-5.2).

Only the pixels the robot can touch from a cell change (:mod:`.renderer`); every activation outside their
cone equals the static image's (:func:`.deployed.static_pass`). Per cell and per block the cone lives in a
window of fixed size at a per-cell origin, so a batch of cells is one tensor:

- block `k`'s changed input window (origin `o`, size `n`) with a halo of 2 of static values is convolved
  (valid) to the pre-activation window (origin `o - 1`, size `n + 2`): the only pre-activations that change;
- ReLU relaxed per neuron from the concrete bounds (upper: the chord; lower: slope 1 or 0, whichever keeps
  more of the range; IBP: 0);
- 2x2 max-pooling (floor mode) on the window widened to even alignment with static neurons: lower bound the
  member with the largest lower bound; upper bound that member when it dominates (its lower bound above every
  other member's upper bound), else the largest upper bound; pooled neurons outside the next grid are zero
  (the next convolution's padding, or rows floor mode drops).

The bounds are forms (:mod:`.renderer`): `(N, S, C, h, w)`, slot 0 the constant, slots 1-2 the coefficients of
`t`. Each block's relaxation is kept (:class:`Block`) for the backward pass (:mod:`.crown`).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch.nn import functional as F

from pipeline.certify.deployed import Deployed, Static

MARGIN = 24  # zero padding of the static maps (windows of cells at the arena's edge reach outside the image)


def concretize(lo: torch.Tensor, hi: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The forms' ranges over `t in [-1, 1]^2`: `(N, S, ...) -> (N, ...)`."""
    return lo[:, 0] - lo[:, 1:].abs().sum(1), hi[:, 0] + hi[:, 1:].abs().sum(1)


def gather(padded: torch.Tensor, origin: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Windows `(N, C, h, w)` at per-cell `origin (N, 2)` of a map `(C, H + 2M, W + 2M)` padded by MARGIN."""
    h, w = size
    r = origin[:, 0, None] + MARGIN + torch.arange(h, device=origin.device)
    c = origin[:, 1, None] + MARGIN + torch.arange(w, device=origin.device)
    if int(r.min()) < 0 or int(c.min()) < 0 or int(r.max()) >= padded.shape[1] or int(c.max()) >= padded.shape[2]:
        raise ValueError("a cell's window leaves the padded image: certify cells inside the arena")
    return padded[:, r[:, :, None], c[:, None, :]].movedim(0, 1)


def pad(t: torch.Tensor) -> torch.Tensor:
    return F.pad(t, (MARGIN,) * 4)


def as_form(value: torch.Tensor, slots: int) -> torch.Tensor:
    """A constant `(N, ...)` as a form `(N, S, ...)`."""
    return torch.cat([value[:, None], value.new_zeros((value.shape[0], slots - 1, *value.shape[1:]))], 1)


def place(inner: torch.Tensor, outer: torch.Tensor, offset: torch.Tensor) -> torch.Tensor:
    """`outer (N, ..., H, W)` with `inner (N, ..., h, w)` written at the per-cell `offset (N, 2)` in {0, 1}^2
    (`H - h >= 1`, `W - w >= 1`): one slice per offset, the cells of each written together."""
    dtype = torch.promote_types(inner.dtype, outer.dtype)
    out = outer.to(dtype).expand(len(inner), *outer.shape[1:]).clone()
    h, w = inner.shape[-2:]
    code = offset[:, 0] * 2 + offset[:, 1]
    for k in range(4):
        rows = torch.nonzero(code == k).flatten()
        if rows.numel():
            r, c = divmod(k, 2)
            out[rows, ..., r:r + h, c:c + w] = inner[rows].to(dtype)
    return out


def extract(outer: torch.Tensor, offset: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """The inverse of :func:`place`: the `size` window of `outer` at the per-cell `offset`."""
    h, w = size
    sel = lambda axis: (offset[:, axis] == 1).view(-1, *[1] * (outer.dim() - 1))  # noqa: E731
    rows = torch.where(sel(0), outer[..., 1:h + 1, :], outer[..., :h, :])
    return torch.where(sel(1), rows[..., :, 1:w + 1], rows[..., :, :w])


@dataclass
class Block:
    """One block's cone and relaxation (what the backward pass needs)."""

    origin: torch.Tensor  # (N, 2): the changed input window's origin; size `size`
    size: tuple[int, int]
    halo_lo: torch.Tensor  # (N, C, h + 4, w + 4): static input values around it
    halo_hi: torch.Tensor
    bias: torch.Tensor  # (N, C', h + 2, w + 2) (block 0's bias map) or (C',)
    lam: torch.Tensor  # ReLU lower slope (N, C', h + 2, w + 2)
    slope: torch.Tensor  # ReLU upper slope
    shift: torch.Tensor  # ReLU upper intercept
    parity: torch.Tensor  # (N, 2): offset of the pre-activation window in the aligned pooling window
    pool_lo: torch.Tensor  # (N, C', m, m'): static values of the aligned window
    pool_hi: torch.Tensor
    member: torch.Tensor  # (N, C', pr, pc) in 0..3: the member with the largest lower bound
    dominant: torch.Tensor  # (N, C', pr, pc) bool
    umax: torch.Tensor  # (N, S, C', pr, pc): the upper form of a pool that no member dominates
    mask: torch.Tensor  # (1 or N, 1, pr, pc): pooled neurons inside the next grid


@dataclass
class Cone:
    """The forward pass: per-block records and the pooled features' window (origin, forms)."""

    blocks: list[Block]
    origin: torch.Tensor
    lo: torch.Tensor
    hi: torch.Tensor
    g: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None  # the last block's ReLU window before its
    # pooling (what a keypoint head reads): its origin `(N, 2)` and forms `(N, S, C, h, w)`


def _relu(lo, hi, ibp: bool):
    lb, ub = concretize(lo, hi)
    unstable = (lb < 0) & (ub > 0)
    slope = torch.where(ub <= 0, 0.0, torch.where(lb >= 0, 1.0, ub / torch.where(unstable, ub - lb, 1.0)))
    shift = torch.where(unstable, -slope * lb, 0.0)
    keep = torch.zeros_like(lb) if ibp else (ub > -lb).to(lb.dtype)
    lam = torch.where(lb >= 0, 1.0, torch.where(ub <= 0, 0.0, keep))
    post_hi = hi * slope[:, None]
    post_hi = torch.cat([post_hi[:, :1] + shift[:, None], post_hi[:, 1:]], 1)
    return lo * lam[:, None], post_hi, lam, slope, shift


def _pool(lo, hi):
    """2x2 max-pool of forms `(N, S, C, 2p, 2q)` (see the module doc)."""
    n, s, c, h, w = lo.shape
    split = lambda t: t.reshape(*t.shape[:-2], h // 2, 2, w // 2, 2).movedim(-3, -2).flatten(-2)  # noqa: E731
    flo, fhi = split(lo), split(hi)  # (N, S, C, p, q, 4)
    lv, uv = concretize(flo, fhi)
    member = lv.argmax(-1)
    lbest = lv.gather(-1, member[..., None])[..., 0]
    others = uv.masked_fill(F.one_hot(member, 4).bool(), float("-inf")).amax(-1)
    dominant = lbest >= others
    umax = _max_plane(fhi, uv.amax(-1))
    idx = member[:, None, ..., None].expand(n, s, *member.shape[1:], 1)
    plo = flo.gather(-1, idx)[..., 0]
    phi = torch.where(dominant[:, None], fhi.gather(-1, idx)[..., 0], umax)
    return plo, phi, member, dominant, umax


def _max_plane(fhi: torch.Tensor, umax: torch.Tensor) -> torch.Tensor:
    """An upper form of `max_i U_i(t)` (members' upper forms `fhi (N, S, C, p, q, 4)`): the max is convex in `t`, so
    a plane above it at the box's corners is above it on the whole box; the plane fitted to the corner values
    (least squares on the cube's corners: their mean and the means of value times sign) and lifted by the largest
    residual, or the constant `umax` where that is lower on average (and in IBP)."""
    s = fhi.shape[1]
    if s == 1:
        return umax[:, None]
    corners = torch.cartesian_prod(*[torch.tensor([-1.0, 1.0], dtype=fhi.dtype, device=fhi.device)] * (s - 1))
    corners = corners.view(-1, s - 1)  # (2^(S-1), S-1)
    vals = fhi[:, 0, ..., None] + torch.einsum("nscpqm,ks->ncpqmk", fhi[:, 1:], corners)
    vals = vals.amax(-2)  # (N, C, p, q, corners): the max over members at each corner
    a = vals.mean(-1)
    b = torch.einsum("ncpqk,ks->ncpqs", vals, corners) / len(corners)
    a = a + (vals - a[..., None] - torch.einsum("ncpqs,ks->ncpqk", b, corners)).amax(-1)
    plane = torch.cat([a[:, None], b.movedim(-1, 1)], 1)
    return torch.where((a <= umax)[:, None], plane, as_form(umax, s))


def _block(net: Deployed, static_padded, k: int, origin, lo, hi, ibp: bool):
    """Block `k` on the changed input window `origin`, forms `lo, hi`: its record and the pooled window."""
    s = lo.shape[1]
    size = tuple(lo.shape[-2:])
    in_lo, in_hi, post_lo, post_hi = static_padded
    halo = (size[0] + 4, size[1] + 4)
    h_lo, h_hi = gather(in_lo[k], origin - 2, halo), gather(in_hi[k], origin - 2, halo)
    x_lo, x_hi = as_form(h_lo, s).clone(), as_form(h_hi, s).clone()
    x_lo[..., 2:2 + size[0], 2:2 + size[1]] = lo
    x_hi[..., 2:2 + size[0], 2:2 + size[1]] = hi
    w = net.weights[k]
    mid, rad = ((x_lo + x_hi) / 2).flatten(0, 1), ((x_hi - x_lo) / 2).flatten(0, 1)
    cm, cr = F.conv2d(mid, w), F.conv2d(rad, w.abs())
    y_lo, y_hi = (t.unflatten(0, (-1, s)) for t in (cm - cr, cm + cr))
    out_origin = origin - 1
    osize = (size[0] + 2, size[1] + 2)
    bias = gather(pad(net.biases[0]), out_origin, osize) if k == 0 else net.biases[k]
    b = bias[:, None] if k == 0 else bias.view(1, 1, -1, 1, 1)
    y_lo = torch.cat([y_lo[:, :1] + b, y_lo[:, 1:]], 1)
    y_hi = torch.cat([y_hi[:, :1] + b, y_hi[:, 1:]], 1)
    r_lo, r_hi, lam, slope, shift = _relu(y_lo, y_hi, ibp)
    parity = out_origin % 2
    aligned = out_origin - parity
    asize = (2 * (osize[0] // 2) + 2, 2 * (osize[1] // 2) + 2)
    a_lo, a_hi = gather(post_lo[k], aligned, asize), gather(post_hi[k], aligned, asize)
    w_lo = place(r_lo, as_form(a_lo, s), parity)
    w_hi = place(r_hi, as_form(a_hi, s), parity)
    p_lo, p_hi, member, dominant, umax = _pool(w_lo, w_hi)
    p_origin = aligned // 2
    grid = net.grids[k + 1]
    pr = p_origin[:, 0, None] + torch.arange(p_lo.shape[-2])
    pc = p_origin[:, 1, None] + torch.arange(p_lo.shape[-1])
    mask = (((pr >= 0) & (pr < grid[0]))[:, :, None] & ((pc >= 0) & (pc < grid[1]))[:, None, :])[:, None]
    mask = mask.to(p_lo.dtype)
    rec = Block(origin, size, h_lo, h_hi, bias, lam, slope, shift, parity, a_lo, a_hi, member, dominant, umax, mask)
    return rec, p_origin, p_lo * mask[:, None], p_hi * mask[:, None], (out_origin, r_lo, r_hi)


def forward(net: Deployed, static: Static, origin: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor,
            ibp: bool = False) -> Cone:
    """Forms of the pixels `lo, hi (N, S, 3, Kr, Kc)` at window `origin (N, 2)` through every block."""
    padded = tuple([pad(t) for t in maps] for maps in (static.inputs_lo, static.inputs_hi, static.post_lo,
                                                          static.post_hi))
    blocks, g = [], None
    for k in range(net.levels):
        rec, origin, lo, hi, g = _block(net, padded, k, origin, lo, hi, ibp)
        blocks.append(rec)
    return Cone(blocks, origin, lo, hi, g)
