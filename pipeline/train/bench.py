"""Benchmark (issues 4 and 10): Lightning `fit` img/s against a raw PyTorch loop of the same model and batch,
the achieved GFLOP/s of training (3x forward FLOPs) and its share of the machine's fp32 matmul ceiling
(`pipeline.bench.ceiling_gflops`), for the default map (conf/model/default.yaml) and the paper-width
network; then batched inference (`pipeline.perception.bench`)."""

from __future__ import annotations

import logging
import os
import time
import warnings

import lightning as L
import numpy as np
import torch
from torch.utils.data import BatchSampler, DataLoader, RandomSampler

from pipeline.allocator import ENV
from pipeline.bench import ceiling_gflops, side_by_side
from pipeline.config import build, compose
from pipeline.perception import bench as infer_bench
from pipeline.train.datamodule import BatchArrays
from pipeline.train.module import PerceptionMap


def _data(n: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    images = torch.from_numpy(rng.integers(0, 256, (n, 60, 100, 3), dtype=np.uint8))
    pos = torch.from_numpy(rng.uniform([-50, -30], [50, 30], (n, 2)).astype(np.float32))
    return images, pos


def raw_loop(model: PerceptionMap, images, pos, batch: int, steps: int) -> float:
    opt = torch.optim.Adam(model.parameters(), lr=1e-3)
    model.train()
    n = len(images)
    t0 = None
    for s in range(steps + 2):  # two warm-up steps
        if s == 2:
            t0 = time.perf_counter()
        idx = torch.randint(0, n, (batch,))
        target = (pos[idx] - model.center) / model.half_range
        # the position head, as the training step (a map's uncertainty head is fitted after the position network)
        loss = torch.nn.functional.mse_loss(model.position_outputs(model.prepare(images[idx])), target)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
    return steps * batch / (time.perf_counter() - t0)


def lightning_fit(model: PerceptionMap, images, pos, batch: int, steps: int) -> float:
    for name in ("lightning", "lightning.pytorch", "lightning.fabric"):
        logging.getLogger(name).setLevel(logging.ERROR)
    warnings.filterwarnings("ignore", ".*does not have many workers.*")
    ds = BatchArrays(images.numpy(), pos.numpy())
    loader = DataLoader(ds, sampler=BatchSampler(RandomSampler(ds), batch, drop_last=True), batch_size=None)

    class Timer(L.Callback):
        t0 = None

        def on_train_batch_start(self, trainer, pl_module, b, i):
            if trainer.global_step == 2 and self.t0 is None:  # after two warm-up steps, once (not per epoch)
                self.t0 = time.perf_counter()

    timer = Timer()
    trainer = L.Trainer(accelerator="cpu", devices=1, max_steps=steps + 2, logger=False, enable_checkpointing=False,
                        limit_val_batches=0, num_sanity_val_steps=0,
                        enable_progress_bar=False, enable_model_summary=False, callbacks=[timer])
    trainer.fit(model, train_dataloaders=loader)
    return steps * batch / (time.perf_counter() - timer.t0)


def _maps():
    """(label, constructor) of the benchmarked maps: the default config's map (BatchNorm, CoordConv) and the
    plain CNNs (no BatchNorm, no CoordConv) of 16/32/64 and 32/64/128 filters."""
    node = compose("train").model
    yield "default map 16/32/64 BN+CoordConv", lambda: PerceptionMap(build(node, "model"))
    plain = dict(lr=1e-3, batch_norm=False, coord_channels=False, dropout=0.5, schedule="constant", uncertainty="none")
    yield "plain 16/32/64", lambda: PerceptionMap.of(filters=(16, 32, 64), **plain)  # no BN, no CoordConv
    yield "plain 32/64/128", lambda: PerceptionMap.of(filters=(32, 64, 128), **plain)


def job_rate(kind: str, model_overrides: tuple[str, ...], batch: int, steps: int, seed: int = 0) -> float:
    """img/s of one training job (`kind`: raw | lightning) of the map `python -m pipeline.train <overrides>`
    builds, on random images (what `side_by_side` runs in each worker)."""
    torch.manual_seed(seed)
    model = PerceptionMap(build(compose("train", list(model_overrides)).model, "model"))
    images, pos = _data(batch * 8, seed)
    return (raw_loop if kind == "raw" else lightning_fit)(model, images, pos, batch, steps)


def schedule_rows(quick: bool = False) -> list[dict]:
    """Training as `make paper` runs it (docs/speed.md): two jobs side by side on one thread each, at the
    training batch, for make paper's map (keypoint head) and the paper's network (`model=paper`, batch 128 of
    `trainer=paper`), beside one job on every core; aggregate img/s as a share of the fp32 ceiling."""
    peak = ceiling_gflops("cpu", quick)
    steps = 3 if quick else 60
    rows = []
    for tag, overrides, batch in (("make paper's map (keypoint head)", ("model=keypoint",), 32),
                                  ("paper's network (model=paper)", ("model=paper",), 128)):
        flops = 3 * PerceptionMap(build(compose("train", list(overrides)).model, "model")).flops_per_image()
        alone = job_rate("raw", overrides, batch, steps)
        raw = sum(side_by_side(job_rate, ("raw", overrides, batch, steps)))
        lit = sum(side_by_side(job_rate, ("lightning", overrides, batch, steps)))
        rows += [
            {"section": "train", "case": f"{tag}, batch {batch}: one raw loop on every core", "value": alone,
             "unit": "img/s", "note": f"{flops * alone / 1e9 / peak:.0%} of ceiling"},
            {"section": "train", "case": f"{tag}, batch {batch}: 2 raw loops side by side (1 thread each)",
             "value": raw, "unit": "img/s", "note": f"sum of both; {raw / alone:.2f}x one loop on every core"},
            {"section": "train", "case": f"{tag}, batch {batch}: 2 Lightning fits side by side", "value": lit,
             "unit": "img/s", "note": f"Lightning / raw {lit / raw:.2f}x (target >= 0.90x)"},
            {"section": "train", "case": f"cpu: training side by side / ceiling, {tag}", "value": flops * lit / 1e9 / peak,
             "unit": "x", "note": "target >= 0.60x (3x fwd FLOPs)"},
        ]
    return rows + allocator_rows(steps)


def allocator_rows(steps: int) -> list[dict]:
    """One raw training loop of make paper's map (batch 32, one thread) in a fresh process with glibc's malloc
    defaults (`PIPELINE_MALLOC=system`) against one with the freed memory kept (`pipeline.allocator`, what every
    stage sets): the same arithmetic, fewer page faults."""
    args = ("raw", ("model=keypoint",), 32, steps)
    old = os.environ.get(ENV)
    try:
        os.environ[ENV] = "system"  # a spawned worker reads it when it calls keep_freed_memory
        system = side_by_side(job_rate, args, workers=1)[0]
    finally:
        if old is None:
            del os.environ[ENV]
        else:
            os.environ[ENV] = old
    kept = side_by_side(job_rate, args, workers=1)[0]
    return [{"section": "train", "case": "make paper's map, batch 32, 1 thread: glibc's malloc defaults", "value": system,
             "unit": "img/s", "note": "PIPELINE_MALLOC=system"},
            {"section": "train", "case": "same, freed memory kept (every stage: pipeline.allocator)", "value": kept,
             "unit": "img/s", "note": f"{kept / system:.2f}x the defaults (the same bytes)"}]


def bench(quick: bool = False) -> list[dict]:
    torch.set_num_threads(torch.get_num_threads())
    batch, steps = (64, 3) if quick else (128, 40)
    images, pos = _data(batch * 8)
    peak = ceiling_gflops("cpu", quick)
    rows = []
    for tag, make in _maps():
        torch.manual_seed(0)
        raw = raw_loop(make(), images, pos, batch, steps)
        torch.manual_seed(0)
        model = make()
        lit = lightning_fit(model, images, pos, batch, steps)
        gflops = 3 * model.flops_per_image() * lit / 1e9
        rows += [
            {"section": "train", "case": f"raw PyTorch loop, {tag}, batch {batch}", "value": raw, "unit": "img/s",
             "note": ""},
            {"section": "train", "case": f"Lightning fit, {tag}, batch {batch}", "value": lit, "unit": "img/s",
             "note": f"{gflops:.0f} GFLOP/s (3x fwd FLOPs)"},
            {"section": "train", "case": f"Lightning / raw, {tag}", "value": lit / raw, "unit": "x",
             "note": "target >= 0.85x"},
            {"section": "train", "case": f"cpu: training / ceiling, {tag}", "value": gflops / peak, "unit": "x",
             "note": "target >= 0.60x" if tag.startswith("default") else ""},
        ]
    return rows + schedule_rows(quick) + infer_bench.bench(quick=quick, ceiling=lambda dev: ceiling_gflops(dev, quick))
