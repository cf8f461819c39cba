"""Inference on the CPU in chunks whose activations stay below glibc's mmap threshold (issue 46: the loop's
inference at the machine's speed). At 1,024 images a call every activation was mmap'ed and unmapped per call, and
the page faults cost more than the convolutions; `cpu_chunk` sizes the chunk from the network itself. The chunk
must change no output beyond float32 rounding (the certificate covers the network, not its batching), and at
the default chunk none at all on the maps measured."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from pipeline.perception.maps import CHUNK_BYTES, PerceptionMapPredictor, activation_bytes, cpu_chunk


def test_the_chunk_keeps_the_largest_activation_under_the_threshold(production):
    """`activation_bytes` against the convolutions' real outputs (forward hooks on one image)."""
    model, _, camera = production
    sizes = []
    hooks = [m.register_forward_hook(lambda _m, _i, out: sizes.append(out[0].numel() * 4))
             for m in model.features if isinstance(m, nn.Conv2d)]
    try:
        with torch.no_grad():
            model(torch.from_numpy(camera.render(np.array([[0.0, 10.0]]))).float())
    finally:
        for h in hooks:
            h.remove()
    assert sizes and max(sizes) == activation_bytes(model)
    k = cpu_chunk(model)
    assert k * max(sizes) <= CHUNK_BYTES < (k + 1) * max(sizes)
    assert PerceptionMapPredictor(model).batch_size == k


def test_the_chunk_changes_outputs_by_float32_rounding_at_most(production):
    """Make paper's map at production size, 300 frames (chunks end mid-batch), positions and uncertainty: the
    default chunk gives the bits of one call of 1,024 images (measured on one and two threads); an odd or small
    chunk (37, 8) may differ by float32 rounding (oneDNN picks other kernels for small batches on one thread:
    measured 2e-6 to 8e-6 world units), never more than the certificate's float slack."""
    model, _, camera = production
    rng = np.random.default_rng(46)
    images = camera.render(np.column_stack([rng.uniform(-45, 45, 300), rng.uniform(-25, 25, 300)]))
    ref = PerceptionMapPredictor(model, batch_size=1024)._run(images)
    assert ref.shape == (300, 4)
    np.testing.assert_array_equal(PerceptionMapPredictor(model)._run(images), ref)
    for chunk in (37, 8):
        np.testing.assert_allclose(PerceptionMapPredictor(model, batch_size=chunk)._run(images), ref, rtol=0,
                                   atol=1e-4)
