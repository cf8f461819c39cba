"""Benchmarks: batched hybrid simulator vs a per-agent Python loop of the same controller (issue 2 §6), and
the cost of the continuous-time model (`sim.model: continuous`) per agent-second against the sampled one
(issue 12: target <= 3x)."""

from __future__ import annotations

import time

import numpy as np

from pipeline.control import HybridController, Scene, in_diamond
from pipeline.control.fields import random_scene
from pipeline.sim import CameraSettings, SimSettings, simulate


def _agents(scene: Scene, n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    (x0, x1), (y0, y1) = scene.bounds
    pts = rng.uniform([x0 + 2, y0 + 2], [x1 - 2, y1 - 2], size=(2 * n, 2))
    return pts[~in_diamond(scene, pts)][:n]


def _rate(scene, x0, steps, period, repeat=2) -> float:
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        simulate(scene, HybridController(scene), x0,
                 sim=SimSettings(dt=0.01, horizon=steps * 0.01, stop_on_success=False),
                 camera=CameraSettings(period=period), record=False)
        best = min(best, time.perf_counter() - t0)
    return len(x0) * steps / best


def _agent_seconds(scene, x0, horizon, model, repeat=2) -> float:
    """Agent-seconds of simulated time per wall second (best of `repeat`), no recording, no early stop."""
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        simulate(scene, HybridController(scene), x0,
                 sim=SimSettings(dt=0.01, horizon=horizon, stop_on_success=False, model=model),
                 camera=CameraSettings(period=0.05), record=False)
        best = min(best, time.perf_counter() - t0)
    return len(x0) * horizon / best


def bench_models(quick: bool = False) -> list[dict]:
    """Continuous vs sampled (20 Hz camera) on random starts of the default scene, clean, 10 s of each arc."""
    scene = Scene(target=[40.0, 0.0])
    n, horizon = (500, 2.0) if quick else (10_000, 10.0)
    x0 = _agents(scene, n)
    sampled = _agent_seconds(scene, x0, horizon, "sampled")
    continuous = _agent_seconds(scene, x0, horizon, "continuous")
    return [
        {"section": "simulator", "case": f"sampled, 20 Hz camera, N={n}, {horizon:g} s", "value": sampled / 1e3,
         "unit": "k agent-s/s", "note": ""},
        {"section": "simulator", "case": f"continuous (rosenbrock23), N={n}, {horizon:g} s",
         "value": continuous / 1e3, "unit": "k agent-s/s", "note": ""},
        {"section": "simulator", "case": "cost per agent-second, continuous / sampled", "value": sampled / continuous,
         "unit": "x", "note": "target <= 3x"},
    ]


def _field(M: int) -> Scene:
    """The default scene (M = 1) or a seeded random valid field of M discs (SPEC §3.6) in a 200 x 120 arena."""
    if M == 1:
        return Scene(target=[40.0, 0.0])
    return random_scene(n_obstacles=M, seed=M, radius_range=[2.0, 3.0], target=[80.0, 0.0], keep_free=[],
                        arena={"x": [-100.0, 100.0], "y": [-60.0, 60.0]})


def bench_obstacles(quick: bool = False) -> list[dict]:
    """The hybrid controller's cost per agent-step against the number of discs M (issue 19: at most linear in M):
    the controller evaluated every step (camera period = dt), the same random starts, no early stop."""
    n, steps = (500, 20) if quick else (5000, 100)
    rows, base = [], None
    for M in (1, 3, 5, 10):
        scene = _field(M)
        x0 = _agents(scene, n)
        rate = _rate(scene, x0, steps, 0.01)
        base = base or rate
        rows.append({"section": "simulator", "case": f"hybrid, M={M} discs, N={len(x0)}, controller every step",
                     "value": base / rate, "unit": "x (cost / M=1)",
                     "note": f"{rate / 1e6:.2f} M agent-steps/s; linear in M: <= {M}x"})
    return rows


def bench(quick: bool = False) -> list[dict]:
    scene = Scene(target=[40.0, 0.0])
    n, steps, n_loop, loop_steps = (1000, 20, 5, 20) if quick else (10_000, 200, 20, 200)
    x0 = _agents(scene, n)
    rows = []
    for period, label in ((0.01, "controller every step"), (0.05, "camera 20 Hz (default)")):
        batched = _rate(scene, x0, steps, period)
        t0 = time.perf_counter()
        for i in range(n_loop):  # the same controller and simulator, one agent at a time
            simulate(scene, HybridController(scene), x0[i : i + 1],
                     sim=SimSettings(dt=0.01, horizon=loop_steps * 0.01, stop_on_success=False),
                     camera=CameraSettings(period=period), record=False)
        loop = n_loop * loop_steps / (time.perf_counter() - t0)
        rows += [
            {"section": "simulator", "case": f"batched N={n}, {label}", "value": batched / 1e6, "unit": "M agent-steps/s",
             "note": "target >= 20 M/s"},
            {"section": "simulator", "case": f"per-agent loop, {label}", "value": loop / 1e6, "unit": "M agent-steps/s",
             "note": ""},
            {"section": "simulator", "case": f"batched / loop, {label}", "value": batched / loop, "unit": "x",
             "note": "target >= 100x"},
        ]
    return rows + bench_models(quick) + bench_obstacles(quick)
