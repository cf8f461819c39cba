"""The certify stage in shards (issue 44, "beyond one machine"): chunks computed anywhere, merged into one map.

The cells of one `kappa` (a pose map's: each with its heading intervals) are cut, in order, into **chunks** of
`batch` rows. Every chunk is bounded and split on its own (its sub-cells are batched with each other only) and its
sampled positions are its own random stream (`(seed, chunk index)`), so a chunk's numbers do not depend on which
process computes it, nor on the other chunks. Shard `i` of `n` is the contiguous run of chunks
`[i C / n, (i + 1) C / n)` (`C` chunks; a shard may hold none). So the certified map merged from shards is the one
computed in one process, array for array (`tests/test_certify_shards.py`), and its id does not name `shards` or
`shard` (`identity.CERTIFY_VOLATILE`).

- `shard=i shards=n`: computes shard `i` for every `kappa` and saves it (one `.npz` per `kappa`, written under a
  temporary name and renamed) in `<certified_dir>/.shards/<map>-<id>/`; a saved shard is not computed again
  (`force=true` recomputes it). Run them side by side with a launcher:
  `python -m pipeline.certify -m shards=4 shard=0,1,2,3 hydra/launcher=joblib` (or `submitit_slurm` on a cluster).
- `shards=n` without `shard`: loads the saved shards, computes the missing ones here (saving each, so that an
  interrupted merge resumes), merges them in chunk order, runs what needs every cell (the PGD attack on the bound,
  the statistics, the figures) and writes the tracked folder; the shard folder is then removed.
"""

from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from pipeline.certify.split import certify_cells, sampled_errors
from pipeline.progress import progress as progress_bar

SHARDS_DIR = ".shards"  # under the certified maps' root; hidden, never a tracked folder


@dataclass
class Part:
    """The per-row arrays of a run of chunks (rows: the bounded cells, in order) and what they add up to."""

    lower: np.ndarray
    upper: np.ndarray
    depth: np.ndarray
    leaves: np.ndarray
    heading: np.ndarray
    emp: np.ndarray | None       # kappa 0 only: the sampled errors
    head_emp: np.ndarray | None  # a pose map's sampled heading errors
    violations: int
    worst: tuple                 # (largest excess over a bound, the counterexample or None)
    seconds: float               # the bound's
    sampled_seconds: float


def chunk_ranges(n: int, batch: int) -> list[tuple[int, int]]:
    """`[(start, stop)]`: `n` rows cut into chunks of `batch`, in order."""
    return [(a, min(a + batch, n)) for a in range(0, n, batch)]


def shard_chunks(n_chunks: int, shards: int, index: int) -> range:
    """The chunks of shard `index` of `shards`: a contiguous run, the runs as even as whole chunks allow."""
    return range(index * n_chunks // shards, (index + 1) * n_chunks // shards)


def compute(prep, predict, camera, rows: np.ndarray, s, chunks, ranges, sample: bool, bar_b, bar_s) -> Part:
    """Bound (and, with `sample`, sample) the chunks `chunks` of `rows`; `ranges` from :func:`chunk_ranges`."""
    parts = []
    for c in chunks:
        a, b = ranges[c]
        t0 = time.perf_counter()
        lower, upper, depth, leaves, heading = certify_cells(prep, rows[a:b], s.mode, s.tolerance, s.max_depth,
                                                             s.batch, bar=bar_b)
        t1 = time.perf_counter()
        emp = head_emp = None
        violations, worst = 0, (-np.inf, None)
        if sample:
            emp, violations, worst, head_emp = sampled_errors(
                predict, camera, rows[a:b], lower, upper, s.samples, s.seed, heading=heading, stream=c, bar=bar_s)
        parts.append(Part(lower, upper, depth, leaves, heading, emp, head_emp, violations, worst, t1 - t0,
                          time.perf_counter() - t1))
    return merge(parts, sample, rows.shape[1])


def merge(parts: list[Part], sample: bool, width: int) -> Part:
    """Parts in order -> one part (an empty list: a part of no rows)."""
    def cat(name, shape):
        values = [getattr(p, name) for p in parts]
        return np.concatenate(values) if values else np.zeros(shape)

    worst = max((p.worst for p in parts), key=lambda w: w[0], default=(-np.inf, None))
    return Part(cat("lower", (0, 2)), cat("upper", (0, 2)), cat("depth", 0).astype(np.int64),
                cat("leaves", 0).astype(np.int64), cat("heading", 0),
                cat("emp", 0) if sample else None,
                cat("head_emp", 0) if sample and width == 6 else None,
                sum(p.violations for p in parts), worst, sum(p.seconds for p in parts),
                sum(p.sampled_seconds for p in parts))


def shard_path(folder: Path, kappa: float, index: int, shards: int) -> Path:
    return Path(folder) / f"kappa{float(kappa):g}-shard{index}of{shards}.npz"


def save(path: Path, part: Part) -> None:
    """Write `part` to `path` atomically (a temporary name, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays = {k: getattr(part, k) for k in ("lower", "upper", "depth", "leaves", "heading", "emp", "head_emp")
              if getattr(part, k) is not None}
    scalars = {"violations": part.violations, "worst": [float(part.worst[0]), part.worst[1]],
               "seconds": part.seconds, "sampled_seconds": part.sampled_seconds}
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    with open(tmp, "wb") as f:
        np.savez(f, scalars=np.array(json.dumps(scalars)), **arrays)
    tmp.rename(path)


def load(path: Path) -> Part:
    with np.load(path) as z:
        sc = json.loads(str(z["scalars"]))
        get = lambda k: z[k] if k in z.files else None  # noqa: E731
        return Part(z["lower"], z["upper"], z["depth"], z["leaves"], z["heading"], get("emp"), get("head_emp"),
                    int(sc["violations"]), (float(sc["worst"][0]), sc["worst"][1]), float(sc["seconds"]),
                    float(sc["sampled_seconds"]))


def run_kappa(prep, predict, camera, rows: np.ndarray, s, folder: Path, sample: bool, desc: str) -> Part | None:
    """One `kappa`'s rows: with `s.shard` set, that shard computed (or found) and saved, `None` returned; else every
    shard (found, or computed here and saved when `s.shards > 1`) merged in order. The progress bars count the
    cells this process computes."""
    ranges, n = chunk_ranges(len(rows), int(s.batch)), int(s.shards)
    wanted = [s.shard] if s.shard is not None else list(range(n))
    found = {i: shard_path(folder, prep.kappa, i, n) for i in wanted
             if n > 1 and not s.force and shard_path(folder, prep.kappa, i, n).is_file()}
    todo = sum(ranges[c][1] - ranges[c][0] for i in wanted if i not in found for c in shard_chunks(len(ranges), n, i))
    parts = []
    with progress_bar(total=todo, desc=desc, unit="cell", enabled=bool(s.progress)) as bar_b, \
            progress_bar(total=todo if sample else 0, desc="sampled positions", unit="cell",
                         enabled=bool(s.progress) and sample) as bar_s:
        for i in wanted:
            if i in found:
                parts.append(load(found[i]))
                continue
            parts.append(compute(prep, predict, camera, rows, s, shard_chunks(len(ranges), n, i), ranges, sample,
                                 bar_b, bar_s))
            if n > 1:
                save(shard_path(folder, prep.kappa, i, n), parts[-1])
    return None if s.shard is not None else merge(parts, sample, rows.shape[1])
