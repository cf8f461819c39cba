"""A PGD attack on the certified bound (SPEC §5.1: a bound is sound or it is not a bound).

Per cell a joint ascent over the position `p = c + h t` (`t in [-1, 1]^2`; a pose cell's `t_θ` too) and every image the relaxation admits
there (the window's pixels anywhere between the renderer's pixel bounds at `t`, rounding and `kappa` included;
every other pixel the static image), through the map as deployed (`FoldedPerceptionNet`), for each of the four
directions `±e_x`, `±e_y`. The largest error it reaches must stay below the cell's certified bound; its share of
the bound says how tight the bound is against an attacker rather than against uniform samples.
"""

from __future__ import annotations

import numpy as np
import torch

from pipeline.certify.renderer import pixel_window
from pipeline.perception.maps import PerceptionMapPredictor
from pipeline.perception.network import FoldedPerceptionNet
from pipeline.progress import progress as progress_bar

PAD = 8  # the window may reach this far outside the image (padding, never read by the network)


def pgd_worst(model, camera, cells, kappa: float = 0.0, steps: int = 25, seed: int = 0, bar=None) -> torch.Tensor:
    """`(N, 4)`: the largest `e_x`, `e_y`, `-e_x`, `-e_y` the attack reaches per cell `cells (N, 4)`; `bar` (a
    progress bar, optional) advances by `N` after each direction's ascent."""
    cells = torch.as_tensor(cells, dtype=torch.float64)
    pw = pixel_window(camera, cells, kappa)
    n, (kr, kc) = len(cells), pw.lo.shape[-2:]
    net = FoldedPerceptionNet(model)
    h, w = camera.height, camera.width
    base = torch.zeros((h + 2 * PAD, w + 2 * PAD, 3), dtype=torch.float64)
    base[PAD:-PAD, PAD:-PAD] = torch.as_tensor(np.asarray(camera.background, dtype=np.float64))
    r = (pw.origin[:, 0, None] + PAD + torch.arange(kr))[:, :, None].expand(n, kr, kc)
    c = (pw.origin[:, 1, None] + PAD + torch.arange(kc))[:, None, :].expand(n, kr, kc)
    centre = (cells[:, [0, 2]] + cells[:, [1, 3]]) / 2
    half = (cells[:, [1, 3]] - cells[:, [0, 2]]) / 2
    found = []
    for sign, j in ((1, 0), (1, 1), (-1, 0), (-1, 1)):
        g = torch.Generator().manual_seed(int(seed))
        t = (torch.rand(n, pw.lo.shape[1] - 1, generator=g, dtype=torch.float64) * 2 - 1).requires_grad_(True)
        th = torch.randn(n, 3, kr, kc, generator=g, dtype=torch.float64).requires_grad_(True)
        opt = torch.optim.Adam([t, th], lr=0.2)
        best = torch.full((n,), -np.inf, dtype=torch.float64)
        for _ in range(steps):
            tt = t.clamp(-1, 1)
            lo, hi = (f[:, 0] + torch.einsum("nschw,ns->nchw", f[:, 1:], tt) for f in (pw.lo.double(), pw.hi.double()))
            win = lo + torch.sigmoid(th) * (hi - lo)  # (n, 3, kr, kc): an admissible window
            img = base.expand(n, *base.shape).clone()
            img[torch.arange(n)[:, None, None], r, c] = win.permute(0, 2, 3, 1)
            e = net(img[:, PAD:-PAD, PAD:-PAD].float())[:, :2].double() - (centre + half * tt[:, :2])
            obj = sign * e[:, j]
            best = torch.maximum(best, obj.detach())
            opt.zero_grad()
            (-obj.sum()).backward()
            opt.step()
        found.append(best)
        if bar is not None:
            bar.update(n)
    return torch.stack(found, 1)


def render_worst(model, camera, cells, rounds: int = 6, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """`(N, 4)`: the largest `e_x`, `e_y`, `-e_x`, `-e_y` that a search over the images the camera really renders
    reaches per cell `cells (N, 4)` (no relaxation, no pixel budget), and `(N, 4, 2)`: the positions reaching them.
    The search: a 3 x 3 grid and a random point per cell, then `rounds` rounds of a pattern search (the best point
    ± the step along each axis, clipped to the cell, the step halved each round), each direction on its own; every
    candidate rendered by the camera and read by the deployed predictor. Beside :func:`pgd_worst` (every image the
    relaxation admits), it says how close the bound comes to an error a rendered frame can have."""
    cells = np.asarray(cells, float)
    n = len(cells)
    deployed = PerceptionMapPredictor(model)  # the folded network, in the loop's CPU chunks
    lo, hi = cells[:, [0, 2]], cells[:, [1, 3]]

    def errors(p: np.ndarray) -> np.ndarray:  # p (n, k, 2) -> signed errors (n, k, 4)
        e = deployed.predict(camera.render(p.reshape(-1, 2)))[:, :2].reshape(p.shape) - p
        return np.concatenate([e, -e], axis=-1)

    g = np.linspace(0.0, 1.0, 3)
    grid = np.stack(np.meshgrid(g, g, indexing="ij"), -1).reshape(-1, 2)
    rng = np.random.default_rng([int(seed), 104729])
    start = np.concatenate([np.broadcast_to(grid, (n, 9, 2)), rng.uniform(0, 1, (n, 1, 2))], axis=1)
    pts = lo[:, None] + start * (hi - lo)[:, None]  # (n, 10, 2)
    e = errors(pts)
    k = e.argmax(axis=1)  # (n, 4)
    best = np.take_along_axis(e, k[:, None], 1)[:, 0]  # (n, 4)
    at = np.take_along_axis(pts, k[..., None], 1)  # (n, 4, 2): the best point per direction
    step = (hi - lo)[:, None] / 4.0
    moves = np.array([[1.0, 0.0], [-1.0, 0.0], [0.0, 1.0], [0.0, -1.0]])
    for _ in range(int(rounds)):
        cand = np.clip(at[:, :, None] + moves[None, None] * step[:, :, None], lo[:, None, None], hi[:, None, None])
        ec = errors(cand.reshape(n, -1, 2)).reshape(n, 4, 4, 4)  # (cell, direction, move, signed error)
        own = ec[:, np.arange(4), :, np.arange(4)].transpose(1, 0, 2)  # (n, direction, move): its own error
        m = own.argmax(axis=2)
        gain = np.take_along_axis(own, m[..., None], 2)[..., 0]
        better = gain > best
        best = np.where(better, gain, best)
        at = np.where(better[..., None], np.take_along_axis(cand, m[..., None, None], 2)[:, :, 0], at)
        step = step / 2.0
    return best, at


def pgd_check(model, camera, cells: np.ndarray, lower: np.ndarray, upper: np.ndarray, kappa: float, n_cells: int,
              steps: int, seed: int, batch: int = 64, progress: bool = False, leaves=None) -> dict:
    """The attack on `n_cells` cells drawn at random (seeded) against their bounds `lower, upper (N, 2)`: how many
    directions it pushes past the bound (`violations`, with the worst as a counterexample), and how far towards
    the bound it gets (`share`: the attack's largest error over the bound, per direction, max and median).
    `leaves`: for split cells, `leaves(cells) -> (boxes, owner)` (:func:`.split.leaf_cells`): each drawn cell is
    attacked on one of its leaves drawn at random (seeded), over that leaf's relaxation, which is what its bound
    holds for; the cell's own relaxation is wider and admits images no leaf's does (such an "excess" is no
    counterexample: found on the arena's border, 2026-12-05). `progress`: the stage's progress
    (:mod:`pipeline.progress`), one ascent per cell and direction."""
    rng = np.random.default_rng([int(seed), 7919])
    pick = np.sort(rng.choice(len(cells), size=min(int(n_cells), len(cells)), replace=False))
    boxes = cells[pick]
    if leaves is not None and len(pick):
        leaf, owner = leaves(cells[pick])
        order = np.argsort(owner, kind="stable")  # each drawn cell's leaves together, the cells in order
        count = np.bincount(owner, minlength=len(pick))
        u = np.random.default_rng([int(seed), 7927]).random(len(pick))  # one leaf per cell, uniformly
        boxes = leaf[order[np.cumsum(count) - count + (u * count).astype(int)]]
    with progress_bar(total=4 * len(pick), desc=f"PGD kappa={float(kappa):g}", unit="ascent",
                      enabled=progress) as bar:
        worst = torch.cat([pgd_worst(model, camera, boxes[s:s + batch], kappa, steps, seed, bar=bar)
                           for s in range(0, len(pick), batch)]).numpy()
    limit = np.concatenate([upper[pick], -lower[pick]], 1)
    excess = worst - limit
    share = worst / np.maximum(np.abs(limit), 1e-9)
    k = np.unravel_index(np.argmax(excess), excess.shape)
    rendered = {}
    if float(kappa) == 0.0 and len(pick):  # the frames the camera renders (the relaxed set holds more images)
        real, _ = render_worst(model, camera, cells[pick], seed=seed)
        real_share = real / np.maximum(np.abs(limit), 1e-9)
        rendered = {"render_violations": int((real > limit).sum()), "render_share_max": float(real_share.max()),
                    "render_share_median": float(np.median(real_share))}
    return {"cells": int(len(pick)), "steps": int(steps), "violations": int((excess > 0).sum()), **rendered,
            "worst_excess": float(excess[k]), "share_max": float(share.max()), "share_median": float(np.median(share)),
            "counterexample": {"cell": cells[pick[k[0]]].tolist(), "leaf": boxes[k[0]].tolist(),
                               "direction": ["+x", "+y", "-x", "-y"][k[1]],
                               "error": float(worst[k])} if excess[k] > 0 else None}
