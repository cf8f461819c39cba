"""The camera h(p): pixel map, sub-pixel robot, leader/follower, clouds (issue 3 §1, §4)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from pipeline.config import build
from pipeline.control import Scene
from pipeline.errors import ConfigError
from pipeline.render import (
    Camera,
    Occlusion,
    load_occlusion,
    occlusion_levels,
    pixel_to_world,
    world_to_pixel,
)

SCENE = Scene(target=[40.0, 0.0])
LEVELS = ("none", "light", "medium", "heavy")


@pytest.fixture(scope="module")
def cam():
    return Camera(SCENE)


def free_positions(rng, n, margin=3.0):
    """Positions away from the borders, the obstacle disc and the target ring (uniform background)."""
    p = rng.uniform([-50 + margin, -30 + margin], [50 - margin, 30 - margin], size=(4 * n, 2))
    ok = (np.hypot(p[:, 0], p[:, 1]) > 4 + 3) & (np.hypot(p[:, 0] - 40, p[:, 1]) > 2.5 + 3)
    return p[ok][:n]


def centroids(cam, images):
    """Intensity centroid (u, v) of image - background, pixel centres at c + 0.5 / r + 0.5."""
    d = (images.astype(np.int32) - cam.background.astype(np.int32)).sum(-1).astype(float)
    h, w = cam.shape
    mass = d.sum(axis=(1, 2))
    u = (d * (np.arange(w) + 0.5)[None, None, :]).sum(axis=(1, 2)) / mass
    v = (d * (np.arange(h) + 0.5)[None, :, None]).sum(axis=(1, 2)) / mass
    return np.stack([u, v], axis=1), mass


# --------------------------------------------------------------------------------------- pixel map
def test_world_to_pixel_convention():
    corners = np.array([[-50.0, 30.0], [50.0, -30.0], [0.0, 0.0], [40.0, 0.0]])
    np.testing.assert_allclose(world_to_pixel(corners), [[0, 0], [100, 60], [50, 30], [90, 30]])
    # a non-default arena and size: 2 px per unit
    uv = world_to_pixel([[1.0, 2.0]], arena=((0, 10), (0, 5)), shape=(10, 20))
    np.testing.assert_allclose(uv, [[2.0, 6.0]])


@settings(max_examples=50, deadline=None)
@given(st.floats(-60, 60), st.floats(-40, 40))
def test_pixel_to_world_inverts(x, y):
    p = np.array([[x, y]])
    np.testing.assert_allclose(pixel_to_world(world_to_pixel(p)), p, atol=1e-9)


# ------------------------------------------------------------------------------------------- robot
def test_robot_centroid_subpixel(cam):
    """The rendered square's intensity centroid is the true position to << 0.1 px; its area is exact."""
    p = free_positions(np.random.default_rng(0), 500)
    images = cam.render(p)
    c, mass = centroids(cam, images)
    err = np.hypot(*(c - cam.world_to_pixel(p)).T)
    assert err.max() < 0.1, err.max()
    full = (cam.colors["leader"] - cam.colors["background"]).sum()
    np.testing.assert_allclose(mass / full, cam.robot_size**2, rtol=0.01)


def test_robot_moves_with_subpixel_shift(cam):
    """A 0.3 px shift moves the centroid by 0.3 px (nearest-pixel drawing would not)."""
    base = np.array([[-20.3, 10.1]])
    shifted = base + [[0.3, 0.0]]
    (c0,), _ = centroids(cam, cam.render(base))
    (c1,), _ = centroids(cam, cam.render(shifted))
    assert abs((c1[0] - c0[0]) - 0.3) < 0.02 and abs(c1[1] - c0[1]) < 0.02


def test_batched_equals_one_at_a_time(cam):
    rng = np.random.default_rng(1)
    lead = rng.uniform([-55, -35], [55, 35], size=(12, 2))  # some partly or fully out of view
    fol = rng.uniform([-50, -30], [50, 30], size=(12, 2))
    fol[::3] = np.nan
    batch = cam.render(lead, fol)
    for i in range(len(lead)):
        np.testing.assert_array_equal(batch[i], cam.render(lead[i : i + 1], fol[i : i + 1])[0])


def test_leader_white_follower_green_and_absent(cam):
    lead, fol = np.array([[-20.0, 10.0]]), np.array([[20.0, -10.0]])
    img = cam.render(lead, fol)[0]
    (lu, lv), (fu, fv) = cam.world_to_pixel(np.vstack([lead, fol])).astype(int)
    np.testing.assert_array_equal(img[lv, lu], cam.colors["leader"])
    np.testing.assert_array_equal(img[fv, fu], cam.colors["follower"])
    # NaN follower rows = no follower; NaN leader = nothing drawn; out of view = background
    np.testing.assert_array_equal(cam.render(lead, np.full((1, 2), np.nan)), cam.render(lead))
    np.testing.assert_array_equal(cam.render(np.full((1, 2), np.nan))[0], cam.background)
    np.testing.assert_array_equal(cam.render([[80.0, 0.0]])[0], cam.background)


def test_background_shows_obstacle_and_target(cam):
    bg = cam.background
    (ou, ov), = cam.world_to_pixel([SCENE.obstacle_center]).astype(int)
    np.testing.assert_array_equal(bg[ov, ou], cam.colors["obstacle"])
    np.testing.assert_array_equal(bg[2, 2], cam.colors["background"])
    # anti-aliased areas (in units of each colour): disc pi r^2, target ring pi (2.5^2 - 1.5^2)
    d = np.abs(bg.astype(float) - cam.colors["background"]).sum(-1)
    disc = d[:, 30:70].sum() / np.abs(cam.colors["obstacle"] - cam.colors["background"]).sum()
    ring = d[:, 80:].sum() / np.abs(cam.colors["target"] - cam.colors["background"]).sum()
    assert abs(disc - np.pi * 16) < 0.5
    assert abs(ring - np.pi * (2.5**2 - 1.5**2)) < 0.3


# ------------------------------------------------------------------------------------------ clouds
def test_levels_exist_and_are_ordered_by_covered_fraction(cam):
    assert set(LEVELS) <= set(occlusion_levels())
    rng = np.random.default_rng(2)
    p = rng.uniform([-48, -28], [48, 28], size=(2000, 2))
    fracs = []
    for level in LEVELS:
        res = cam.render(p, occlusion=load_occlusion(level), rng=np.random.default_rng(3), return_info=True)
        fracs.append(res.occluded_frac.mean())
    assert fracs[0] == 0.0
    assert all(a < b for a, b in zip(fracs, fracs[1:])), fracs
    assert fracs[-1] > 0.1  # heavy really is heavy


@pytest.mark.parametrize("level", ["light", "heavy"])
def test_occluded_fraction_matches_drawn_clouds(cam, level):
    """The reported fraction is the mean cloud opacity actually blended into the pixels."""
    occ = load_occlusion(level)
    res = cam.render(np.full((300, 2), np.nan), occlusion=occ, rng=np.random.default_rng(4), return_info=True)
    bg = cam.background[..., 2].astype(float)  # blue channel: the cloud colour differs most there
    alpha = (res.images[..., 2] - bg) / (occ.color[2] - bg)
    np.testing.assert_allclose(alpha.mean(axis=(1, 2)), res.occluded_frac, atol=0.01)
    assert np.all((res.occluded_frac > 0) == (alpha.max(axis=(1, 2)) > 0.02))
    assert np.all(res.leader_alpha == 0)  # no leader in view


def test_clouds_can_cover_the_robot(cam):
    dense = Occlusion(name="dense", probability=1.0, blobs=(12, 12), radius=(25.0, 25.0), opacity=(1.0, 1.0))
    p = free_positions(np.random.default_rng(5), 200)
    res = cam.render(p, occlusion=dense, rng=np.random.default_rng(6), return_info=True)
    covered = res.leader_alpha > 0.99
    assert covered.mean() > 0.5
    uv = cam.world_to_pixel(p[covered]).astype(int)
    px = res.images[covered][np.arange(covered.sum()), uv[:, 1], uv[:, 0]]
    assert np.abs(px.astype(int) - dense.color).max() <= 3  # the leader is hidden under the cloud


def test_same_rng_same_bytes_different_seed_different(cam):
    p = np.random.default_rng(7).uniform([-48, -28], [48, 28], size=(64, 2))
    occ = load_occlusion("medium")
    a = cam.render(p, occlusion=occ, rng=np.random.default_rng(8))
    b = cam.render(p, occlusion=occ, rng=np.random.default_rng(8))
    c = cam.render(p, occlusion=occ, rng=np.random.default_rng(9))
    assert a.tobytes() == b.tobytes()
    assert a.tobytes() != c.tobytes()
    # pre-drawn cloud choices, rendered in two halves into a preallocated array: same bytes
    clouds = occ.sample(64, np.random.default_rng(8), cam.shape)
    out = np.empty_like(a)
    cam.render(p[:30], occlusion=occ, clouds=clouds[:30], out=out[:30])
    cam.render(p[30:], occlusion=occ, clouds=clouds[30:], out=out[30:])
    np.testing.assert_array_equal(out, a)


def test_level_none_is_a_no_op(cam):
    p = np.random.default_rng(10).uniform([-48, -28], [48, 28], size=(32, 2))
    np.testing.assert_array_equal(cam.render(p, occlusion=load_occlusion("none"), rng=np.random.default_rng(0)), cam.render(p))


# --------------------------------------------------------------------------------------- bad input
RENDER = "pipeline.render.Camera"
OCCLUSION = "pipeline.render.Occlusion"


def test_bad_config_names_the_field():
    # the image size is the arena times px_per_unit (square pixels): a size that is no whole number of pixels
    # (the old mismatched height/width) names px_per_unit, in one line with the arena's size
    with pytest.raises(ConfigError) as e:
        Camera(SCENE, px_per_unit=0.33)
    assert e.value.field == "render.px_per_unit" and "whole numbers" in str(e.value) and "60 x 100" in str(e.value)
    assert "\n" not in str(e.value)
    with pytest.raises(ConfigError) as e:
        Camera(SCENE, px_per_unit=0)
    assert e.value.field == "render.px_per_unit"
    with pytest.raises(ConfigError) as e:
        Camera(SCENE, robot_size=0)
    assert e.value.field == "render.robot_size"
    with pytest.raises(ConfigError) as e:
        build({"_target_": RENDER, "px_per_unit": 1.0, "colors": {"leader": [300, 0, 0]}}, "render", scene=SCENE)
    assert e.value.field == "render.colors.leader"
    with pytest.raises(ConfigError) as e:  # the removed keys are unknown keys of the render node
        build({"_target_": RENDER, "height": 60, "width": 100}, "render", scene=SCENE)
    assert e.value.field in ("render.height", "render.width") and "px_per_unit" in str(e.value)
    with pytest.raises(ConfigError) as e:
        load_occlusion("fog", field="data.occlusion")
    assert e.value.field == "data.occlusion" and "heavy" in str(e.value)
    with pytest.raises(ConfigError) as e:
        build({"_target_": OCCLUSION, "probability": 1.5}, "occlusion")
    assert e.value.field == "occlusion.probability"
    with pytest.raises(ConfigError) as e:
        build({"_target_": OCCLUSION, "blobs": [3, 1]}, "occlusion")
    assert e.value.field == "occlusion.blobs"


def test_from_config_matches_constructor():
    cam = build({"_target_": RENDER, "px_per_unit": 0.5, "robot_size": 1.5}, "render", scene=SCENE)
    assert cam.shape == (30, 50) and cam.scale == 0.5
    np.testing.assert_allclose(cam.world_to_pixel([[0.0, 0.0]]), [[25.0, 15.0]])
    cfg = {"_target_": "pipeline.control.Scene", "target": [40.0, 0.0], "arena": {"x": [-50.0, 50.0], "y": [-30.0, 30.0]}}
    assert build({"_target_": RENDER}, "render", scene=build(cfg, "scene")).shape == (60, 100)
    occ = load_occlusion("heavy")
    assert build({"_target_": OCCLUSION, **occ.config()}, "occlusion") == occ
    assert Occlusion(**occ.config()) == occ


def test_authors_clouds_are_clustered_bubbles_and_the_disc_target():
    """The `authors` level: 1-4 round bubbles per image whose centres lie within +-cluster px of one centre;
    clustering two fixed-size blobs makes them overlap (less covered area than two blobs anywhere)."""
    from pipeline.render.occlusion import Occlusion

    authors = load_occlusion("authors")
    assert authors.cluster == 10.0 and authors.blobs == (1, 4) and authors.probability == 1.0
    base = dict(name="t", probability=1.0, blobs=(2, 2), radius=(6.0, 6.0), opacity=(0.5, 0.5), aspect=(1.0, 1.0),
                softness=0.2, bank=64, seed=5)
    tight = Occlusion(**base, cluster=0.5).fields((60, 100))[0][:, :60, :100]
    loose = Occlusion(**base).fields((60, 100))[0][:, :60, :100]
    assert (tight > 0).mean() < 0.75 * (loose > 0).mean()
    rebuilt = build({"_target_": OCCLUSION, **Occlusion(**base).config()}, "occlusion")
    assert Occlusion(**base).config() == rebuilt.config()
    assert "cluster" not in Occlusion(**base).config()  # levels without clustering keep their mapping
    with pytest.raises(ConfigError, match="occlusion.cluster"):
        build({"_target_": OCCLUSION, **base, "cluster": -1}, "occlusion")
    scene = Scene(target=[40.0, 0.0])
    disc = Camera(scene, target_radius=4.0, target_ring_width=None, colors={"target": (255, 0, 0)})
    ring = Camera(scene, target_radius=4.0, colors={"target": (255, 0, 0)})
    (tu, tv), = disc.world_to_pixel([scene.target])
    centre = disc.background[int(tv), int(tu)]
    assert tuple(centre) == (255, 0, 0) and tuple(ring.background[int(tv), int(tu)]) != (255, 0, 0)
