"""The keypoint position head (`model.position_head: keypoint`, pipeline/perception/keypoint.py): its geometry (a
cell's centre and offset in the arena's coordinates), the folded inference network, the heading read at the
keypoint, its cross-field rule, and that it learns sub-pixel positions where the flat head does not yet."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.cli import compose
from pipeline.errors import ConfigError

torch = pytest.importorskip("torch")


@settings(max_examples=60, deadline=None)
@given(i=st.integers(0, 14), j=st.integers(0, 24), dx=st.floats(-0.5, 0.5), dy=st.floats(-0.5, 0.5))
def test_a_peaked_attention_reads_its_cells_centre_plus_the_offset_in_arena_coordinates(i, j, dx, dy):
    """A cell of the 15 x 25 grid (4 px cells of the 60 x 100 image) holds the pixels u in [4j, 4j + 4) (x = -50 + u)
    and v in [4i, 4i + 4) (y = 30 - v); its centre plus the offset (in cells, dy down the image) is the position."""
    from pipeline.perception.keypoint import KeypointHead

    head = KeypointHead(3, (15, 25))
    with torch.no_grad():
        head.score.weight.zero_()
        head.score.bias.zero_()
        head.score.weight[0, 0] = 100.0  # score: channel 0; dx: channel 1; dy: channel 2
        head.score.weight[1, 1] = 1.0
        head.score.weight[2, 2] = 1.0
    g = torch.zeros(1, 3, 15, 25)
    g[0, :, i, j] = torch.tensor([1.0, dx, dy])
    with torch.no_grad():
        z, a = head(g)
    assert a.shape == (1, 1, 15, 25) and float(a[0, 0, i, j]) > 0.999
    x_world = -50.0 + 4.0 * (j + 0.5 + dx)
    y_world = 30.0 - 4.0 * (i + 0.5 + dy)
    expect = [(x_world + 50.0) / 50.0 - 1.0, (y_world + 30.0) / 30.0 - 1.0]  # the map's normalised targets
    np.testing.assert_allclose(z[0].numpy(), expect, atol=2e-4)


def _model(**kw):
    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    model = PerceptionMap.of(position_head="keypoint", filters=[4, 8, 8], **kw)
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):  # non-trivial running statistics
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
    return model.eval()


@pytest.mark.parametrize("kw", [{"uncertainty": "none"}, {"uncertainty": "gaussian"},
                                {"outputs": "pose", "heading_head": "attention", "uncertainty": "none"}],
                         ids=["position", "with-uncertainty", "pose"])
def test_folded_keypoint_map_matches_the_module(kw):
    from pipeline.perception.maps import PerceptionMapPredictor

    model = _model(**kw)
    images = np.random.default_rng(1).integers(0, 256, (24, 60, 100, 3), dtype=np.uint8)
    with torch.inference_mode():
        ref = model(torch.from_numpy(images)).double().numpy()
    out = PerceptionMapPredictor(model, batch_size=8)._run(images)
    assert out.shape == ref.shape
    np.testing.assert_allclose(out, ref, atol=2e-3, rtol=1e-4)


def test_keypoint_map_is_differentiable_for_the_pixel_attack():
    """The attacks' network contract (pipeline/perception/attacks.py): the folded network's position has a
    gradient w.r.t. the float image."""
    from pipeline.perception.network import FoldedPerceptionNet

    net = FoldedPerceptionNet(_model(uncertainty="none"))
    x = torch.from_numpy(np.random.default_rng(2).uniform(0, 255, (2, 60, 100, 3)).astype(np.float32))
    x.requires_grad_(True)
    net(x)[:, :2].sum().backward()
    assert x.grad is not None and float(x.grad.abs().sum()) > 0


@pytest.mark.parametrize("position,heading", [("keypoint", "pooled"), ("keypoint", "flat"), ("flat", "attention")])
def test_the_heading_head_must_match_the_position_head(position, heading):
    from pipeline.train.module import PerceptionMap

    with pytest.raises(ConfigError, match="model.heading_head"):
        PerceptionMap.of(outputs="pose", position_head=position, heading_head=heading, uncertainty="none")
    PerceptionMap.of(outputs="position", position_head=position, heading_head=heading)  # a position map reads none


def test_the_pose_and_keypoint_configs_compose_to_keypoint_maps():
    from pipeline.config import build
    from pipeline.train.module import PerceptionMap

    for name, pose in (("keypoint", False), ("pose", True)):
        model = PerceptionMap(build(compose("train", ["data=unicycle", f"model={name}"]).model, "model"))
        assert model.keypoint and model.pose == pose
    assert not PerceptionMap(build(compose("train", []).model, "model")).keypoint  # the paper's maps keep the flat head


def test_the_keypoint_head_learns_sub_pixel_positions_where_the_flat_head_does_not_yet():
    """Same trunk, images, optimiser and steps (600 rendered clean frames, 6 epochs): the keypoint head reaches
    sub-pixel accuracy on held-out frames, the flat head is still pixels off (docs/train.md, "Keypoint head")."""
    from pipeline.control import Scene
    from pipeline.render import Camera
    from pipeline.train.module import PerceptionMap

    rng = np.random.default_rng(0)
    cam = Camera(Scene())
    pos = np.column_stack([rng.uniform(-45, 45, 800), rng.uniform(-27, 27, 800)])
    images = torch.from_numpy(cam.render(pos))
    target = torch.from_numpy(pos.astype(np.float32))
    mae = {}
    for head in ("keypoint", "flat"):
        torch.manual_seed(0)
        model = PerceptionMap.of(position_head=head, uncertainty="none", filters=[8, 16, 32])
        opt = torch.optim.Adam(model.parameters(), lr=3e-3)
        model.train()
        for _ in range(6):
            for s in range(0, 600, 16):
                x = model.prepare(images[s:s + 16])
                loss = torch.nn.functional.mse_loss(model.position_outputs(x), model.targets(target[s:s + 16]))
                opt.zero_grad()
                loss.backward()
                opt.step()
        model.eval()
        with torch.inference_mode():
            err = (model(images[600:]) - target[600:]).abs().mean()
        mae[head] = float(err)
    assert mae["keypoint"] < 1.0 and mae["keypoint"] < mae["flat"] / 2, mae
    assert math.isfinite(mae["flat"])
