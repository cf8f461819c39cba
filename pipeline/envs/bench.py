"""Benchmark (`make bench`): the vector environment (N agents in one batched call of the plant and the renderer)
against N single environments stepped one by one, per agent-step (issue 31: target >= 20x at N = 1000)."""

from __future__ import annotations

import time

import numpy as np

from pipeline.envs.navigate import NavigateEnv, NavigateVectorEnv, objects


def _actions(n: int, steps: int, obj, seed: int = 0) -> np.ndarray:
    """Velocities towards +x with a random transverse part (few agents stop within the run), as the env's
    normalised actions (`u / scale`)."""
    rng = np.random.default_rng(seed)
    return np.stack([np.full((steps, n), 4.0), rng.uniform(-3.0, 3.0, (steps, n))], -1) / obj.scale


def vector_rate(n: int, steps: int, obj=None) -> float:
    """Agent-steps per second of one :class:`NavigateVectorEnv` of `n` agents (autoreset on)."""
    obj = obj or objects()
    venv = NavigateVectorEnv(n, objects_=obj)
    venv.reset(seed=0)
    acts = _actions(n, steps, obj)
    t0 = time.perf_counter()
    for k in range(steps):
        venv.step(acts[k])
    return n * steps / (time.perf_counter() - t0)


def single_rate(n: int, steps: int, obj=None) -> float:
    """Agent-steps per second of `n` :class:`NavigateEnv` stepped in a Python loop (reset when one ends)."""
    obj = obj or objects()
    envs = [NavigateEnv(objects_=obj) for _ in range(n)]
    for i, env in enumerate(envs):
        env.reset(seed=i)
    acts = _actions(n, steps, obj)
    t0 = time.perf_counter()
    for k in range(steps):
        for i, env in enumerate(envs):
            _, _, term, trunc, _ = env.step(acts[k, i])
            if term or trunc:
                env.reset()
    return n * steps / (time.perf_counter() - t0)


def bench(quick: bool = False) -> list[dict]:
    n, steps = (100, 3) if quick else (1000, 20)
    obj = objects()
    vec, single = vector_rate(n, steps, obj), single_rate(n, steps, obj)
    return [
        {"section": "envs", "case": f"vector env, N={n}, {steps} frames (one batched plant + render call)",
         "value": vec / 1e3, "unit": "k agent-steps/s", "note": ""},
        {"section": "envs", "case": f"{n} single envs stepped in a loop", "value": single / 1e3,
         "unit": "k agent-steps/s", "note": ""},
        {"section": "envs", "case": "per agent-step, vector / single", "value": vec / single, "unit": "x",
         "note": "target >= 20x"},
    ]
