"""The perception map `l(theta) ≈ p` (SPEC §2): the paper's CNN as a torch module (:class:`PerceptionNet`).

Three Conv(3x3)-ReLU-MaxPool(2x2) blocks, flatten, Dropout(0.5), Linear -> 2 (the paper's block
structure). Filter counts, an optional BatchNorm, an optional hidden layer and the input/target
normalisation are config values (`conf/model/`); `position_head: keypoint` replaces the flattened linear head
by a soft-argmax over the last block's cells (:mod:`pipeline.perception.keypoint`, `conf/model/keypoint.yaml`).
Inputs are uint8 images `(N, H, W, 3)` as stored in the datasets; the module converts them to float channels_last
tensors itself. Outputs are world coordinates: the network predicts positions normalised to `[-1, 1]` over the
arena and the module scales them back. Training adds Lightning's steps on top of it
(`pipeline.train.module.PerceptionMap`); loading and running a map (inference, certificates) needs torch alone.
"""

from __future__ import annotations

import contextlib
import copy
from collections.abc import Sequence

import torch
from torch import nn

from pipeline.errors import ModelError
from pipeline.perception.heading import AttentionHeadingHead, HeadingHead
from pipeline.perception.keypoint import KeypointHead
from pipeline.perception.spec import MapSpec

CHI2_2_95 = 5.991464547107979  # 95% quantile of chi^2 with 2 degrees of freedom: the 95% ellipse of a 2-D Gaussian
LOGVAR_RANGE = (-14.0, 2.0)  # normalised coordinates: sigma from ~1e-3 (0.05 px) to ~3 half-arenas
VAR_HIDDEN = 64  # units of the variance head's hidden layer
THUMB_SCALE = 10.0  # the variance head's thumbnail (input in [-0.5, 0.5]) scaled to the features' magnitude


def thumbnail(x: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """The colour image `x` (N, 3+, H, W, in [-0.5, 0.5]) averaged down to `size`, flattened and scaled: where
    the clouds are, for the variance head (the position's features learn to ignore them)."""
    return nn.functional.adaptive_avg_pool2d(x[:, :3], size).flatten(1).mul_(THUMB_SCALE)


def gaussian_nll(logvar: torch.Tensor, sq_residual: torch.Tensor) -> torch.Tensor:
    """Mean Gaussian negative log-likelihood (constant dropped) of residuals with per-coordinate log variance:
    `0.5 (s + r^2 e^-s)`. For fixed residuals it is minimised at `s = log r^2`, i.e. the head learns the mean
    squared error of the frames that look alike."""
    return 0.5 * (logvar + sq_residual * torch.exp(-logvar)).mean()


def conv_blocks(in_ch: int, filters: Sequence[int], batch_norm: bool) -> nn.Sequential:
    layers: list[nn.Module] = []
    for out_ch in filters:
        layers.append(nn.Conv2d(in_ch, out_ch, 3, padding=1, bias=not batch_norm))
        if batch_norm:
            layers.append(nn.BatchNorm2d(out_ch))
        layers += [nn.ReLU(inplace=True), nn.MaxPool2d(2)]
        in_ch = out_ch
    return nn.Sequential(*layers)


def position_head_layers(flat: int, hidden: int, dropout: float, n_out: int) -> nn.Sequential:
    """Flatten, Dropout, (Linear-ReLU,) Linear -> `n_out` normalised outputs from `flat` features."""
    head: list[nn.Module] = [nn.Flatten(), nn.Dropout(dropout)]
    if hidden:
        head += [nn.Linear(flat, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, n_out)]
    else:
        head += [nn.Linear(flat, n_out)]
    return nn.Sequential(*head)


def variance_head(n_in: int) -> nn.Sequential:
    """The log-variance head (2 outputs), initialised on a forked random stream (everything drawn after it is
    what a map without it draws) and frozen: not a parameter of the position fit (DDP ignores frozen ones)."""
    with torch.random.fork_rng(devices=[]):
        head = nn.Sequential(nn.Linear(n_in, VAR_HIDDEN), nn.ReLU(inplace=True), nn.Linear(VAR_HIDDEN, 2))
    return head.requires_grad_(False)


class PerceptionNet(nn.Module):
    """CNN perception map; `forward(uint8 or float images NHWC) -> (N, 2)` world coordinates, built from its typed
    spec (:class:`pipeline.perception.spec.MapSpec`, checked there; kept as `spec`)."""

    @classmethod
    def of(cls, **fields) -> PerceptionNet:
        """The map of `MapSpec(**fields)` (Python callers, a saved map's hyperparameters)."""
        return cls(MapSpec(**fields))

    def __init__(self, spec: MapSpec):
        super().__init__()
        self.spec = spec
        h, w, _ = (int(s) for s in spec.image_shape)
        self.image_shape = (h, w, 3)
        (x0, x1), (y0, y1) = spec.arena
        self.register_buffer("center", torch.tensor([(x0 + x1) / 2, (y0 + y1) / 2], dtype=torch.float32))
        self.register_buffer("half_range", torch.tensor([(x1 - x0) / 2, (y1 - y0) / 2], dtype=torch.float32))
        # px per world unit (for metrics reported in pixels)
        self.px_per_unit = float(w / (x1 - x0))
        # CoordConv: two extra input channels holding the pixel's column/row in [-0.5, 0.5]
        self.coord_channels = bool(spec.coord_channels)
        self.clamp = bool(spec.clamp)
        if self.coord_channels:
            cols = torch.linspace(-0.5, 0.5, w).view(1, 1, 1, w).expand(1, 1, h, w)
            rows = torch.linspace(-0.5, 0.5, h).view(1, 1, h, 1).expand(1, 1, h, w)
            self.register_buffer("coords", torch.cat([cols, rows], 1).contiguous(), persistent=False)
        filters = [int(f) for f in spec.filters]
        self.features = conv_blocks(3 + 2 * self.coord_channels, filters, spec.batch_norm)
        gh, gw = h >> (len(filters) - 1), w >> (len(filters) - 1)  # the last block's grid before its pooling
        flat = filters[-1] * (gh // 2) * (gw // 2)
        self.uncertainty = spec.uncertainty
        self.pose = spec.outputs == "pose"  # a pose map: (x, y, cos θ, sin θ) from the head, θ = atan2 (SPEC §2)
        self.keypoint = spec.position_head == "keypoint"
        # its (cos θ, sin θ): from the pooled features (`heading_head: pooled`, pipeline.perception.heading), the
        # keypoint's attention-weighted features (`attention`) or two more outputs of the position's head (`flat`)
        heading_cls = {"pooled": HeadingHead, "attention": AttentionHeadingHead}.get(spec.heading_head)
        self.heading_head = heading_cls(filters[-1], int(spec.heading_hidden)) \
            if self.pose and heading_cls is not None else None
        head = KeypointHead(filters[-1], (gh, gw)) if self.keypoint else \
            position_head_layers(flat, spec.hidden, spec.dropout, 4 if self.pose and self.heading_head is None else 2)
        # `uncertainty: gaussian`: a second head on the features predicts the log variance of each normalised
        # coordinate. It is fitted AFTER the position network (`pipeline.train.uncertainty.fit_variance_head`, on
        # the trained network's eval-mode features and errors), so it is frozen during training and never changes
        # the position estimate (initialised on a forked random stream: dropout masks and everything after are
        # those of a map without it)
        # It reads the features and a thumbnail of the image (`thumbnail`: cells of uncertainty_thumbnail px).
        self.var_head = None
        self.thumb_size = (h // int(spec.uncertainty_thumbnail), w // int(spec.uncertainty_thumbnail))
        if spec.uncertainty == "gaussian":
            self.var_head = variance_head(flat + 3 * self.thumb_size[0] * self.thumb_size[1])
        # calibration of the predicted sigma on the validation split (set after training; 1 = raw NLL sigma)
        self.register_buffer("sigma_scale", torch.ones(()))
        self.head = head
        self.to(memory_format=torch.channels_last)

    # --------------------------------------------------------------------------------- forward
    def prepare(self, images: torch.Tensor) -> torch.Tensor:
        """uint8/float NHWC -> float NCHW (channels_last memory), scaled to [-0.5, 0.5]."""
        if images.ndim != 4 or tuple(images.shape[1:]) != self.image_shape:
            raise ModelError(
                f"image shape {tuple(images.shape[1:])} does not match the model's {self.image_shape}"
            )
        x = images.permute(0, 3, 1, 2)  # a view: NCHW shape with channels_last strides
        x = x.to(torch.float32)
        if images.dtype == torch.uint8:
            x = x.mul_(1.0 / 255.0)
        x = x.sub_(0.5)
        if self.coord_channels:
            x = torch.cat([x, self.coords.expand(len(x), -1, -1, -1)], 1)
        return x.contiguous(memory_format=torch.channels_last)

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        """World coordinates `(N, 2)` (a pose map: `(N, 3)`, the heading θ in radians last); with
        `uncertainty: gaussian` followed by the calibrated standard deviation of each position coordinate (world
        units)."""
        return _to_world(self.normalised(images), self.center, self.half_range, self.sigma_scale,
                         self.clamp and not self.training, self.pose)

    def normalised(self, images: torch.Tensor) -> torch.Tensor:
        """Raw head outputs: normalised position (and log variances with `uncertainty: gaussian`)."""
        x = self.prepare(images)
        g, f = self.encode(x)
        z = self.head_outputs(g, f)
        return z if self.var_head is None else torch.cat([z, self.var_head(self.variance_inputs(x, f))], 1)

    def encode(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """The prepared images' last-block activations before (`g`) and after (`f`, the features) its pooling."""
        g = self.features[:-1](x)
        return g, self.features[-1](g)

    def head_outputs(self, g: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        """The normalised position (a pose map: and `(cos θ, sin θ)`) from the activations `g, f` of `encode`."""
        return head_outputs(self.head, self.heading_head, self.keypoint, g, f)

    def position_outputs(self, x: torch.Tensor) -> torch.Tensor:
        """The normalised position `(N, 2)` of the prepared images `x` (what the position loss reads)."""
        return self.head_outputs(*self.encode(x))[:, :2]

    def variance_inputs(self, x: torch.Tensor, f: torch.Tensor) -> torch.Tensor:
        """What the variance head reads: the (detached) features and the thumbnail of the prepared images `x`."""
        return torch.cat([f.detach().flatten(1), thumbnail(x, self.thumb_size)], 1)

    # ------------------------------------------------------------------ what the training fits (pipeline.train.module)
    def targets(self, labels: torch.Tensor) -> torch.Tensor:
        """The head's targets: the position normalised to [-1, 1] over the arena; a pose map adds (cos θ, sin θ)."""
        target = (labels[:, :2] - self.center) / self.half_range
        if self.pose:
            th = labels[:, 2]
            target = torch.cat([target, torch.stack([torch.cos(th), torch.sin(th)], 1)], 1)
        return target

    def flops_per_image(self) -> float:
        """Forward multiply-adds x2 of the conv and linear layers (for GFLOP/s figures)."""
        h, w, _ = self.image_shape
        flops = 0.0
        for m in self.features:
            if isinstance(m, nn.Conv2d):
                flops += 2 * h * w * m.in_channels * m.out_channels * 9
            elif isinstance(m, nn.MaxPool2d):
                h, w = h // 2, w // 2
        head = [] if self.keypoint else [*self.head]
        for m in [*head, *(self.var_head or []), *(self.heading_head.mlp if self.heading_head else [])]:
            if isinstance(m, nn.Linear):
                flops += 2 * m.in_features * m.out_features
        return flops + (self.head.flops() if self.keypoint else 0.0)


def head_outputs(head: nn.Module, heading_head: nn.Module | None, keypoint: bool, g: torch.Tensor,
                 f: torch.Tensor) -> torch.Tensor:
    """The position head (flat: on the pooled features `f`; keypoint: on the pre-pool activations `g`) and a pose
    map's heading head (pooled: on `f`; attention: on `g` with the keypoint's weights), normalised outputs."""
    if keypoint:
        z, attention = head(g)
    else:
        z, attention = head(f), None
    if heading_head is None:
        return z
    return torch.cat([z, heading_head(g, attention) if attention is not None else heading_head(f)], 1)


def _to_world(z: torch.Tensor, center, half_range, sigma_scale, clamp: bool, pose: bool = False) -> torch.Tensor:
    """Head outputs -> world units: positions `(N, 2)` (a pose map: `(N, 3)` with θ = atan2(sin, cos)), then the
    per-coordinate sigmas of the position with an uncertainty head."""
    pos = z[:, :2].clamp(-1.0, 1.0) if clamp else z[:, :2]  # an estimate never leaves the arena the camera sees
    pos = pos * half_range + center
    k = 4 if pose else 2
    if pose:
        pos = torch.cat([pos, torch.atan2(z[:, 3], z[:, 2])[:, None]], 1)
    if z.shape[1] == k:
        return pos
    sigma = torch.exp(0.5 * z[:, k:].clamp(*LOGVAR_RANGE)) * half_range * sigma_scale
    return torch.cat([pos, sigma], 1)


# -------------------------------------------------------------------------------------- inference
def fold(model: PerceptionNet, dtype: torch.dtype = torch.float32,
         grad: bool = False) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """The convolution blocks of `model` as deployed, `(weights, biases)`: block `k`'s 3x3 convolution (padding 1).

    The one folding of both :class:`FoldedPerceptionNet` (inference) and `pipeline.certify.deployed.deployed` (the
    bounds): eval-mode BatchNorm (running statistics, whatever `model.training` is) folded into each convolution;
    block 0 reads images in `[0, 255]`: its weight is `w0[:, :3] / 255` and its bias the per-pixel map `(C, H, W)`
    of the input's `-0.5` centring, the CoordConv channels (zero padding included) and the convolution's bias; the
    other biases are `(C,)`. Folded in the parameters' dtype, then cast to `dtype`. `grad`: differentiable functions
    of the model's parameters (a certified training's bound backpropagates through them), else detached."""
    with contextlib.nullcontext() if grad else torch.no_grad():
        mods, blocks = list(model.features), []
        for i, conv in enumerate(mods):
            if not isinstance(conv, nn.Conv2d):
                continue
            wt = conv.weight
            b = conv.bias if conv.bias is not None else torch.zeros(wt.shape[0], dtype=wt.dtype, device=wt.device)
            bn = mods[i + 1] if i + 1 < len(mods) and isinstance(mods[i + 1], nn.BatchNorm2d) else None
            if bn is not None:
                scale = bn.weight / torch.sqrt(bn.running_var + bn.eps)
                wt, b = wt * scale.view(-1, 1, 1, 1), (b - bn.running_mean) * scale + bn.bias
            blocks.append((wt, b))
        (w0, b0), (h, w, _) = blocks[0], model.image_shape
        conv0 = lambda x, wk: nn.functional.conv2d(x, wk.contiguous(), padding=1)[0]  # noqa: E731 (one layout)
        bias_map = -0.5 * conv0(torch.ones(1, 3, h, w, dtype=w0.dtype, device=w0.device), w0[:, :3])
        if model.coord_channels:
            bias_map = bias_map + conv0(model.coords.to(w0.dtype), w0[:, 3:])
        weights = [w0[:, :3] / 255.0] + [wk for wk, _ in blocks[1:]]
        biases = [bias_map + b0.view(-1, 1, 1)] + [bk for _, bk in blocks[1:]]
        cast = (lambda t: t.to(dtype)) if grad else (lambda t: t.detach().to(dtype))  # noqa: E731
        return [cast(t) for t in weights], [cast(t) for t in biases]


class FoldedPerceptionNet(nn.Module):
    """The eval-mode `PerceptionNet` rewritten for fast inference (same outputs up to float rounding); its
    convolutions are :func:`fold`'s, the very ones the certificate bounds (`pipeline.certify.deployed`).

    - BatchNorm folded into the preceding convolution (one pass instead of three per block);
    - the input scaling (`x / 255 - 0.5`) and the CoordConv channels folded into the first convolution: its
      weights are divided by 255 and a constant per-pixel bias map (the coordinate channels' and the -0.5
      offset's contribution, zero padding included) replaces the extra input channels and the offset;
    - Dropout dropped (identity at inference); activations in channels_last memory.
    `forward(uint8 or float NHWC images in [0, 255]) -> (N, 2)` world coordinates.
    """

    def __init__(self, model: PerceptionNet):
        super().__init__()
        weights, biases = fold(model)
        self.register_buffer("w0", weights[0].contiguous(memory_format=torch.channels_last))
        self.register_buffer("bias_map", biases[0][None].contiguous(memory_format=torch.channels_last))
        self.convs = nn.ModuleList()
        for wk, bk in zip(weights[1:], biases[1:]):
            conv = nn.Conv2d(wk.shape[1], wk.shape[0], 3, padding=1)  # its init draws from the global stream
            with torch.no_grad():
                conv.weight.copy_(wk)
                conv.bias.copy_(bk)
            self.convs.append(conv)
        self.keypoint = model.keypoint
        self.head = copy.deepcopy(model.head) if self.keypoint else \
            nn.Sequential(*[m for m in model.head if not isinstance(m, nn.Dropout)])
        self.heading_head = copy.deepcopy(model.heading_head)
        self.var_head = None if model.var_head is None else nn.Sequential(*model.var_head)
        self.thumb_size = model.thumb_size
        self.register_buffer("center", model.center.detach().clone())
        self.register_buffer("half_range", model.half_range.detach().clone())
        self.register_buffer("sigma_scale", model.sigma_scale.detach().clone())
        self.clamp = model.clamp
        self.pose = model.pose
        self.image_shape = model.image_shape
        self.to(memory_format=torch.channels_last).requires_grad_(False).eval()

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        img = images.permute(0, 3, 1, 2).to(self.w0.dtype)  # NHWC uint8 -> NCHW float, channels_last
        g = nn.functional.relu_(nn.functional.conv2d(img, self.w0, None, padding=1).add_(self.bias_map))
        for conv in self.convs:
            g = nn.functional.relu_(conv(nn.functional.max_pool2d(g, 2)))
        x = nn.functional.max_pool2d(g, 2)  # g: the last block before its pooling; x: the features
        f = x.flatten(1)
        z = head_outputs(self.head, self.heading_head, self.keypoint, g, x)
        if self.var_head is not None:
            thumb = nn.functional.adaptive_avg_pool2d(img, self.thumb_size).flatten(1)  # `thumbnail` of [0, 255]
            thumb = (thumb * (1.0 / 255.0) - 0.5) * THUMB_SCALE
            z = torch.cat([z, self.var_head(torch.cat([f, thumb], 1))], 1)
        return _to_world(z, self.center, self.half_range, self.sigma_scale, self.clamp, self.pose)

