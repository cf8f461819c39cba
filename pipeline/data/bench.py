"""Benchmark: the batched camera (clean and heavy clouds) vs a per-image OpenCV drawing loop (issue 3 §5)."""

from __future__ import annotations

import time

import cv2
import numpy as np

from pipeline.control import Scene
from pipeline.render import Camera, load_occlusion


def _positions(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    lead = rng.uniform([-48.5, -28.5], [48.5, 28.5], size=(n, 2))
    fol = rng.uniform([-48.5, -28.5], [48.5, 28.5], size=(n, 2))
    fol[rng.random(n) < 0.5] = np.nan
    return lead, fol


def _best_rate(fn, n: int, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return n / best


def opencv_loop(cam: Camera, lead, fol, clouds: bool, rng) -> np.ndarray:
    """The naive renderer: every image drawn on its own with OpenCV (anti-aliased primitives, 1/16 px
    sub-pixel coordinates), clouds as blurred ellipses blended per image."""
    n = len(lead)
    h, w = cam.shape
    out = np.empty((n, h, w, 3), np.uint8)
    sh = 16  # cv2 `shift=4`: coordinates in 1/16 px
    uv_l, uv_f = cam.world_to_pixel(lead), cam.world_to_pixel(fol)
    (ou, ov), (tu, tv) = cam.world_to_pixel([cam.scene.obstacle_center, cam.scene.target])
    rad = int(cam.scene.obstacle_radius * cam.scale * sh)
    half = cam.robot_size / 2
    col = {k: tuple(int(c) for c in v) for k, v in cam.colors.items()}
    for i in range(n):
        img = np.empty((h, w, 3), np.uint8)
        img[:] = col["background"]
        cv2.circle(img, (int(ou * sh), int(ov * sh)), rad, col["obstacle"], -1, cv2.LINE_AA, 4)
        cv2.circle(img, (int(tu * sh), int(tv * sh)), int(2 * sh), col["target"], 1, cv2.LINE_AA, 4)
        for uv, c in ((uv_f[i], col["follower"]), (uv_l[i], col["leader"])):
            if np.isfinite(uv[0]):
                p0 = (int((uv[0] - half) * sh), int((uv[1] - half) * sh))
                p1 = (int((uv[0] + half) * sh), int((uv[1] + half) * sh))
                cv2.rectangle(img, p0, p1, c, -1, cv2.LINE_AA, 4)
        if clouds:
            mask = np.zeros((h, w), np.float32)
            for _ in range(rng.integers(5, 10)):
                cx, cy = rng.uniform(0, w), rng.uniform(0, h)
                axes = (int(rng.uniform(8, 20)), int(rng.uniform(4, 20)))
                cv2.ellipse(mask, (int(cx), int(cy)), axes, rng.uniform(0, 180), 0, 360, rng.uniform(0.65, 0.95), -1)
            mask = cv2.GaussianBlur(mask, (0, 0), 3)[..., None]
            img = (img * (1 - mask) + np.array([185, 205, 255]) * mask).astype(np.uint8)
        out[i] = img
    return out


def bench(quick: bool = False) -> list[dict]:
    cam = Camera(Scene(target=[40.0, 0.0]))
    heavy = load_occlusion("heavy")
    cam.render(np.zeros((1, 2)), occlusion=heavy)  # the cloud bank is built once per level and image size
    n, n_loop, repeat = (2000, 200, 2) if quick else (20000, 2000, 3)
    lead, fol = _positions(n)
    out = np.empty((n, *cam.shape, 3), np.uint8)
    clouds = heavy.sample(n, np.random.default_rng(1), cam.shape)
    clean = _best_rate(lambda: cam.render(lead, fol, out=out), n, repeat)
    cloudy = _best_rate(lambda: cam.render(lead, fol, heavy, clouds=clouds, out=out), n, repeat)
    rng = np.random.default_rng(2)
    loop_clean = _best_rate(lambda: opencv_loop(cam, lead[:n_loop], fol[:n_loop], False, rng), n_loop, 1)
    loop_cloudy = _best_rate(lambda: opencv_loop(cam, lead[:n_loop], fol[:n_loop], True, rng), n_loop, 1)
    sec = "render"
    return [
        {"section": sec, "case": f"batched clean, N={n}", "value": clean, "unit": "img/s", "note": "target >= 100k"},
        {"section": sec, "case": f"batched heavy clouds, N={n}", "value": cloudy, "unit": "img/s", "note": "target >= 30k"},
        {"section": sec, "case": "per-image OpenCV loop, clean", "value": loop_clean, "unit": "img/s", "note": ""},
        {"section": sec, "case": "per-image OpenCV loop, heavy clouds", "value": loop_cloudy, "unit": "img/s", "note": ""},
        {"section": sec, "case": "batched / loop, clean", "value": clean / loop_clean, "unit": "x", "note": ""},
        {"section": sec, "case": "batched / loop, heavy clouds", "value": cloudy / loop_cloudy, "unit": "x", "note": ""},
    ]
