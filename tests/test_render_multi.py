"""The camera for several obstacles and a unicycle (SPEC §1 last bullet, §3.6, §3.7): every disc drawn, a larger
arena renders a larger image, and an oriented leader marker whose image carries the heading."""

import hashlib
import time
from types import SimpleNamespace as NS

import numpy as np
import pytest

from pipeline.control import Obstacle, Scene
from pipeline.render import DEFAULT_ARENA, Camera, load_occlusion
from pipeline.render.marker import heading_marker, polygon_coverage

SCENE = Scene(target=[40.0, 0.0])
# sha256 of the bytes the renderer produced before several obstacles and headings were added (computed with the
# implementation of commit eec9f6c): the single-obstacle background and a leader/follower batch stay bit-identical.
BG_SHA = "1d5f54faed6fc79ed521421856c88892209deb4b973b87dfe6dcd0ea470e5ec5"
RENDER_SHA = "498d9ab3961b80ef5150208bac35b533c4345937bad00b061679461f4e53cff1"
BG2_SHA = "41aa494145149adfd11f1e640ceddb2902745fa822e921ecf75be105b53bd396"  # off-centre r = 6.5, filled target

ARENA_BIG = ((-100.0, 100.0), (-50.0, 50.0))
DISCS = [[-84, 16, 8], [-64, -20, 5], [-50, 34, 9], [-36, 0, 6], [-16, -28, 6], [-4, 24, 5], [14, -6, 9], [36, 16, 4],
         [34, -36, 8], [74, 30, 7], [70, -4, 8], [70, -34, 5]]


def multi_scene(discs, target=(90.0, 40.0), bounds=DEFAULT_ARENA):
    """A stand-in scene: the camera reads `bounds` (its arena), `obstacles` and `target`."""
    return NS(obstacles=[NS(center=[float(x), float(y)], radius=float(r)) for x, y, r in discs], target=list(target),
              bounds=bounds)


@pytest.fixture(scope="module")
def cam():
    return Camera(SCENE)


@pytest.fixture(scope="module")
def big():
    return Camera(multi_scene(DISCS, bounds=ARENA_BIG), px_per_unit=1.0)


def sha(a) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def free_positions(rng, n, margin=5.0):
    """Positions on plain background in the default arena (away from borders, the obstacle and the target)."""
    p = rng.uniform([-50 + margin, -30 + margin], [50 - margin, 30 - margin], size=(4 * n, 2))
    ok = (np.hypot(p[:, 0], p[:, 1]) > 4 + 5) & (np.hypot(p[:, 0] - 40, p[:, 1]) > 2.5 + 5)
    return p[ok][:n]


def moments(cam, images):
    """Intensity centroid `(u, v)` and heading estimate (world radians) of image - background.

    Heading: the principal axis of the second central moments (an elongated marker), its sign from the third
    moment along that axis (the mass of a triangle sits at its base, the long tail points to the apex)."""
    d = (images.astype(np.int32) - cam.background.astype(np.int32)).sum(-1).astype(float)
    h, w = cam.shape
    uu, vv = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    m = d.sum(axis=(1, 2))
    cu = (d * uu).sum(axis=(1, 2)) / m
    cv = (d * vv).sum(axis=(1, 2)) / m
    du, dv = uu[None] - cu[:, None, None], vv[None] - cv[:, None, None]
    suu, svv, suv = ((d * du * du).sum((1, 2)) / m, (d * dv * dv).sum((1, 2)) / m, (d * du * dv).sum((1, 2)) / m)
    phi = 0.5 * np.arctan2(2 * suv, suu - svv)  # axis angle in (u, v)
    ax_u, ax_v = np.cos(phi), np.sin(phi)
    t = du * ax_u[:, None, None] + dv * ax_v[:, None, None]
    skew = (d * t**3).sum((1, 2))
    s = np.where(skew >= 0, 1.0, -1.0)
    heading = np.arctan2(-s * ax_v, s * ax_u)  # back to the world frame (row axis points down)
    return np.stack([cu, cv], 1), heading, m


def wrap(a):
    return (a + np.pi) % (2 * np.pi) - np.pi


# ------------------------------------------------------------------------------------ unchanged bytes
def test_single_obstacle_background_and_square_render_bit_identical(cam):
    assert sha(cam.background) == BG_SHA
    c2 = Camera(Scene(target=[40.0, 0.0], obstacles=[Obstacle(center=[3.3, -2.1], radius=6.5)]), robot_size=1.7,
                target_radius=4.0, target_ring_width=None)
    assert sha(c2.background) == BG2_SHA
    rng = np.random.default_rng(123)
    lead = rng.uniform([-55, -35], [55, 35], size=(700, 2))
    fol = rng.uniform([-50, -30], [50, 30], size=(700, 2))
    fol[::4] = np.nan
    lead[::7] = np.nan
    imgs = cam.render(lead, fol)
    assert sha(imgs) == RENDER_SHA
    np.testing.assert_array_equal(cam.render(lead, fol, heading=None), imgs)


def test_obstacles_list_with_one_disc_equals_the_single_obstacle_scene(cam):
    one = Camera(multi_scene([[0, 0, 4]], target=(40.0, 0.0)))
    np.testing.assert_array_equal(one.background, cam.background)
    mapping = NS(obstacles=[{"center": (0.0, 0.0), "radius": 4.0}], target=(40.0, 0.0), bounds=DEFAULT_ARENA)
    np.testing.assert_array_equal(Camera(mapping).background, cam.background)
    none = Camera(NS(obstacles=[], target=(40.0, 0.0), bounds=DEFAULT_ARENA))
    assert not np.any(np.all(none.background == none.colors["obstacle"], axis=-1))


# ------------------------------------------------------------------------------------ several discs
def test_every_disc_drawn_at_its_place_with_its_area(big):
    bg = big.background
    assert bg.shape == (100, 200, 3)
    obst = big.colors["obstacle"] - big.colors["background"]
    cover = (bg.astype(float) - big.colors["background"]) @ obst / (obst @ obst)  # obstacle fraction per pixel
    uv = big.world_to_pixel([d[:2] for d in DISCS])
    for (x, y, r), (u, v) in zip(DISCS, uv):
        np.testing.assert_array_equal(bg[int(v), int(u)], big.colors["obstacle"])  # the centre pixel
        c0, c1, r0, r1 = int(u - r - 2), int(u + r + 3), int(v - r - 2), int(v + r + 3)
        others = [q for q in DISCS if q != [x, y, r]]
        assert all(np.hypot(q[0] - x, q[1] - y) > q[2] + r + 4 for q in others)  # the window holds one disc
        area = cover[max(r0, 0) : r1, max(c0, 0) : c1].sum()
        assert abs(area - np.pi * r * r) < 0.5, (x, y, r, area)
    # nothing between the discs, the target ring where it belongs
    np.testing.assert_array_equal(bg[50, 40], big.colors["background"])  # world (-60, 0)
    (tu, tv), = big.world_to_pixel([[90.0, 40.0]])
    tgt = big.colors["target"] - big.colors["background"]
    ring = ((bg.astype(float) - big.colors["background"]) @ tgt / (tgt @ tgt))[int(tv) - 4 : int(tv) + 5, int(tu) - 4 : int(tu) + 5]
    assert abs(ring.sum() - np.pi * (2.5**2 - 1.5**2)) < 0.3


def test_overlapping_discs_are_one_layer():
    """Two overlapping discs: covered area = the union's, and a pixel inside both is the plain obstacle colour."""
    cam2 = Camera(multi_scene([[-2, 0, 5], [2, 0, 5]], target=(40.0, 0.0)))
    col = cam2.colors["obstacle"] - cam2.colors["background"]
    cover = (cam2.background.astype(float) - cam2.colors["background"]) @ col / (col @ col)
    union = 2 * 25 * np.pi - (2 * 25 * np.arccos(4 / 10) - 2 * np.sqrt(100 - 16))  # minus the lens, d = 4
    assert abs(cover[:, 35:65].sum() - union) < 0.5
    np.testing.assert_array_equal(cam2.background[30, 50], cam2.colors["obstacle"])


def test_large_arena_with_twelve_discs_renders_fast(big):
    t = time.perf_counter()
    Camera(multi_scene(DISCS, bounds=ARENA_BIG), px_per_unit=1.0)
    assert time.perf_counter() - t < 2.0
    rng = np.random.default_rng(0)
    p = rng.uniform([-100, -50], [100, 50], size=(64, 2))
    imgs = big.render(p, heading=rng.uniform(-np.pi, np.pi, 64), occlusion=load_occlusion("light"),
                      rng=np.random.default_rng(1))
    assert imgs.shape == (64, 100, 200, 3) and imgs.dtype == np.uint8


# ------------------------------------------------------------------------------------ heading marker
def test_marker_geometry_follows_robot_size():
    """Apex 4/3 L ahead, base 2/3 L behind, base width L: area L^2, area centroid at the position."""
    for size in (1.5, 3.0, 5.0):
        v = heading_marker([[10.0, 20.0]], [0.0], size)[0]
        np.testing.assert_allclose(v, [[10 + 4 / 3 * size, 20], [10 - 2 / 3 * size, 20 - size / 2],
                                       [10 - 2 / 3 * size, 20 + size / 2]], atol=1e-12)
        np.testing.assert_allclose(v.mean(0), [10.0, 20.0], atol=1e-12)
    # world heading +90 deg (towards +y) points up the image (-v)
    v = heading_marker([[0.0, 0.0]], [np.pi / 2], 3.0)[0]
    np.testing.assert_allclose(v[0], [0.0, -4.0], atol=1e-12)


def test_polygon_coverage_is_exact_area():
    """Against a fine supersampling of the same triangles, and the total is the triangle's area."""
    rng = np.random.default_rng(3)
    n, k, s = 16, 9, 64
    verts = heading_marker(rng.uniform(10, 20, (n, 2)), np.r_[np.arange(8) * np.pi / 4, rng.uniform(-4, 4, 8)], 3.0)
    start = np.floor(verts.min(1)).astype(int)
    rows, cols = start[:, 1, None] + np.arange(k), start[:, 0, None] + np.arange(k)
    a = polygon_coverage(verts, rows, cols)
    np.testing.assert_allclose(a.sum((1, 2)), 9.0, atol=1e-9)
    off = (np.arange(s) + 0.5) / s
    for i in range(n):
        uu = (cols[i][:, None] + off).reshape(1, -1)
        vv = (rows[i][:, None] + off).reshape(-1, 1)
        p = verts[i]
        orient = np.sign((p[1, 0] - p[0, 0]) * (p[2, 1] - p[0, 1]) - (p[1, 1] - p[0, 1]) * (p[2, 0] - p[0, 0]))
        inside = np.ones((vv.size, uu.size), bool)
        for j in range(3):
            a0, b0 = p[j], p[(j + 1) % 3]
            inside &= orient * ((b0[0] - a0[0]) * (vv - a0[1]) - (b0[1] - a0[1]) * (uu - a0[0])) >= 0
        np.testing.assert_allclose(inside.reshape(k, s, k, s).mean((1, 3)), a[i], atol=0.02)


def test_heading_and_position_recoverable(cam):
    rng = np.random.default_rng(11)
    p = free_positions(rng, 400)
    th = rng.uniform(-np.pi, np.pi, len(p))
    th[:8] = np.arange(8) * np.pi / 4  # axis-aligned and diagonal headings included
    imgs = cam.render(p, heading=th)
    c, est, mass = moments(cam, imgs)
    err_px = np.hypot(*(c - cam.world_to_pixel(p)).T)
    assert err_px.max() < 0.1 and err_px.mean() < 0.02, (err_px.max(), err_px.mean())  # uint8 rounding only
    err_deg = np.degrees(np.abs(wrap(est - th)))
    assert err_deg.max() < 4.0 and err_deg.mean() < 1.0, (err_deg.max(), err_deg.mean())
    full = (cam.colors["leader"] - cam.colors["background"]).sum()
    np.testing.assert_allclose(mass / full, cam.robot_size**2, rtol=0.01)  # area L^2, the square's


def test_heading_batched_equals_one_by_one_and_deterministic(cam):
    rng = np.random.default_rng(12)
    lead = rng.uniform([-55, -35], [55, 35], size=(14, 2))  # some partly or fully out of view
    fol = rng.uniform([-50, -30], [50, 30], size=(14, 2))
    th = rng.uniform(-7, 7, 14)
    fol[::3] = np.nan
    lead[5] = np.nan
    th[5] = np.nan  # no leader: its heading may be NaN
    batch = cam.render(lead, fol, heading=th)
    for i in range(len(lead)):
        np.testing.assert_array_equal(batch[i], cam.render(lead[i : i + 1], fol[i : i + 1], heading=th[i : i + 1])[0])
    np.testing.assert_array_equal(batch[5], cam.render(np.full((1, 2), np.nan), fol[5:6])[0])
    again = cam.render(lead, fol, heading=th)
    assert sha(again) == sha(batch)
    # chunked: more than one internal block, into a preallocated array
    lead2 = rng.uniform([-48, -28], [48, 28], size=(1100, 2))
    th2 = rng.uniform(-np.pi, np.pi, 1100)
    out = np.empty((1100, 60, 100, 3), np.uint8)
    cam.render(lead2[:600], heading=th2[:600], out=out[:600])
    cam.render(lead2[600:], heading=th2[600:], out=out[600:])
    np.testing.assert_array_equal(out, cam.render(lead2, heading=th2))


def test_heading_changes_the_image_and_follower_stays_square(cam):
    lead, fol = np.array([[-20.0, 10.0]]), np.array([[20.0, -10.0]])
    a = cam.render(lead, fol, heading=[0.3])[0]
    b = cam.render(lead, fol, heading=[0.3 + np.pi])[0]
    sq = cam.render(lead, fol)[0]
    assert not np.array_equal(a, b) and not np.array_equal(a, sq)
    (fu, fv), = cam.world_to_pixel(fol)
    win = np.s_[int(fv) - 3 : int(fv) + 4, int(fu) - 3 : int(fu) + 4]
    np.testing.assert_array_equal(a[win], sq[win])  # the follower's square, unchanged
    np.testing.assert_array_equal(b[win], sq[win])
    (lu, lv), = cam.world_to_pixel(lead)
    win = np.s_[int(lv) - 5 : int(lv) + 6, int(lu) - 5 : int(lu) + 6]
    full = (cam.colors["leader"] - cam.colors["background"]).sum() * cam.robot_size**2
    for img in (a, b):
        mass = (img[win].astype(np.int32) - cam.background[win]).sum() / full
        assert abs(mass - 1) < 0.01  # the whole marker (area L^2) around the leader, in the leader's colour


def test_marker_partly_outside_is_clipped(cam):
    p = np.array([[-50.0, 0.0], [50.0, 30.0], [0.0, -30.5], [-51.0, 31.0], [80.0, 0.0], [-46.0, 0.0]])
    th = np.array([np.pi, 0.3, -np.pi / 2, 2.0, 0.0, 0.0])
    imgs = cam.render(p, heading=th, occlusion=load_occlusion("heavy"), rng=np.random.default_rng(0))
    clear = cam.render(p, heading=th)
    full = (cam.colors["leader"] - cam.colors["background"]).sum() * cam.robot_size**2
    mass = (clear.astype(np.int32) - cam.background.astype(np.int32)).sum((1, 2, 3)) / full
    assert np.all(mass[:4] > 0.01) and np.all(mass[:4] < 0.9)
    assert mass[4] == 0 and abs(mass[5] - 1) < 0.01  # fully out of view / just inside
    np.testing.assert_array_equal(clear[4], cam.background)
    assert imgs.shape == clear.shape


def test_bad_heading_input(cam):
    with pytest.raises(ValueError, match="heading has 1 rows"):
        cam.render(np.zeros((2, 2)), heading=[0.0])
    with pytest.raises(ValueError, match="not finite"):
        cam.render(np.zeros((2, 2)), heading=[0.0, np.nan])
