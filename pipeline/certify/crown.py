"""The backward (CROWN-style) pass: linear lower bounds of `Λ · features` in `t`, through the relaxations the
forward pass chose (:mod:`.cone`), back to the renderer's pixel forms (SPEC §5.2).

Going backward, a positive coefficient takes each relaxation's lower side and a negative one its upper side;
static neurons (the halo, the aligned pooling windows' static members) are constants (intervals under `kappa`:
the side the coefficient's sign asks for); the rounding and `kappa` terms enter at the pixels, where they are
concretised exactly for the final linear function (instead of layer by layer as in the forward pass).
"""

from __future__ import annotations

import torch
from torch.nn import functional as F

from pipeline.certify.cone import Block, Cone, extract, place


def _static(lam: torch.Tensor, lo: torch.Tensor, hi: torch.Tensor) -> torch.Tensor:
    """Lower bound of `lam · x` over `x in [lo, hi]` per spec: `(N, P, ...)` with `(N, ...)` -> `(N, P)`."""
    return (lam.clamp(min=0) * lo[:, None] + lam.clamp(max=0) * hi[:, None]).flatten(2).sum(-1)


def _back_block(rec: Block, weight: torch.Tensor, lam: torch.Tensor, const: torch.Tensor, level0: bool):
    """`lam (N, P, C', pr, pc)` on block `rec`'s pooled output -> on its changed input window."""
    n, p = lam.shape[:2]
    lam = lam * rec.mask[:, None]
    pos, neg = lam.clamp(min=0), lam.clamp(max=0)
    free = (neg * (~rec.dominant[:, None]))[:, :, None]  # (N, P, 1, C', pr, pc): onto the plane over the members
    const = const + (free * rec.umax[:, None]).flatten(3).sum(-1)
    to_member = pos + neg * rec.dominant[:, None]
    onehot = F.one_hot(rec.member, 4).to(lam.dtype)[:, None]  # (N, 1, C', pr, pc, 4)
    members = to_member[..., None] * onehot
    pr, pc = members.shape[-3:-1]
    aligned = members.unflatten(-1, (2, 2)).movedim(-2, -3).reshape(n, p, -1, 2 * pr, 2 * pc)
    osize = (rec.size[0] + 2, rec.size[1] + 2)
    changed = extract(aligned, rec.parity, osize)
    static_lam = place(torch.zeros_like(changed), aligned, rec.parity)  # the window's coefficients moved to `changed`
    const = _add(const, _static(static_lam, rec.pool_lo, rec.pool_hi))
    return _back_relu_conv(rec, weight, changed, const, level0)


def _back_relu_conv(rec: Block, weight: torch.Tensor, changed: torch.Tensor, const: torch.Tensor, level0: bool):
    """`changed (N, P, C', h + 2, w + 2)` on block `rec`'s ReLU outputs (its pre-activation window) -> on its
    changed input window."""
    n, p = changed.shape[:2]
    # ReLU: lower side lam * y for positive coefficients, upper slope * y + shift for negative ones
    const = _add(const, (changed.clamp(max=0) * rec.shift[:, None]).flatten(2).sum(-1))
    lam_y = torch.where(changed >= 0, changed * rec.lam[:, None], changed * rec.slope[:, None])
    bias = rec.bias[:, None] if level0 else rec.bias.view(1, 1, -1, 1, 1)
    const = _add(const, (lam_y * bias).flatten(2).sum(-1))
    lam_x = F.conv_transpose2d(lam_y.flatten(0, 1), weight).unflatten(0, (n, p))
    h, w = rec.size
    inner = lam_x[..., 2:2 + h, 2:2 + w]
    ring = lam_x.clone()
    ring[..., 2:2 + h, 2:2 + w] = 0
    const = _add(const, _static(ring, rec.halo_lo, rec.halo_hi))
    return inner, const


def _add(form: torch.Tensor, value: torch.Tensor) -> torch.Tensor:
    """`form (N, P, S) + value (N, P)` on the constant slot."""
    return torch.cat([form[..., :1] + value[..., None], form[..., 1:]], -1)


def backward(net, cone: Cone, lam: torch.Tensor, const: torch.Tensor, pix_lo: torch.Tensor, pix_hi: torch.Tensor):
    """Lower-bound forms `(N, P, S)` of `lam · features + const` (`lam (N, P, C, pr, pc)` on the cone's feature
    window, `const (N, P)`), through every block to the pixel forms `pix_lo, pix_hi (N, S, 3, Kr, Kc)`."""
    const = torch.cat([const[..., None], const.new_zeros((*const.shape, pix_lo.shape[1] - 1))], -1)  # a form
    for k in reversed(range(net.levels)):
        lam, const = _back_block(cone.blocks[k], net.weights[k], lam, const, k == 0)
    # pixels: lam (N, P, 3, Kr, Kc); forms (N, S, 3, Kr, Kc)
    form = (lam.clamp(min=0)[:, :, None] * pix_lo[:, None] + lam.clamp(max=0)[:, :, None] * pix_hi[:, None])
    return form.flatten(3).sum(-1) + const  # (N, P, S)


def backward_from_relu(net, cone: Cone, lam: torch.Tensor, const: torch.Tensor, pix_lo: torch.Tensor,
                       pix_hi: torch.Tensor):
    """As :func:`backward`, from `lam (N, P, C, h, w)` on the last block's ReLU window before its pooling (`cone.g`,
    what a keypoint head reads)."""
    const = torch.cat([const[..., None], const.new_zeros((*const.shape, pix_lo.shape[1] - 1))], -1)
    last = net.levels - 1
    lam, const = _back_relu_conv(cone.blocks[last], net.weights[last], lam, const, last == 0)
    for k in reversed(range(last)):
        lam, const = _back_block(cone.blocks[k], net.weights[k], lam, const, k == 0)
    form = (lam.clamp(min=0)[:, :, None] * pix_lo[:, None] + lam.clamp(max=0)[:, :, None] * pix_hi[:, None])
    return form.flatten(3).sum(-1) + const
