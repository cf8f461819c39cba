"""Attacks through the camera (SPEC §3.5's Proposition-1 attack, moved from the state into the image).

SPEC §3.5's `adversarial` disturbance adds `e = -eps sign(b(p)) e_b` to the *measured state*. The attacks
here reach the same goal through the image the perception map reads: each frame they push the map's estimate
along a caller-given direction per agent, normally that same `-sign(b(p)) e_b` (:func:`proposition1_direction`),
i.e. across the line `b = 0` behind the obstacle, where the smooth controllers stall and the hybrid one must not.

- :func:`pixel_attack`: an L-infinity bounded perturbation of the rendered uint8 image (`|delta| <= kappa`
  intensity levels per channel and pixel), found by projected gradient ascent (PGD with sign steps) through
  a differentiable network;
- :func:`worst_cloud`: a physical adversary: among `K` cloud layouts drawn from an occlusion level's own ranges
  it picks the one that moves the estimate furthest along the direction (batched rendering and inference, a
  search: no gradients, any `predict` works);
- :class:`AttackedCamera` (in :mod:`pipeline.perception.adversary`, with the attacks' config nodes): the
  measurement hook of the closed loop (`measure(p, idx, frame, rng)`, the signature of
  `pipeline.perception.measure.CameraMeasure`) that renders, attacks, infers and keeps per-image statistics of
  the error the attack induces.

**The network contract** (for :func:`pixel_attack`): any `torch.nn.Module` mapping float NHWC images with
intensities in `[0, 255]` (shape `(N, H, W, 3)`) to world coordinates `(N, >= 2)`; columns 0-1 are the
position (further columns, e.g. an uncertainty head's sigmas, are ignored), and the output must be
differentiable w.r.t. the input.

- `pipeline.perception.network.FoldedPerceptionNet` (the inference network of `PerceptionMapPredictor.net`) satisfies
  it as is: its first convolution reads the float image in `[0, 255]` (the `/255 - 0.5` scaling is folded into
  its weights and bias map), nothing in it is in-place on the input, and although its parameters have
  `requires_grad=False` the gradient w.r.t. the input flows (checked in the tests). A `torch.compile`d
  predictor net works too but recompiles for autograd: pass the eager `FoldedPerceptionNet`.
- `pipeline.perception.network.PerceptionNet` does **not** satisfy it directly: its float input is read in `[0, 1]`
  (only uint8 input is divided by 255), so wrap it: `ScaledInput(model)` (multiplies by 1/255 first; this also
  avoids its in-place `sub_` on a view of a leaf tensor, which autograd refuses).
- In eval mode both clamp the estimate to the arena (`model.clamp`), so the gradient of a coordinate vanishes
  once the estimate sits on the arena's edge (the attack cannot push it further there anyway).

This module takes the network, predictor and camera as arguments; it imports only `pipeline.render`,
`pipeline.errors`, `pipeline.schema` and third-party libraries (the closed-loop hook, `AttackedCamera`, and
`proposition1_direction` live in :mod:`pipeline.perception.adversary`, which imports this module).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from torch import nn

from pipeline.render import CloudSample
from pipeline.schema import Kappa, NonNegative, NonNegativeInt, PositiveInt, checked


# -------------------------------------------------------------------------------------------- result
@dataclass
class AttackResult:
    """What an attack did to a batch of `N` frames.

    - `images`: the attacked uint8 images `(N, H, W, 3)` (what the camera delivers), or None when not kept;
    - `clean`: the estimate `(N, 2)` on the unattacked image (pixel attack: the given image; worst cloud: the
      same scene without clouds);
    - `attacked`: the estimate `(N, 2)` on the attacked image;
    - `direction`: the unit attack direction `(N, 2)` (zero rows where the caller's direction was zero);
    - worst cloud only: `scores (N, K)` (the candidates' error along the direction, `d . (est_k - p)`),
      `chosen (N,)` (the argmax, the first on ties), `clouds` (the chosen `CloudSample`, length N) and
      `candidates` (all `N * K` layouts, agent-major: row `i * K + k`);
    - `extra`: the network's further output columns on the attacked image `(N, C)` (e.g. an uncertainty head's
      sigmas), `(N, 0)` when it has none.

    `induced = attacked - clean` is the estimate error the attack induces; `along` its component along the
    direction, `norm` its length; `error(p)` is the attacked estimate's error w.r.t. the true positions.
    """

    images: np.ndarray | None
    clean: np.ndarray
    attacked: np.ndarray
    direction: np.ndarray
    scores: np.ndarray | None = None
    chosen: np.ndarray | None = None
    clouds: CloudSample | None = None
    candidates: CloudSample | None = None
    extra: np.ndarray | None = None

    @property
    def induced(self) -> np.ndarray:
        return self.attacked - self.clean

    @property
    def along(self) -> np.ndarray:
        """`d . (attacked - clean)` per frame (world units)."""
        return np.einsum("ij,ij->i", self.induced, self.direction)

    @property
    def norm(self) -> np.ndarray:
        """`|attacked - clean|` per frame (world units)."""
        return np.hypot(self.induced[:, 0], self.induced[:, 1])

    def error(self, positions) -> np.ndarray:
        """`attacked - p` `(N, 2)`: the measurement error w.r.t. the true positions."""
        return self.attacked - np.asarray(positions, dtype=np.float64).reshape(-1, 2)

    def __len__(self) -> int:
        return len(self.attacked)


# ----------------------------------------------------------------------------------------- helpers
class ScaledInput(nn.Module):
    """`module(x * scale)`: adapts a network that reads float images in `[0, 1]` (e.g. `PerceptionNet`) to
    the `[0, 255]` contract of :func:`pixel_attack`."""

    def __init__(self, module: nn.Module, scale: float = 1.0 / 255.0):
        super().__init__()
        self.module = module
        self.scale = float(scale)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        return self.module(images * self.scale)


def _unit_directions(direction, n: int) -> np.ndarray:
    d = np.asarray(direction, dtype=np.float64)
    if d.shape == (2,):
        d = np.broadcast_to(d, (n, 2))
    if d.shape != (n, 2):
        raise ValueError(f"direction must be (2,) or ({n}, 2), got {d.shape}")
    if not np.all(np.isfinite(d)):
        raise ValueError("direction has non-finite entries")
    nrm = np.hypot(d[:, 0], d[:, 1])
    return np.where(nrm[:, None] > 0, d / np.where(nrm > 0, nrm, 1.0)[:, None], 0.0)


# ------------------------------------------------------------------------------------ pixel attack
@checked("attack")
def pixel_attack(net: nn.Module, images, direction, *, kappa: Kappa | Sequence[Kappa], steps: NonNegativeInt = 5,
                 step_size: NonNegative | None = None, device="cpu", batch_size: PositiveInt = 512,
                 rng: np.random.Generator | None = None) -> AttackResult:
    """L-infinity PGD on the camera image, pushing the estimate along `direction` (one row per image).

    With `x` the clean image (float, `[0, 255]`), `l = net(.)[:, :2]` the estimate (world units) and
    `d_n = direction_n / |direction_n|`, each image's perturbation solves (approximately)

        max_delta  d_n . l(x_n + delta_n)    s.t.  |delta_n|_inf <= kappa_n,   0 <= x_n + delta_n <= 255,

    the image-space counterpart of SPEC §3.5's Proposition-1 attack `e = -eps sign(b(p)) e_b`: pass
    `direction = -sign(b(p)) e_b` (:func:`proposition1_direction`). `kappa`: one budget, or one per image `(N,)`
    (the camera falsifier's runs, :mod:`pipeline.bracket.camera_falsifier`). The objective is the sum over the
    batch (images are independent, so this is each image's own ascent). Steps: `delta <- P(delta + alpha
    sign(grad))`, `alpha = step_size` (default `2.5 kappa_n / steps`), `P` the projection onto the ball and the
    box. `rng` given: a uniform random start inside the ball (drawn in image order, so batching does not
    change it); None: start at `delta = 0`.

    The result is what a camera delivers: `round(x + delta)` as uint8, re-clipped to
    `[x - floor(kappa_n), x + floor(kappa_n)]` so the budget holds exactly in integer levels. Where the rounded
    image does worse along `d` than the clean one, the clean image is kept (`delta = 0` is feasible), so the
    attack never helps the controller. Runs in eval mode (restored afterwards) in batches of `batch_size` on
    `device`; only the input gets gradients (`torch.autograd.grad`), nothing accumulates in the network's
    parameters. See the module docstring for the network contract.
    """
    steps, batch_size = int(steps), int(batch_size)
    imgs = images.detach().cpu().numpy() if isinstance(images, torch.Tensor) else np.asarray(images)
    if imgs.ndim != 4 or imgs.shape[-1] != 3 or imgs.dtype != np.uint8:
        raise ValueError(f"images must be uint8 (N, H, W, 3), got {imgs.dtype} {imgs.shape}")
    n = len(imgs)
    d = _unit_directions(direction, n)
    kap = np.asarray(kappa, dtype=np.float64)
    if kap.shape not in ((), (n,)):
        raise ValueError(f"kappa must be one budget or one per image ({n},), got shape {kap.shape}")
    kap = np.broadcast_to(kap, (n,)).copy()
    alpha = 2.5 * kap / max(steps, 1) if step_size is None else np.full(n, float(step_size))
    budget = np.floor(kap)  # the integer levels a uint8 image can move within the budget
    start = rng if rng is not None and (kap > 0).any() else None  # a random start (it draws from `rng`)
    idle = not budget.any() or (steps == 0 and rng is None)  # nothing can move: the clean image, no gradient
    dev = torch.device(device)
    out, clean, attacked, extra = np.empty_like(imgs), np.empty((n, 2)), np.empty((n, 2)), None
    was_training = net.training
    net.eval()
    try:
        with torch.inference_mode(False), torch.enable_grad():
            for s in range(0, n, batch_size):
                e = min(s + batch_size, n)
                x0 = torch.from_numpy(np.ascontiguousarray(imgs[s:e])).to(dev).to(torch.float32)
                per_image = [torch.from_numpy(np.ascontiguousarray(v[s:e])).to(dev, torch.float32)
                             for v in (d, kap, alpha, budget)]
                adv, out_clean, out_adv = _pgd_batch(net, x0, *per_image, steps=0 if idle else steps, idle=idle,
                                                     rng=start)
                out[s:e] = adv.to(torch.uint8).cpu().numpy()
                clean[s:e] = out_clean[:, :2].double().cpu().numpy()
                attacked[s:e] = out_adv[:, :2].double().cpu().numpy()
                if extra is None:
                    extra = np.empty((n, out_adv.shape[1] - 2))
                extra[s:e] = out_adv[:, 2:].double().cpu().numpy()
    finally:
        net.train(was_training)
    return AttackResult(out, clean, attacked, d, extra=np.empty((0, 0)) if extra is None else extra)


def _pgd_batch(net: nn.Module, x0, db, kappa, alpha, budget, *, steps: int, idle: bool, rng):
    """One batch of :func:`pixel_attack` (gradients enabled by the caller), the budget `kappa`, step `alpha` and
    integer `budget` per image `(n,)`: the projected sign-gradient steps from the clean or (`rng` given) a random
    start, then the camera's rounding and the keep-the-clean-image rule. Returns `(attacked images, clean
    outputs, attacked outputs)` as tensors."""
    kappa, alpha, budget = (v.view(-1, 1, 1, 1) for v in (kappa, alpha, budget))
    out_clean = None
    if rng is not None:
        u = rng.random(tuple(x0.shape))  # float64: one 64-bit draw each, batch-invariant
        delta = torch.from_numpy(u).to(x0.device, torch.float32).mul_(2 * kappa).sub_(kappa)
        delta = (x0 + delta).clamp_(0.0, 255.0).sub_(x0)
    else:
        delta = torch.zeros_like(x0)
    for _ in range(steps):
        delta.requires_grad_(True)
        full = net(x0 + delta)
        if out_clean is None and rng is None:  # the first step starts at the clean image
            out_clean = full.detach()
        (grad,) = torch.autograd.grad((full[:, :2] * db).sum(), delta)
        with torch.no_grad():
            delta = torch.clamp(delta.detach() + alpha * grad.sign(), -kappa, kappa)
            delta = (x0 + delta).clamp_(0.0, 255.0).sub_(x0)
    with torch.no_grad():
        if out_clean is None:
            out_clean = net(x0)
        if idle:
            adv, out_adv = x0, out_clean.clone()
        else:
            adv = torch.round(x0 + delta)
            adv = torch.minimum(torch.maximum(adv, x0 - budget), x0 + budget).clamp_(0.0, 255.0)
            out_adv = net(adv)
        worse = ((out_adv[:, :2] - out_clean[:, :2]) * db).sum(1) < 0
        adv[worse] = x0[worse]
        out_adv[worse] = out_clean[worse]
    return adv, out_clean, out_adv


# ------------------------------------------------------------------------------------- worst cloud
@checked("attack")
def worst_cloud(camera, occlusion, positions, direction, predict: Callable, *, candidates: PositiveInt = 16,
                rng: np.random.Generator, follower=None, chunk: PositiveInt = 4096, always: bool = True,
                keep_images: bool = True) -> AttackResult:
    """The worst of `candidates` cloud layouts per agent: a physical adversary searching the level's own clouds.

    For each agent `i` at true position `p_i`, `K = candidates` layouts are drawn with `occlusion.sample(N * K,
    rng, camera.shape)` (agent-major: row `i * K + k`), so the adversary's budget is the level itself: its
    bank of fields (number, size, opacity and shape of blobs from the level's ranges) and their cyclic shifts
    (where the clouds lie). `always=True` (default): every candidate's `mask` is set, i.e. the adversary always
    gets to place a cloud when the level allows one at all (`occlusion.active`, probability > 0; a level with
    probability `p` puts clouds on a share `p` of the images, and the worst case is the adversary choosing
    those frames); `always=False` keeps the level's own mask draws (a candidate may then be a clear image).
    An inactive level yields clear images only.

    All `N * K` images are rendered with `camera.render(..., clouds=...)` and predicted with `predict(images)
    -> (n, 2)` in chunks of `chunk` images (memory `chunk * H * W * 3` bytes); per agent the candidate with the
    largest `d_i . (est_k - p_i)` is kept (`d_i` the unit direction; first on ties). `clean` is the estimate of
    the same scene without clouds, `attacked` the chosen candidate's; the chosen images are re-rendered
    (bytes identical) when `keep_images`. Same inputs and rng state -> same result, whatever `chunk`.
    """
    k, chunk = int(candidates), int(chunk)
    p = np.asarray(positions, dtype=np.float64).reshape(-1, 2)
    n = len(p)
    d = _unit_directions(direction, n)
    fol = None if follower is None else np.asarray(follower, dtype=np.float64).reshape(-1, 2)
    if fol is not None and len(fol) != n:
        raise ValueError(f"follower has {len(fol)} rows, positions {n}")
    active = occlusion is not None and occlusion.active
    if active:
        cand = occlusion.sample(n * k, rng, camera.shape)
        if always:
            cand = CloudSample(np.ones(n * k, dtype=bool), cand.field, cand.dy, cand.dx)
    else:
        z = np.zeros(n * k, dtype=np.int64)
        cand = CloudSample(np.zeros(n * k, dtype=bool), z, z, z)
    est, extra = np.empty((n * k, 2)), None
    agent = np.repeat(np.arange(n), k)
    for s in range(0, n * k, chunk):
        e = min(s + chunk, n * k)
        rows = agent[s:e]
        imgs = camera.render(p[rows], None if fol is None else fol[rows], occlusion=occlusion if active else None,
                             clouds=cand[s:e] if active else None)
        rows = np.asarray(predict(imgs), dtype=np.float64)
        if extra is None:
            extra = np.empty((n * k, rows.shape[1] - 2))
        est[s:e], extra[s:e] = rows[:, :2], rows[:, 2:]
    scores = np.einsum("ikj,ij->ik", est.reshape(n, k, 2) - p[:, None, :], d)
    chosen = np.argmax(scores, axis=1)
    pick = np.arange(n) * k + chosen
    clouds = cand[pick]
    clean = np.empty((n, 2))
    images = np.empty((n, camera.height, camera.width, 3), dtype=np.uint8) if keep_images else None
    for s in range(0, n, chunk):
        e = min(s + chunk, n)
        f = None if fol is None else fol[s:e]
        clean[s:e] = np.asarray(predict(camera.render(p[s:e], f)), dtype=np.float64)[:, :2]
        if keep_images:
            camera.render(p[s:e], f, occlusion=occlusion if active else None,
                          clouds=clouds[s:e] if active else None, out=images[s:e])
    return AttackResult(images, clean, est[pick], d, scores=scores, chosen=chosen, clouds=clouds,
                        candidates=cand, extra=np.empty((n, 0)) if extra is None else extra[pick])
