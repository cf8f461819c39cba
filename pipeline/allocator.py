"""glibc's malloc told to keep what a stage frees (docs/speed.md §12).

A training step, a PGD step or an inference chunk allocates the same few activation buffers of 1–400 MB again and
again. glibc's defaults hand them back to the kernel as soon as they are freed (large blocks are `mmap`ed and
unmapped; the heap's top is trimmed past a threshold of twice the last unmapped block), so every step faults its
buffers in again page by page: 5.1 million minor page faults in 120 training steps of make paper's map, a fifth of
the step in the kernel (glibc raises its mmap threshold as blocks are freed, but never past 32 MiB, and the
validation's batches are larger). With the heap kept (`M_TRIM_THRESHOLD` 1 GiB) and blocks up to 256 MiB served
from it (`M_MMAP_THRESHOLD`), the same steps run 1.25x faster (docs/speed.md §12).

Only the allocator's bookkeeping changes: the arithmetic, and so every output byte, is the same. Every stage calls
:func:`keep_freed_memory` when it starts (`pipeline.cli.stage_main`); `PIPELINE_MALLOC=system` in the environment
keeps glibc's defaults (to measure the difference). Elsewhere than glibc (macOS, musl) it does nothing. It adds to
the Makefile's `GLIBC_TUNABLES=glibc.malloc.hugetlb=1` (huge pages: fewer faults per byte mapped, only under `make`);
this one stops the mapping again, in every stage's process however it is started.
"""

from __future__ import annotations

import ctypes
import os
import sys

M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3  # glibc's <malloc.h>
TRIM_BYTES = 1 << 30  # free memory the heap's top keeps before giving it back to the kernel
MMAP_BYTES = 256 << 20  # blocks up to this come from the heap (a validation batch's activations included)
ENV = "PIPELINE_MALLOC"


def _glibc() -> bool:
    try:
        return os.confstr("CS_GNU_LIBC_VERSION") is not None  # "glibc 2.36"; musl has no such name
    except (ValueError, OSError):
        return False


def keep_freed_memory(trim: int = TRIM_BYTES, mmap: int = MMAP_BYTES) -> bool:
    """Set glibc's trim and mmap thresholds for this process (and the children it forks). True when both were
    set; False where the C library is not glibc, or `PIPELINE_MALLOC=system` asks for its defaults."""
    if os.environ.get(ENV, "").strip().lower() == "system":
        return False
    if not sys.platform.startswith("linux") or not _glibc():
        return False
    mallopt = getattr(ctypes.CDLL(None), "mallopt", None)
    if mallopt is None:
        return False
    mallopt.argtypes, mallopt.restype = (ctypes.c_int, ctypes.c_int), ctypes.c_int
    return bool(mallopt(M_TRIM_THRESHOLD, int(trim))) and bool(mallopt(M_MMAP_THRESHOLD, int(mmap)))
