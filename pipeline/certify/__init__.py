"""Certified error maps (SPEC §5.1-5.3): sound bounds of the perception error `e = l(h(p)) - p` over cells of
positions, propagated from the position itself through the camera and the network exactly as deployed.

Plain torch (no bound-propagation library runs on the project's torch), differentiable in the network's weights
so that a training loss can use the bound::

    from pipeline.certify import prepare, certified_error_bound
    prep = prepare(model, camera, kappa=0.0)          # deployed net (BatchNorm folded, eval semantics) and the
                                                      # static image's activations; rebuild after a weight update
    b = certified_error_bound(prep, cells, mode="crown")   # cells: (N, 4) = (x0, x1, y0, y1), world units
    b.lower, b.upper   # (N, 2): lower <= l(h(p)) - p <= upper per coordinate, for every p in the cell
    b.eps              # (N,): the Euclidean bound max |e| over the cell

- `mode`: `ibp` (intervals; cheapest: the warm-up of certified training), `forward` (forms linear in the
  position through every layer), `crown` (forward, then a backward pass from the output; tightest).
- What the bound covers: every image the camera renders for a position of the cell, the `uint8` rounding
  included (`±0.5` level on fractional-coverage pixels), and under `kappa > 0` every image within `kappa`
  levels of it per pixel and channel (clipped to `[0, 255]`: the pixel attack's set).
- Models: position maps (`PerceptionNet`, any filters, BatchNorm and CoordConv or not, `clamp` or not) with the
  flat head without a hidden layer, or the keypoint head (:mod:`.keypoint`: its outputs bounded on the last
  block's window, forward and, with `crown`, by a backward pass per output; the softmax-weighted mean bounded
  exactly over their intervals); pose maps with the keypoint head and the attention heading head, over cells of
  poses `(N, 6) = (x0, x1, y0, y1, th0, th1)` (the triangle marker, :func:`.renderer.marker_coverage`; the heading
  error `b.heading (N,)`, :mod:`.heading`). Float32 by default; pass `dtype=torch.float64` to `prepare` for
  bounds free of the bound computation's own float32 rounding (the deployed network itself runs in float32:
  `prepare(..., float_margin=m)` moves every bound out by `m` world units for its rounding, as the stages do with
  their `float_margin`, docs/certify.md "Float32"; 0 by default: the network in exact arithmetic).
- Cost: one static pass per `prepare`; per cell only the cone of activations the robot's pixels reach
  (:mod:`.cone`), batched over cells (no per-cell Python).

Modules: :mod:`.renderer` (the camera inside the bound), :mod:`.deployed` (the folded network, the static
pass), :mod:`.cone` (forward forms through the cone), :mod:`.crown` (backward pass), :mod:`.keypoint` (the
keypoint head), :mod:`.heading` (a pose map's heading), :mod:`.bounds` (the API).
"""

__all__ = ["MODES", "ErrorBound", "Prepared", "certified_error_bound", "prepare"]


def __getattr__(name: str):
    """The API from :mod:`.bounds`, imported on first use: the stage's checks (`pipeline.certify.checks`) answer bad
    input without importing torch and lightning (1 s instead of 4.5 s)."""
    if name in __all__:
        from pipeline.certify import bounds  # torch and lightning: not for the checks

        return getattr(bounds, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
