"""Benchmark: error-map points/s (render + infer, batched) vs raw inference of the same model (issue 5).

The model is the newest trained perception map under outputs/models (policies there are skipped), else a fresh
untrained `PerceptionNet` (same architecture, same cost).
"""

from __future__ import annotations

import time

import numpy as np
import torch

from pipeline.control import Scene
from pipeline.errormap.estimates import arena_grid, error_field
from pipeline.perception.maps import PerceptionMapPredictor, newest_perception_map
from pipeline.perception.network import PerceptionNet
from pipeline.render import Camera, load_occlusion


def _predictor(models_dir=None):
    """`(predict, camera, label)`: the newest trained perception map's under `models_dir` (default
    `outputs/models`), else an untrained one's (the same cost)."""
    pmap, note = newest_perception_map(models_dir)
    if pmap is not None:
        return pmap.predict, pmap.camera(), note
    # the predictor, not the raw network: the default map has four outputs (position + its variance)
    torch.manual_seed(0)
    pm = PerceptionMapPredictor(PerceptionNet.of())
    return pm.predict, Camera(Scene(target=[40.0, 0.0])), note + "; untrained PerceptionNet (same cost)"


def _best(fn, repeat: int) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        best = min(best, time.perf_counter() - t0)
    return best


def bench(quick: bool = False) -> list[dict]:
    predict, camera, label = _predictor()
    n, batch, repeat = (1024, 512, 1) if quick else (4096, 2048, 3)
    pts, _, _, _ = arena_grid(camera.arena, 0.5)
    pts = pts[np.random.default_rng(0).choice(len(pts), n, replace=False)]
    predict(camera.render(pts[:batch]))  # warm-up at full batch size (threads, allocator)
    rows = []
    for level in ("none", "heavy"):
        occ = load_occlusion(level)
        images = camera.render(pts, occlusion=occ, rng=np.random.default_rng(1))

        def render(p, rng, occ=occ):
            return camera.render(p, occlusion=occ, rng=rng)

        t_raw = t_full = np.inf
        for _ in range(repeat):  # interleaved, best of `repeat`: both see the same machine load
            t_raw = min(t_raw, _best(lambda images=images: [predict(images[s : s + batch])
                                                            for s in range(0, n, batch)], 1))
            t_full = min(t_full, _best(lambda render=render: error_field(
                predict, render, pts, batch=batch, rng=np.random.default_rng(1)), 1))
        raw, full = n / t_raw, n / t_full
        rows += [
            {"section": "errormap", "case": f"raw inference, {level} images (N={n}, batch {batch})", "value": raw,
             "unit": "images/s", "note": label},
            {"section": "errormap", "case": f"error map (render + infer), {level}", "value": full,
             "unit": "points/s", "note": ""},
            {"section": "errormap", "case": f"error map / raw inference, {level}", "value": full / raw, "unit": "x",
             "note": "target >= 0.8x"},
        ]
    return rows
