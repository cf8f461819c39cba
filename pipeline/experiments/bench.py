"""Benchmark (issue 6 §5): closed-loop agent-frames/s with the CNN in the loop at N agents, against
(a) the raw batched inference throughput of the same model and (b) a per-agent loop that renders one
image and calls the model once per agent per frame (what the authors' code does)."""

from __future__ import annotations

import time

import torch

from pipeline.bench import ceiling_gflops
from pipeline.control import HybridController, Scene
from pipeline.perception.maps import PerceptionMapPredictor, newest_perception_map
from pipeline.perception.measure import CameraMeasure
from pipeline.perception.network import PerceptionNet
from pipeline.render import Camera
from pipeline.sim import CameraSettings, SimSettings, simulate
from pipeline.sim.starts import Random


def _map():
    """The newest trained perception map (make run's, folded as the loop deploys it), else a fresh one of the
    default architecture (the same cost)."""
    pm, note = newest_perception_map()
    if pm is not None:
        return pm, note
    torch.manual_seed(0)
    net = PerceptionNet.of(filters=(16, 32, 64), batch_norm=True, coord_channels=False, dropout=0.5, lr=1e-3,
                        schedule="constant", uncertainty="none")
    return PerceptionMapPredictor(net), note + "; untrained 16/32/64 map"


def bench(quick: bool = False) -> list[dict]:
    n, frames, loop_agents, loop_frames = (100, 3, 5, 2) if quick else (1000, 20, 20, 5)
    pm, which = _map()
    cam = pm.camera() if pm.manifest else Camera(Scene(target=[40.0, 0.0]))
    scene = cam.scene
    x0 = Random(n=n, seed=0, margin=2.0)(scene)
    dt, period = 0.01, 0.05

    # (a) raw batched inference on pre-rendered images
    imgs = cam.render(x0)
    pm.predict(imgs[:64])
    t0 = time.perf_counter()
    reps = max(1, frames // 4)
    for _ in range(reps):
        pm.predict(imgs)
    raw = reps * n / (time.perf_counter() - t0)

    # closed loop: every frame renders all N agents and infers them in one batch
    measure = CameraMeasure(cam, pm)
    t0 = time.perf_counter()
    simulate(scene, HybridController(scene), x0, sim=SimSettings(dt=dt, horizon=frames * period, stop_on_success=False),
             camera=CameraSettings(period=period), measure=measure, record=False)
    loop_s = time.perf_counter() - t0
    closed = measure.images / loop_s

    # (b) per-agent loop: one image rendered and one model call per agent per frame
    t0 = time.perf_counter()
    for _ in range(loop_frames):
        for i in range(loop_agents):
            pm.predict(cam.render(x0[i : i + 1]))
    per_agent = loop_frames * loop_agents / (time.perf_counter() - t0)
    # no batching does better than the fp32 ceiling: the ratio's bound is the ceiling's image rate over the loop's
    flops = pm.model.flops_per_image()
    bound = ceiling_gflops("cpu", quick) * 1e9 / flops / per_agent
    return [
        {"section": "closed loop", "case": f"raw batched inference ({which})", "value": raw, "unit": "img/s", "note": ""},
        {"section": "closed loop", "case": f"CNN in the loop, N={n}, {frames} frames", "value": closed,
         "unit": "agent-frames/s", "note": ""},
        {"section": "closed loop", "case": "per-agent loop (render 1 + infer 1)", "value": per_agent,
         "unit": "agent-frames/s", "note": ""},
        {"section": "closed loop", "case": "closed loop / raw inference", "value": closed / raw, "unit": "x",
         "note": "target >= 0.8x"},
        {"section": "closed loop", "case": "closed loop / per-agent loop", "value": closed / per_agent, "unit": "x",
         "note": f"target >= 10x; at most {bound:.1f}x here (below)"},
        {"section": "closed loop", "case": "inference at the fp32 ceiling / per-agent loop", "value": bound,
         "unit": "x", "note": f"{flops / 1e6:.1f} MFLOP per image: the ratio's bound on this machine"},
    ]
