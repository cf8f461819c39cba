"""ε-error maps of a perception map (SPEC §2, the paper's Assumption 1 and Lemma 1) as pure numpy.

For grid positions `p`, `E(p) = l(h(p)) - p` is the error of the perception map `l` on the image `h(p)`.
This module measures it (`error_field`, batched, with the camera and the map injected as callables),
summarises it (`error_stats`), estimates the Lipschitz constant of `E` from neighbouring grid points
(`lipschitz_estimate`), computes the Assumption-1 coverage set

    S^L_eps = U_d { p in p_d + r_cov B : |l(theta_d) - p_d| + L |p - p_d| <= eps }

through its exact per-point threshold `eps_min(p)` (`coverage_eps_min`: `p` is in `S^L_eps` iff
`eps_min(p) <= eps`), fits the error model of Dean et al., "Robust guarantees for perception-based
control" (`|e|_inf <= eps_C |p|_inf + eps_eta`, `dean_fit`), and bins errors against the distance to
the nearest training sample (`binned_stats`).

No I/O, no Hydra, no torch: every function works on `(N, 2)` arrays.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor

import numpy as np

# The 4 neighbour offsets (row, col) that visit each horizontal, vertical and diagonal pair once.
NEIGHBOUR_OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1))
# With these 8 directions the largest quotient of a linear field A p is at least cos(22.5°) ||A||_2.
DIRECTION_COVERAGE = math.cos(math.pi / 8)


# --------------------------------------------------------------------------------------------- grid
def arena_grid(arena, step: float) -> tuple[np.ndarray, tuple[int, int], np.ndarray, np.ndarray]:
    """Cell-centred grid of spacing `step` over `arena = ((x0, x1), (y0, y1))`.

    Returns `(points (ny*nx, 2), (ny, nx), xs (nx,), ys (ny,))`; points are row-major with `y`
    ascending, so `values.reshape(ny, nx)` is an image for `imshow(origin="lower")`. The grid is centred
    in the arena (step 0.5 on the default 100 x 60 arena: 200 x 120 = 24 000 points, x = -49.75 ... 49.75).
    """
    (x0, x1), (y0, y1) = arena
    step = float(step)
    if not (math.isfinite(step) and step > 0):
        raise ValueError(f"grid step must be > 0, got {step!r}")
    nx = int(math.floor((x1 - x0) / step + 1e-9))
    ny = int(math.floor((y1 - y0) / step + 1e-9))
    if nx < 2 or ny < 2:
        raise ValueError(f"grid step {step} leaves fewer than 2 points per axis in the arena {arena}")
    xs = x0 + ((x1 - x0) - (nx - 1) * step) / 2 + step * np.arange(nx)
    ys = y0 + ((y1 - y0) - (ny - 1) * step) / 2 + step * np.arange(ny)
    gx, gy = np.meshgrid(xs, ys, indexing="xy")
    return np.column_stack([gx.ravel(), gy.ravel()]), (ny, nx), xs, ys


# ------------------------------------------------------------------------------------ error field
def error_field(
    predict: Callable[[np.ndarray], np.ndarray],
    render: Callable[[np.ndarray, np.random.Generator | None], np.ndarray],
    points: np.ndarray,
    *,
    batch: int = 2048,
    rng: np.random.Generator | None = None,
    progress: bool = False,
    desc: str = "error map",
    overlap: bool = True,
    heading: float | None = None,
) -> np.ndarray:
    """`E(p) = l(h(p)) - p` for `(N, 2)` points, rendered and inferred in chunks of `batch`.

    `render(points_chunk, rng) -> images` plays `h` (its random draws, e.g. clouds, come from `rng`, used
    by the chunks in order); `predict(images) -> (n, 2)` plays `l`. With `overlap`, the next chunk is
    rendered on a worker thread while the current one is inferred (numpy and torch release the GIL).
    A pose map (`heading`: the heading every image shows, radians; `predict -> (n, 3)`): `(N, 3)`, the
    heading error wrapped to `(-π, π]` last.
    """
    points = np.asarray(points, dtype=float)
    n = len(points)
    if heading is not None:
        points = np.column_stack([points, np.full(n, float(heading))])
    batch = max(1, int(batch))
    starts = list(range(0, n, batch))
    out = np.empty((n, points.shape[1]), dtype=float)
    bar = _progress(n, desc, progress)
    try:
        if overlap and len(starts) > 1:
            with ThreadPoolExecutor(max_workers=1) as pool:
                future = pool.submit(render, points[0:batch, :2], rng)
                for i, s in enumerate(starts):
                    images = future.result()
                    if i + 1 < len(starts):  # sequential on one worker: the rng is consumed in chunk order
                        nxt = starts[i + 1]
                        future = pool.submit(render, points[nxt : nxt + batch, :2], rng)
                    out[s : s + batch] = _predict_chunk(predict, images, points[s : s + batch])
                    bar.update(min(batch, n - s))
        else:
            for s in starts:
                images = render(points[s : s + batch, :2], rng)
                out[s : s + batch] = _predict_chunk(predict, images, points[s : s + batch])
                bar.update(min(batch, n - s))
    finally:
        bar.close()
    return out


def _predict_chunk(predict, images, pts: np.ndarray) -> np.ndarray:
    pred = np.asarray(predict(images), dtype=float)
    if pred.shape != pts.shape:
        raise ValueError(f"perception map returned shape {pred.shape} for {len(pts)} images, expected {pts.shape}")
    err = pred - pts
    if pts.shape[1] == 3:  # a pose: the heading error wrapped to (-pi, pi]
        err[:, 2] = np.angle(np.exp(1j * err[:, 2]))
    return err


def _progress(total: int, desc: str, enabled: bool):
    """A bar on a terminal, one line every few seconds in a log (pipeline.progress); `enabled=False`: silent."""
    from pipeline.progress import progress

    return progress(total=total, desc=desc, unit="pt", enabled=enabled)


# ---------------------------------------------------------------------------------------- summaries
def error_stats(mag: np.ndarray) -> dict:
    """n, mean, median, p95, max and RMS of error magnitudes (NaN for an empty set)."""
    mag = np.asarray(mag, dtype=float).ravel()
    if mag.size == 0:
        return {"n": 0, "mean": math.nan, "median": math.nan, "p95": math.nan, "max": math.nan, "rms": math.nan}
    return {
        "n": int(mag.size),
        "mean": float(mag.mean()),
        "median": float(np.median(mag)),
        "p95": float(np.percentile(mag, 95)),
        "max": float(mag.max()),
        "rms": float(np.sqrt(np.mean(mag**2))),
    }


# ---------------------------------------------------------------------------------------- Lipschitz
def difference_quotients(field: np.ndarray, step: float, mask: np.ndarray | None = None):
    """`|E(p) - E(p')| / |p - p'|` over horizontal, vertical and diagonal grid neighbours.

    `field` is `(ny, nx, 2)` on a grid of spacing `step`; pairs with an endpoint outside `mask` (or a
    non-finite value) are dropped. Yields `(offset, quotients (ny', nx'), valid (ny', nx'), slices)` per
    direction, where `slices = (a, b)` index the two endpoints in the `(ny, nx)` grid.
    """
    field = np.asarray(field, dtype=float)
    ny, nx = field.shape[:2]
    finite = np.isfinite(field).all(axis=-1)
    ok = finite if mask is None else finite & np.asarray(mask, dtype=bool)
    for di, dj in NEIGHBOUR_OFFSETS:
        if dj >= 0:
            a = (slice(0, ny - di), slice(0, nx - dj))
            b = (slice(di, ny), slice(dj, nx))
        else:
            a = (slice(0, ny - di), slice(-dj, nx))
            b = (slice(di, ny), slice(0, nx + dj))
        dist = step * math.hypot(di, dj)
        q = np.linalg.norm(field[a] - field[b], axis=-1) / dist
        valid = ok[a] & ok[b]
        yield (di, dj), q, valid, (a, b)


def lipschitz_estimate(field: np.ndarray, step: float, mask: np.ndarray | None = None, q: float = 99.0) -> dict:
    """Estimate of the Lipschitz constant `L` of `E` from neighbouring grid points.

    Returns `{"max", "p<q>" (percentile q of the quotients), "n_pairs", "slope" (ny, nx)}`; `slope` is the
    local slope map, the largest quotient over the (up to 8) neighbour pairs of each point (NaN where a
    point has no valid pair). For a linear field `E(p) = A p + b` the estimate lies in
    `[cos(22.5°) ||A||_2, ||A||_2]` (8 directions sampled); for `E` with several draws per point pass
    `field` of shape `(K, ny, nx, 2)`: the quotients of all draws are pooled.
    """
    field = np.asarray(field, dtype=float)
    fields = field[None] if field.ndim == 3 else field
    ny, nx = fields.shape[1:3]
    slope = np.full((ny, nx), -np.inf)
    pooled = []
    for f in fields:
        for _, quot, valid, (a, b) in difference_quotients(f, step, mask):
            vals = np.where(valid, quot, -np.inf)
            slope[a] = np.fmax(slope[a], vals)
            slope[b] = np.fmax(slope[b], vals)
            pooled.append(quot[valid])
    allq = np.concatenate(pooled) if pooled else np.empty(0)
    slope[~np.isfinite(slope)] = np.nan
    if allq.size == 0:
        return {"max": math.nan, f"p{q:g}": math.nan, "n_pairs": 0, "slope": slope}
    return {"max": float(allq.max()), f"p{q:g}": float(np.percentile(allq, q)), "n_pairs": int(allq.size),
            "slope": slope}


# ----------------------------------------------------------------------------------------- coverage
def min_plus_within(
    queries: np.ndarray,
    samples: np.ndarray,
    values: np.ndarray,
    slope: float,
    radius: float | None,
    *,
    budget: int = 4_000_000,
) -> tuple[np.ndarray, np.ndarray]:
    """For each query `p`: `min_d values_d + slope |p - p_d|` over samples with `|p - p_d| <= radius`.

    Returns `(minimum (Nq,), argmin (Nq,))`, `inf` / `-1` where no sample lies within `radius`
    (`radius=None`: no limit). Vectorised over x-sorted strips: each chunk of x-sorted queries meets only
    the samples whose x lies within `radius` of the chunk, in distance blocks of at most `budget` pairs.
    """
    queries = np.asarray(queries, dtype=float).reshape(-1, 2)
    samples = np.asarray(samples, dtype=float).reshape(-1, 2)
    values = np.asarray(values, dtype=float).ravel()
    if len(values) != len(samples):
        raise ValueError(f"{len(values)} values for {len(samples)} samples")
    nq = len(queries)
    best = np.full(nq, np.inf)
    arg = np.full(nq, -1, dtype=np.int64)
    if nq == 0 or len(samples) == 0:
        return best, arg
    r = math.inf if radius is None else float(radius)
    s_order = np.argsort(samples[:, 0], kind="stable")
    sx = samples[s_order, 0]
    q_order = np.argsort(queries[:, 0], kind="stable")
    qs = queries[q_order]
    # chunk size: x-strips of queries about 2 r wide (each meets the samples of a 4 r wide strip), at
    # most `budget` pairs per distance block
    if math.isfinite(r):
        qspan = max(float(qs[-1, 0] - qs[0, 0]), 1e-12)
        chunk = max(16, int(nq * 2 * r / qspan))
        density = len(samples) / max(float(sx[-1] - sx[0]), 1e-12)
        chunk = min(chunk, max(1, budget // max(1, min(len(samples), int(density * 4 * r) + 1))))
    else:
        chunk = max(1, budget // len(samples))
    chunk = min(chunk, nq)
    r2 = r * r
    for s in range(0, nq, chunk):
        qc = qs[s : s + chunk]
        lo = np.searchsorted(sx, qc[0, 0] - r, side="left") if math.isfinite(r) else 0
        hi = np.searchsorted(sx, qc[-1, 0] + r, side="right") if math.isfinite(r) else len(sx)
        if hi <= lo:
            continue
        idx = s_order[lo:hi]
        # sub-blocks when a strip is denser than the budget allows
        sub = max(1, budget // len(qc))
        cb = np.full(len(qc), np.inf)
        ca = np.full(len(qc), -1, dtype=np.int64)
        for t in range(0, len(idx), sub):
            blk = idx[t : t + sub]
            diff = qc[:, None, :] - samples[blk][None, :, :]
            d2 = np.einsum("ijk,ijk->ij", diff, diff)
            cand = values[blk][None, :] + slope * np.sqrt(d2)
            cand[d2 > r2] = np.inf
            j = np.argmin(cand, axis=1)
            v = cand[np.arange(len(qc)), j]
            better = v < cb
            cb[better] = v[better]
            ca[better] = blk[j[better]]
        best[q_order[s : s + chunk]] = cb
        arg[q_order[s : s + chunk]] = ca
    return best, arg


def coverage_eps_min(
    points: np.ndarray, samples: np.ndarray, sample_err: np.ndarray, lipschitz: float, r_cov: float | None
) -> np.ndarray:
    """Per-point threshold of Assumption 1: `eps_min(p) = min_d |l(theta_d) - p_d| + L |p - p_d|` over
    training samples within `r_cov` (`inf` where none is).

    `p` lies in the coverage set `S^L_eps` of the paper (Assumption 1) iff `eps_min(p) <= eps`; so the
    covered fraction is monotone in `eps` and the smallest `eps` whose coverage set holds a set is the max of `eps_min`.
    """
    best, _ = min_plus_within(points, samples, sample_err, float(lipschitz), r_cov)
    return best


def nearest_distance(points: np.ndarray, samples: np.ndarray, radius0: float | None = None) -> np.ndarray:
    """Distance from each point to its nearest sample (exact; search radius doubles until all are found)."""
    points = np.asarray(points, dtype=float).reshape(-1, 2)
    samples = np.asarray(samples, dtype=float).reshape(-1, 2)
    out = np.full(len(points), np.inf)
    if len(samples) == 0 or len(points) == 0:
        return out
    if radius0 is None:
        span = np.ptp(samples, axis=0)
        radius0 = 3.0 * math.sqrt(max(span[0] * span[1], 1e-12) / len(samples)) or 1.0
    r = float(radius0)
    todo = np.arange(len(points))
    zeros = np.zeros(len(samples))
    while todo.size:
        d, _ = min_plus_within(points[todo], samples, zeros, 1.0, r)
        found = np.isfinite(d)
        out[todo[found]] = d[found]
        todo = todo[~found]
        r *= 2.0
    return out


def coverage_curve(eps_min: np.ndarray, eps: Sequence[float] | np.ndarray) -> np.ndarray:
    """Covered fraction `mean(eps_min <= eps)` for each value of `eps` (non-decreasing in `eps`)."""
    e = np.sort(np.asarray(eps_min, dtype=float).ravel())
    if e.size == 0:
        return np.full(len(np.atleast_1d(eps)), math.nan)
    return np.searchsorted(e, np.asarray(eps, dtype=float), side="right") / e.size


def smallest_coverage_eps(eps_min: np.ndarray, fraction: float = 1.0) -> float:
    """Smallest `eps` whose coverage set contains at least `fraction` of the points (`inf` if none does)."""
    e = np.sort(np.asarray(eps_min, dtype=float).ravel())
    if e.size == 0:
        return math.nan
    k = max(1, math.ceil(fraction * e.size - 1e-9))
    return float(e[k - 1])


def eps_sweep(eps_min: np.ndarray, n: int = 201, upper: float | None = None) -> np.ndarray:
    """Default ε values for a coverage sweep: `n` values from 0 to just past the largest finite eps_min."""
    e = np.asarray(eps_min, dtype=float)
    finite = e[np.isfinite(e)]
    top = upper if upper is not None else (1.05 * float(finite.max()) if finite.size else 1.0)
    return np.linspace(0.0, max(top, 1e-9), n)


# ------------------------------------------------------------------------------------ Dean et al.
def dean_fit(errors: np.ndarray, points: np.ndarray, center=(0.0, 0.0), eps_C: Sequence[float] = ()) -> dict:
    """Error model of Dean et al. (2020): smallest `(eps_C, eps_eta)` with `|e|_inf <= eps_C |p - c|_inf + eps_eta`.

    The feasible set is `eps_eta >= eta(eps_C) := max_i (|e_i|_inf - eps_C s_i)`, `s_i = |p_i - c|_inf`,
    convex and piecewise linear in `eps_C`. Returns

    - `eps_eta_at_0`: `eta(0) = max |e|_inf` (a uniform bound);
    - `eps_C_at_0`: the smallest `eps_C` with `eta = 0` (`max |e_i|_inf / s_i`; `inf` if an error sits at `s = 0`);
    - `front`: the exact Pareto front as its vertices `[(eps_C, eps_eta), ...]`, from `(0, eta(0))` to
      `(eps_C_at_0, 0)`;
    - `at`: `[(eps_C, eta(eps_C) clipped at 0)]` for the requested `eps_C` values.
    """
    e = np.abs(np.asarray(errors, dtype=float).reshape(-1, 2)).max(axis=1)
    s = np.abs(np.asarray(points, dtype=float).reshape(-1, 2) - np.asarray(center, dtype=float)).max(axis=1)
    ok = np.isfinite(e) & np.isfinite(s)
    e, s = e[ok], s[ok]
    if e.size == 0:
        return {"eps_eta_at_0": math.nan, "eps_C_at_0": math.nan, "front": [], "at": [], "n": 0}
    pos = s > 0
    zero_floor = float(e[~pos].max()) if (~pos).any() else 0.0
    c_star = float(np.max(e[pos] / s[pos])) if pos.any() else math.inf
    if zero_floor > 0:
        c_star = math.inf
    # As eps_C grows the binding line moves to smaller s: keep the staircase of points not dominated by one
    # with smaller s and larger error, then walk its upper hull vertex by vertex (few vertices).
    order = np.lexsort((-e, s))  # s ascending, then e descending
    es, ss = e[order], s[order]
    prev_max = np.concatenate([[-np.inf], np.maximum.accumulate(es)[:-1]])
    keep = es > prev_max
    hs, he = ss[keep], es[keep]  # s ascending, e ascending
    i = len(he) - 1  # the largest error binds at eps_C = 0
    c = 0.0
    front = [(0.0, float(he[i]))]
    while i > 0:
        left = np.arange(i)
        cand = (he[i] - he[left]) / (hs[i] - hs[left])  # eps_C where line j overtakes line i
        j = int(np.argmin(cand))  # ties: the smallest s (collinear vertices skipped)
        c_next = float(cand[j])
        if c_next >= c_star:
            break
        c, i = c_next, j
        front.append((c, float(he[i] - c * hs[i])))
    if math.isfinite(c_star):
        front.append((c_star, 0.0))
    at = [(float(cv), float(max(0.0, np.max(e - cv * s)))) for cv in eps_C]
    return {"eps_eta_at_0": float(e.max()), "eps_C_at_0": c_star, "front": front, "at": at, "n": int(e.size)}


# ---------------------------------------------------------------------------------- binned errors
def binned_stats(x: np.ndarray, y: np.ndarray, edges: np.ndarray) -> dict[str, np.ndarray]:
    """Per bin of `x` (edges, right-closed last bin): count, mean, median, p95 and max of `y`."""
    x = np.asarray(x, dtype=float).ravel()
    y = np.asarray(y, dtype=float).ravel()
    edges = np.asarray(edges, dtype=float)
    nb = len(edges) - 1
    idx = np.clip(np.searchsorted(edges, x, side="right") - 1, 0, nb - 1)
    inside = (x >= edges[0]) & (x <= edges[-1])
    out = {k: np.full(nb, np.nan) for k in ("mean", "median", "p95", "max")}
    out["count"] = np.bincount(idx[inside], minlength=nb)
    order = np.argsort(idx[inside], kind="stable")
    ys = y[inside][order]
    bounds = np.concatenate([[0], np.cumsum(out["count"])])
    for b in range(nb):  # one slice per bin (a handful of bins), not per sample
        seg = ys[bounds[b] : bounds[b + 1]]
        if seg.size:
            out["mean"][b] = seg.mean()
            out["median"][b] = np.median(seg)
            out["p95"][b] = np.percentile(seg, 95)
            out["max"][b] = seg.max()
    out["lo"], out["hi"] = edges[:-1], edges[1:]
    return out
