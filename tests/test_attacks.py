"""Attacks through the camera (pipeline.perception.attacks): the PGD pixel attack, the worst cloud, the closed-loop hook.

A differentiable stand-in for the perception map (the centroid of the bright pixels, in world units) and the
real Camera keep these fast; one test runs the real (untrained) FoldedPerceptionNet to check that gradients
flow through the inference network as it is.
"""

from types import SimpleNamespace

import numpy as np
import pytest
import torch
from torch import nn

from pipeline.errors import ConfigError
from pipeline.perception.adversary import AttackedCamera, proposition1_direction
from pipeline.perception.attacks import ScaledInput, pixel_attack, worst_cloud
from pipeline.render import Camera, CloudSample, Occlusion

SCENE = SimpleNamespace(obstacle_center=(0.0, 0.0), obstacle_radius=4.0, target=(40.0, 0.0))
E_B = np.array([0.0, 1.0])  # target to the right of the obstacle: e_a = (1, 0), e_b its left-hand normal


class Centroid(nn.Module):
    """Intensity-weighted centroid of the pixels brighter than `thr` (grey level), as world coordinates of
    the default 100 x 60 arena (1 px = 1 unit, row 0 at y = +30). Differentiable in the image."""

    def __init__(self, thr: float = 150.0):
        super().__init__()
        self.thr = thr
        self.scale = nn.Parameter(torch.ones(()))  # a parameter, to check that the attack leaves it alone

    def forward(self, x):
        g = x.mean(-1)  # (N, H, W)
        w = torch.relu(g - self.thr) * self.scale
        h, wd = g.shape[1:]
        cols = torch.arange(wd, dtype=x.dtype) + 0.5
        rows = torch.arange(h, dtype=x.dtype) + 0.5
        tot = w.sum((1, 2)) + 1e-6
        u = (w.sum(1) * cols).sum(1) / tot
        v = (w.sum(2) * rows).sum(1) / tot
        return torch.stack([u - 50.0, 30.0 - v], 1)


def centroid_predict(net):
    def predict(images):
        with torch.no_grad():
            return net(torch.from_numpy(np.asarray(images)).float()).double().numpy()
    return predict


pytestmark = pytest.mark.usefixtures("one_torch_thread")  # tests/conftest.py


@pytest.fixture(scope="module")
def camera():
    return Camera(SCENE)


@pytest.fixture(scope="module")
def positions():
    rng = np.random.default_rng(7)
    return np.column_stack([rng.uniform(-40, 30, 12), rng.uniform(-22, 22, 12)])


def directions(p):
    """-sign(b) e_b (SPEC §3.5), b = y here."""
    return -np.where(p[:, 1] >= 0, 1.0, -1.0)[:, None] * E_B


def test_proposition1_direction_matches_the_state_attack():
    scene = SimpleNamespace(e_b=E_B, to_frame=lambda p: (p[:, 0], p[:, 1]))
    p = np.array([[-12.0, 2.0], [-12.0, -2.0], [5.0, 0.0]])
    np.testing.assert_array_equal(proposition1_direction(scene)(p), [[0, -1], [0, 1], [0, -1]])


# ------------------------------------------------------------------------------------ pixel attack
@pytest.mark.parametrize("kappa", [3, 2.5])
@pytest.mark.parametrize("start", [None, 5])
def test_pixel_budget_holds_exactly_in_integer_levels(camera, positions, kappa, start):
    imgs = camera.render(positions)
    rng = None if start is None else np.random.default_rng(start)
    res = pixel_attack(Centroid(), imgs, directions(positions), kappa=kappa, steps=4, rng=rng)
    assert res.images.dtype == np.uint8 and res.images.shape == imgs.shape
    diff = np.abs(res.images.astype(int) - imgs.astype(int))
    assert diff.max() == int(np.floor(kappa))  # within the budget, and the budget is used
    assert res.clean.shape == res.attacked.shape == (len(positions), 2)


def test_pixel_attack_beats_random_perturbation_of_the_same_budget(camera, positions):
    net = Centroid(thr=100.0)  # the obstacle's rim counts too: a map a perturbation can distract
    imgs = camera.render(positions)
    d = directions(positions)
    kappa = 4
    res = pixel_attack(net, imgs, d, kappa=kappa, steps=5)
    rng = np.random.default_rng(1)
    noise = rng.choice([-kappa, kappa], size=imgs.shape)
    rand = np.clip(imgs.astype(int) + noise, 0, 255).astype(np.uint8)
    rand_along = np.einsum("ij,ij->i", centroid_predict(net)(rand) - res.clean, d)
    assert np.all(res.along > 0)
    assert res.along.mean() > 5 * np.abs(rand_along).mean()  # measured: 17x
    # the reported estimates are the network's on the returned images
    np.testing.assert_allclose(res.attacked, centroid_predict(net)(res.images), atol=1e-4)
    np.testing.assert_allclose(res.clean, centroid_predict(net)(imgs), atol=1e-4)
    np.testing.assert_allclose(res.norm, np.hypot(*(res.attacked - res.clean).T))
    assert net.scale.grad is None and net.training  # parameters untouched, mode restored


def test_pixel_kappa_zero_changes_nothing(camera, positions):
    imgs = camera.render(positions)
    res = pixel_attack(Centroid(), imgs, directions(positions), kappa=0, steps=5, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(res.images, imgs)
    np.testing.assert_array_equal(res.attacked, res.clean)


def test_pixel_attack_is_deterministic_and_batch_invariant(camera, positions):
    imgs = camera.render(positions)
    d = directions(positions)
    runs = [pixel_attack(Centroid(), imgs, d, kappa=4, steps=3, batch_size=b, rng=np.random.default_rng(3))
            for b in (512, 512, 5, 1)]
    for r in runs[1:]:
        np.testing.assert_array_equal(r.images, runs[0].images)
        np.testing.assert_allclose(r.attacked, runs[0].attacked, atol=1e-5)
    other = pixel_attack(Centroid(), imgs, d, kappa=4, steps=3, rng=np.random.default_rng(4))
    assert not np.array_equal(other.images, runs[0].images)  # the seed matters: the random start is used


def test_pixel_attack_never_helps_the_controller(camera, positions):
    # steps=0 with a random start is a random perturbation: where it moves the estimate against the
    # direction, the clean image is kept (delta = 0 is feasible)
    imgs = camera.render(positions)
    res = pixel_attack(Centroid(thr=100.0), imgs, directions(positions), kappa=6, steps=0,
                       rng=np.random.default_rng(0))
    assert np.all(res.along >= 0)
    kept = np.all(res.images == imgs, axis=(1, 2, 3))
    assert 0 < kept.sum() < len(imgs)  # some random starts helped the attack, some did not
    np.testing.assert_array_equal(res.attacked[kept], res.clean[kept])


def test_pixel_attack_through_the_folded_perception_net(camera, positions):
    from pipeline.perception.network import FoldedPerceptionNet
    from pipeline.train.module import PerceptionMap

    torch.manual_seed(0)
    model = PerceptionMap.of(filters=[4, 8], batch_norm=True, coord_channels=True)
    folded = FoldedPerceptionNet(model.eval())
    imgs = camera.render(positions)
    d = directions(positions)
    res = pixel_attack(folded, imgs, d, kappa=4, steps=5)
    assert np.all(res.along > 0)
    assert all(p.grad is None for p in folded.parameters())
    # the training module reads float input in [0, 1]: ScaledInput adapts it, same estimates and attack
    model.train()
    res_m = pixel_attack(ScaledInput(model), imgs, d, kappa=4, steps=5)
    assert model.training and all(p.grad is None for p in model.parameters())
    np.testing.assert_allclose(res_m.clean, res.clean, atol=1e-3)
    assert np.all(res_m.along > 0)


def test_pixel_attack_takes_a_budget_per_image(camera, positions):
    """One PGD (issue 47, the camera falsifier's): a budget per image is each image attacked alone with its own
    budget, and a constant one is the scalar budget, bit for bit."""
    imgs, d, net = camera.render(positions), directions(positions), Centroid(thr=100.0)
    one = pixel_attack(net, imgs, d, kappa=4, steps=3, rng=np.random.default_rng(3))
    same = pixel_attack(net, imgs, d, kappa=np.full(len(imgs), 4.0), steps=3, rng=np.random.default_rng(3))
    for a, b in ((one.images, same.images), (one.clean, same.clean), (one.attacked, same.attacked)):
        np.testing.assert_array_equal(a, b)
    kappa = np.array([0.0, 0.9, 2.0, 6.0, 12.0, 3.0, 1.0, 0.0, 16.0, 5.0, 4.0, 7.0])
    res = pixel_attack(net, imgs, d, kappa=kappa, steps=3, batch_size=5)
    for i in range(len(imgs)):
        alone = pixel_attack(net, imgs[i:i + 1], d[i:i + 1], kappa=kappa[i], steps=3)
        np.testing.assert_array_equal(res.images[i], alone.images[0])
        np.testing.assert_allclose(res.attacked[i], alone.attacked[0], atol=1e-9)
    moved = np.abs(res.images.astype(int) - imgs.astype(int)).max((1, 2, 3))
    assert (moved <= np.floor(kappa)).all() and (moved[kappa >= 2] > 0).all() and (res.along >= 0).all()


def test_pixel_attack_validates_its_budget(camera, positions):
    imgs = camera.render(positions[:2])
    with pytest.raises(ConfigError, match="attack.kappa"):
        pixel_attack(Centroid(), imgs, E_B, kappa=-1)
    with pytest.raises(ConfigError, match=r"attack.kappa\[1\]: must be a number in \[0, 255\], got 300"):
        pixel_attack(Centroid(), imgs, E_B, kappa=np.array([1.0, 300.0]))
    with pytest.raises(ValueError, match=r"kappa must be one budget or one per image \(2,\), got shape \(3,\)"):
        pixel_attack(Centroid(), imgs, E_B, kappa=np.ones(3))
    with pytest.raises(ValueError, match="direction"):
        pixel_attack(Centroid(), imgs, np.zeros((3, 2)), kappa=1)


# ------------------------------------------------------------------------------------- worst cloud
@pytest.fixture(scope="module")
def clouds():
    return Occlusion(name="test", probability=0.3, blobs=(1, 3), radius=(4.0, 10.0), opacity=(0.6, 0.9),
                     bank=8, seed=2)


def test_worst_cloud_is_the_argmax_of_an_explicit_loop(camera, clouds, positions):
    net = Centroid()
    predict = centroid_predict(net)
    p, k = positions[:3], 5
    d = directions(p)
    res = worst_cloud(camera, clouds, p, d, predict, candidates=k, rng=np.random.default_rng(11), chunk=4)
    assert len(res.candidates) == 3 * k and res.candidates.mask.all()  # the adversary always places a cloud
    scores = np.empty((3, k))
    for i in range(3):
        for j in range(k):
            img = camera.render(p[i : i + 1], occlusion=clouds, clouds=res.candidates[i * k + j : i * k + j + 1])
            scores[i, j] = (predict(img)[0] - p[i]) @ d[i]
    np.testing.assert_allclose(res.scores, scores, atol=1e-6)
    np.testing.assert_array_equal(res.chosen, scores.argmax(1))
    assert len(set(scores.round(6).ravel())) > 3  # the candidates differ: the choice is not trivial
    err_along = np.einsum("ij,ij->i", res.error(p), d)
    np.testing.assert_allclose(err_along, scores.max(1), atol=1e-6)
    assert np.all(err_along >= scores[:, 0] - 1e-9)  # never worse than the first candidate alone
    np.testing.assert_array_equal(res.images, camera.render(p, occlusion=clouds, clouds=res.clouds))
    np.testing.assert_allclose(res.clean, predict(camera.render(p)), atol=1e-9)


def test_worst_cloud_chunking_and_seed(camera, clouds, positions):
    predict = centroid_predict(Centroid())
    d = directions(positions)
    a = worst_cloud(camera, clouds, positions, d, predict, candidates=4, rng=np.random.default_rng(5))
    b = worst_cloud(camera, clouds, positions, d, predict, candidates=4, rng=np.random.default_rng(5), chunk=3)
    np.testing.assert_array_equal(a.images, b.images)
    np.testing.assert_array_equal(a.chosen, b.chosen)
    np.testing.assert_array_equal(a.attacked, b.attacked)
    # more candidates (a superset drawn from the same stream is not guaranteed, so compare with the mean)
    assert a.along.mean() > 0


def test_worst_cloud_mask_policy_and_inactive_level(camera, clouds, positions):
    predict = centroid_predict(Centroid())
    p = positions[:4]
    d = directions(p)
    own = worst_cloud(camera, clouds, p, d, predict, candidates=50, rng=np.random.default_rng(0), always=False)
    ref = clouds.sample(4 * 50, np.random.default_rng(0), camera.shape)
    np.testing.assert_array_equal(own.candidates.mask, ref.mask)  # the level's own draws
    assert 0 < own.candidates.mask.mean() < 1
    none = Occlusion(name="none")
    res = worst_cloud(camera, none, p, d, predict, candidates=3, rng=np.random.default_rng(0))
    np.testing.assert_array_equal(res.attacked, res.clean)
    np.testing.assert_array_equal(res.images, camera.render(p))


# --------------------------------------------------------------------------------- closed-loop hook
def stub_map(net):
    return SimpleNamespace(net=net, device="cpu", predict=centroid_predict(net))


@pytest.mark.parametrize("attack", ["pixel", "cloud"])
def test_hook_statistics_add_up(camera, clouds, positions, attack):
    hook = AttackedCamera(camera, stub_map(Centroid()), directions, attack=attack, occlusion=clouds, kappa=6,
                          candidates=4, keep_clouds=True)
    rng = np.random.default_rng(0)
    sizes = (5, 12, 3)
    along_true = []
    for frame, n in enumerate(sizes):
        p = positions[:n]
        est = hook(p, np.arange(n), frame, rng)
        assert est.shape == (n, 2)
        along_true.append(np.einsum("ij,ij->i", est - p, directions(p)))
    assert hook.frames == 3 and hook.images == sum(sizes)
    rows = hook.table()
    assert list(rows.groupby("frame").size()) == list(sizes)
    np.testing.assert_allclose(rows["error_along"], np.concatenate(along_true))  # |d| = 1 here
    np.testing.assert_allclose(rows[["x", "y"]].to_numpy(), np.concatenate([positions[:n] for n in sizes]))
    assert hook.mean_along == pytest.approx(rows["along"].mean())
    assert hook.mean_norm == pytest.approx(rows["norm"].mean())
    assert hook.mean_norm >= abs(hook.mean_along) and hook.mean_along > 0
    assert hook.flagged == hook.gated == 0 and not rows["flagged"].any()  # no uncertainty head, no gate
    if attack == "cloud":
        assert sum(len(c) for c in hook.clouds) == sum(sizes)


def test_hook_without_budget_is_the_camera_measurement(camera, clouds, positions):
    from pipeline.perception.measure import CameraMeasure

    pm = stub_map(Centroid())
    hook = AttackedCamera(camera, pm, directions, attack="pixel", occlusion=clouds, kappa=0)
    plain = CameraMeasure(camera, pm, occlusion=clouds)
    r1, r2 = np.random.default_rng(9), np.random.default_rng(9)
    for frame in range(2):
        np.testing.assert_array_equal(hook(positions, None, frame, r1), plain(positions, None, frame, r2))
    assert r1.random() == r2.random()  # the hook draws the scenario's clouds from the simulator's rng, no more
    with pytest.raises(ConfigError, match="attack.attack: must be one of pixel, cloud"):
        AttackedCamera(camera, pm, directions, attack="laser")


def test_cloud_sample_rows_are_agent_major(camera, clouds, positions):
    res = worst_cloud(camera, clouds, positions[:2], directions(positions[:2]), centroid_predict(Centroid()),
                      candidates=3, rng=np.random.default_rng(1))
    assert isinstance(res.clouds, CloudSample)
    np.testing.assert_array_equal(res.clouds.field, res.candidates.field[np.arange(2) * 3 + res.chosen])
