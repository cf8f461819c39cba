"""`make bench`: every area's benchmark in one run, printed as one table.

Each area exposes `pipeline.<area>.bench.bench(quick=False) -> list[dict]` (rows with section, case, value,
unit, note). Absolute numbers depend on the machine and its load; ratios are measured in the same run.

The machine's ceiling is measured first: the fp32 GFLOP/s of a large matrix multiply per device present
(`ceiling_gflops`, measured once per run and cached), so that training and inference rows can be given as a
share of it.
"""

from __future__ import annotations

import argparse
import functools
import importlib
import os
import sys
import time

import torch

from pipeline.allocator import keep_freed_memory

AREAS = ("sim", "data", "train", "errormap", "experiments", "envs")


@functools.cache
def ceiling_gflops(device: str = "cpu", quick: bool = False) -> float:
    """fp32 GFLOP/s of a large square matrix multiply on `device` (best of several): what the device can do."""
    n, repeat = (1024, 3) if quick else ((2048, 8) if device == "cpu" else (8192, 10))
    a = torch.randn(n, n, device=device)
    b = torch.randn(n, n, device=device)
    best = float("inf")
    for _ in range(repeat + 1):  # the first multiply is a warm-up
        if device != "cpu":
            torch.cuda.synchronize()
        t0 = time.perf_counter()
        a @ b
        if device != "cpu":
            torch.cuda.synchronize()
        best = min(best, time.perf_counter() - t0)
    return 2 * n**3 / best / 1e9


def _worker(fn, args, threads: int, barrier, queue) -> None:
    keep_freed_memory()  # as every stage does when it starts (a spawned process starts with glibc's defaults)
    torch.set_num_threads(threads)
    barrier.wait()  # every worker starts its timed work together
    queue.put(fn(*args))


def side_by_side(fn, args: tuple, workers: int = 2, threads: int = 1) -> list:
    """`fn(*args)` in `workers` processes at once, `threads` torch threads each (how `make paper` runs its jobs:
    `pipeline.jobs`); the list of their results. `fn` must be importable (a module-level function)."""
    import multiprocessing as mp

    ctx = mp.get_context("spawn")
    barrier, queue = ctx.Barrier(workers), ctx.Queue()
    procs = [ctx.Process(target=_worker, args=(fn, args, threads, barrier, queue)) for _ in range(workers)]
    for p in procs:
        p.start()
    out = [queue.get() for _ in procs]
    for p in procs:
        p.join()
    return out


def ceiling_rows(quick: bool = False) -> list[dict]:
    rows = []
    for dev in ["cpu"] + (["cuda"] if torch.cuda.is_available() else []):
        g = ceiling_gflops(dev, quick)
        rows.append({"section": "ceiling", "case": f"{dev}: fp32 matmul ({torch.get_num_threads()} threads)"
                     if dev == "cpu" else f"{dev}: fp32 matmul ({torch.cuda.get_device_name()})",
                     "value": g, "unit": "GFLOP/s", "note": "the machine's ceiling; shares below are of this"})
    return rows


def collect(areas=AREAS, quick: bool = False) -> list[dict]:
    t0 = time.perf_counter()
    rows = ceiling_rows(quick)  # measured first, on a quiet process
    print(f"[bench] ceiling: {len(rows)} rows in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
    for area in areas:
        try:
            mod = importlib.import_module(f"pipeline.{area}.bench")
        except ModuleNotFoundError as err:
            if err.name and err.name.startswith(f"pipeline.{area}"):
                continue  # that area has no benchmark
            raise
        t0 = time.perf_counter()
        area_rows = mod.bench(quick=quick)
        print(f"[bench] {area}: {len(area_rows)} rows in {time.perf_counter() - t0:.1f} s", file=sys.stderr)
        rows += area_rows
    return rows


def format_table(rows: list[dict]) -> str:
    head = ("section", "case", "value", "unit", "note")
    cells = [[str(r.get("section", "")), str(r.get("case", "")), _fmt(r.get("value")), str(r.get("unit", "")),
              str(r.get("note", ""))] for r in rows]
    widths = [max(len(h), *(len(c[i]) for c in cells)) if cells else len(h) for i, h in enumerate(head)]
    line = lambda c: "| " + " | ".join(x.ljust(w) for x, w in zip(c, widths)) + " |"  # noqa: E731
    sep = "|" + "|".join("-" * (w + 2) for w in widths) + "|"
    return "\n".join([line(head), sep, *(line(c) for c in cells)])


def _fmt(v) -> str:
    if isinstance(v, int | float):
        return f"{v:,.3g}" if abs(v) < 1000 else f"{v:,.0f}"
    return str(v)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("areas", nargs="*", default=list(AREAS), help=f"subset of {AREAS}")
    ap.add_argument("--quick", action="store_true", help="tiny sizes (seconds), for smoke tests")
    args = ap.parse_args(argv)
    unknown = set(args.areas) - set(AREAS)
    if unknown:
        print(f"error: unknown bench area(s) {sorted(unknown)}; choose from {AREAS}", file=sys.stderr)
        return 2
    kept = keep_freed_memory()
    print(f"# bench on {os.cpu_count()} CPU cores (GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '')}; "
          f"freed memory kept: {kept}, pipeline.allocator)")
    print(format_table(collect(args.areas, quick=args.quick)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
