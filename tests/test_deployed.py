"""One folding (issue 47): the map the certificate bounds (`pipeline.certify.deployed.deployed`) is the map inference
runs (`FoldedPerceptionNet`), both built by `pipeline.perception.network.fold`."""

import pytest
import torch
from torch import nn
from torch.nn import functional as F

from pipeline.certify.deployed import deployed
from pipeline.perception.network import FoldedPerceptionNet, fold
from pipeline.train.module import PerceptionMap

pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


def _map(seed: int, **kw) -> PerceptionMap:
    """A small map whose BatchNorm statistics are not the identity (so that folding them matters), eval mode."""
    torch.manual_seed(seed)
    m = PerceptionMap.of(filters=(4, 8, 8), uncertainty="none", clamp=False, **kw)
    with torch.no_grad():
        for bn in (x for x in m.features if isinstance(x, nn.BatchNorm2d)):
            bn.running_mean.normal_(0.0, 0.3)
            bn.running_var.uniform_(0.5, 1.5)
            bn.weight.uniform_(0.5, 1.5)
            bn.bias.normal_(0.0, 0.2)
        m.features[0].weight.mul_(6.0)  # ReLUs that switch with the image
    return m.eval()


def _position(net, images: torch.Tensor) -> torch.Tensor:
    """The position `(N, 2)` a `Deployed` flat-head map reads off float NHWC images in `[0, 255]`."""
    x = images.permute(0, 3, 1, 2)
    for k, (w, b) in enumerate(zip(net.weights, net.biases)):
        x = F.max_pool2d(F.relu(F.conv2d(x, w, padding=1) + (b if k == 0 else b.view(-1, 1, 1))), 2)
    z = torch.einsum("ochw,nchw->no", net.head_w, x) + net.head_b
    return (z.clamp(-1.0, 1.0) if net.clamp else z) * net.half_range + net.center


@pytest.mark.parametrize(("batch_norm", "coord_channels"), [(True, True), (False, False), (True, False)])
def test_the_certified_map_is_the_inference_network(batch_norm, coord_channels):
    m = _map(1, batch_norm=batch_norm, coord_channels=coord_channels)
    images = torch.randint(0, 256, (8, *m.image_shape), generator=torch.Generator().manual_seed(2),
                           dtype=torch.uint8)
    with torch.no_grad():
        want = FoldedPerceptionNet(m)(images)
        got = _position(deployed(m), images.float())
    torch.testing.assert_close(got, want, rtol=1e-5, atol=1e-5)
    assert (want - m(images)).abs().max() < 1e-3  # and both are the map (up to the folding's rounding)


@pytest.mark.parametrize("kw", [{}, {"batch_norm": False, "coord_channels": False},
                                {"position_head": "keypoint", "outputs": "pose", "heading_head": "attention"}])
def test_one_folding_bit_for_bit(kw):
    """The certificate's weights and bias map are the inference network's, bit for bit (no second folding)."""
    m = _map(3, **kw)
    net, inf = deployed(m), FoldedPerceptionNet(m)
    assert torch.equal(net.weights[0], inf.w0) and torch.equal(net.biases[0], inf.bias_map[0])
    for (w, b), conv in zip(zip(net.weights[1:], net.biases[1:]), inf.convs, strict=True):
        assert torch.equal(w, conv.weight) and torch.equal(b, conv.bias)


def test_the_folding_is_differentiable_for_the_bounds_and_detached_for_inference():
    m = _map(4)
    weights, biases = fold(m, grad=True)
    assert all(t.requires_grad for t in weights + biases)
    (weights[1].sum() + biases[0].sum()).backward()
    assert m.features[0].weight.grad is not None and m.features[5].running_mean.grad is None
    assert not any(t.requires_grad for t in sum(fold(m), []))
    w64, b64 = fold(m, torch.float64)  # folded in the parameters' dtype, then cast
    assert all(torch.equal(a, b.double()) for a, b in zip(w64 + b64, sum(fold(m), [])))
