"""Benchmark (issue 10): batched inference of the default perception map, per device present.

Rows: images/s of the training module in eval mode (the reference), of the folded network
(`FoldedPerceptionNet`: BatchNorm and input scaling folded into the convolutions, channels_last) and of the
folded network under `torch.compile` when a compiler is present; each as effective GFLOP/s (the default
map's forward FLOPs per image x images/s) and as a share of the device's fp32 matmul ceiling.
"""

from __future__ import annotations

import time

import numpy as np
import torch

from pipeline.bench import ceiling_gflops, side_by_side
from pipeline.config import build, compose
from pipeline.perception.maps import PerceptionMapPredictor
from pipeline.perception.network import PerceptionNet


def default_map(overrides: tuple[str, ...] = ()) -> PerceptionNet:
    """The default config's map (conf/model/default.yaml; `overrides`: e.g. `model=keypoint`) on the default 60x100
    camera, random weights with non-trivial BatchNorm statistics (same cost as a trained one)."""
    torch.manual_seed(0)
    model = PerceptionNet(build(compose("train", list(overrides)).model, "model"))
    for m in model.modules():
        if isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.2, 0.2)
            m.running_var.uniform_(0.5, 1.5)
    return model.eval()


def _rate(pm, images: np.ndarray, repeat: int) -> float:
    """images/s of `pm.predict` (uint8 host images in, float64 host coordinates out), best of `repeat`."""
    pm.predict(images)  # warm-up (threads, allocator, kernels)
    best = np.inf
    for _ in range(repeat):
        t0 = time.perf_counter()
        pm.predict(images)
        best = min(best, time.perf_counter() - t0)
    return len(images) / best


def folded_rate(overrides: tuple[str, ...], n: int, batch: int, repeat: int) -> float:
    """img/s of the folded map `overrides` build (one worker of `side_by_side`)."""
    model = default_map(overrides)
    images = np.random.default_rng(0).integers(0, 256, (n, *model.image_shape), dtype=np.uint8)
    return _rate(PerceptionMapPredictor(model, device="cpu", batch_size=batch), images, repeat)


def schedule_rows(quick: bool, ceiling) -> list[dict]:
    """Inference as `make paper`'s experiments run it: two jobs side by side on one thread each (docs/speed.md)."""
    n, batch, repeat = (512, 256, 1) if quick else (4096, 1024, 5)
    rows = []
    for tag, overrides in (("make paper's map (keypoint head)", ("model=keypoint",)), ("paper's network", ("model=paper",))):
        flops = default_map(overrides).flops_per_image()
        rate = sum(side_by_side(folded_rate, (overrides, n, batch, repeat)))
        rows.append({"section": "infer", "case": f"cpu: {tag}, folded, 2 jobs side by side (1 thread each)",
                     "value": rate, "unit": "img/s",
                     "note": f"{flops * rate / 1e9 / ceiling('cpu'):.0%} of ceiling; target >= 70%"})
    return rows


def devices() -> list[str]:
    return ["cpu"] + (["cuda"] if torch.cuda.is_available() else [])


def bench(quick: bool = False, ceiling=None) -> list[dict]:
    ceiling = ceiling or ceiling_gflops
    model = default_map()
    flops = model.flops_per_image()
    n, batch, repeat = (512, 256, 1) if quick else (4096, 1024, 5)
    images_np = np.random.default_rng(0).integers(0, 256, (n, *model.image_shape), dtype=np.uint8)
    rows = []
    for dev in devices():
        peak = ceiling(dev)
        variants = [("module (eval, reference)", PerceptionMapPredictor(model, device=dev, fold=False,
                                                                         batch_size=batch)),
                    ("folded BN + input scaling, channels_last", PerceptionMapPredictor(model, device=dev,
                                                                                       batch_size=batch))]
        if not quick:
            t0 = time.perf_counter()
            comp = PerceptionMapPredictor(model, device=dev, batch_size=batch, compile="auto")
            note = f"compile {time.perf_counter() - t0:.0f} s" if comp.compiled else "no compiler: eager"
            variants.append((f"folded + torch.compile ({note})", comp))
        rates = {}
        for label, pm in variants:
            rate = _rate(pm, images_np, repeat)
            rates[label] = rate
            g = flops * rate / 1e9
            rows.append({"section": "infer", "case": f"{dev}: {label}, batch {batch}", "value": rate,
                         "unit": "img/s", "note": f"{g:.0f} GFLOP/s = {g / peak:.0%} of ceiling"})
        ref = rates[variants[0][0]]
        best_label = max(rates, key=rates.get)
        g = flops * rates[best_label] / 1e9
        rows.append({"section": "infer", "case": f"{dev}: best inference / ceiling", "value": g / peak,
                     "unit": "x", "note": f"{best_label.split(' (')[0]}; {rates[best_label] / ref:.2f}x the module; "
                                          "target >= 0.70x on CPU"})
    return rows + schedule_rows(quick, ceiling)

