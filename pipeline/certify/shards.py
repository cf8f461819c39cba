"""The certify stage in shards (issue 44, "beyond one machine"): chunks computed anywhere, merged into one map.

The cells of one `kappa` (a pose map's: each with its heading intervals) are cut, in order, into **chunks** of
`batch` rows (the clouds app's: of `clouds.chunk` cells, :mod:`.clouds_run`). Every chunk is bounded and split on its own (its sub-cells are batched with each other only) and its
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

The mechanism is the stage's own and the clouds app's: a chunk's result is a *part*, per-row arrays and scalars
(counts, seconds, the worst counterexample), merged in order by concatenating the arrays and reducing the scalars
(:func:`merge`), whether the parts are chunks of one shard or shards of one map.
"""

from __future__ import annotations

import json
import os
from collections.abc import Callable
from pathlib import Path

import numpy as np

from pipeline.progress import progress as progress_bar

SHARDS_DIR = ".shards"  # under the certified maps' root; hidden, never a tracked folder

Part = tuple[dict, dict]  # (per-row arrays by name, scalars by name)


def chunk_ranges(n: int, batch: int) -> list[tuple[int, int]]:
    """`[(start, stop)]`: `n` rows cut into chunks of `batch`, in order."""
    return [(a, min(a + batch, n)) for a in range(0, n, batch)]


def shard_chunks(n_chunks: int, shards: int, index: int) -> range:
    """The chunks of shard `index` of `shards`: a contiguous run, the runs as even as whole chunks allow."""
    return range(index * n_chunks // shards, (index + 1) * n_chunks // shards)


def _first(v):
    return v[0] if isinstance(v, (list, tuple)) else v


def merge(parts: list[Part], reduce: dict[str, str]) -> Part:
    """Parts in row order -> one: each array concatenated (parts without it skipped: a part of no rows), each
    scalar of `reduce` summed (`"sum"`) or the largest kept (`"max"`; a pair `(value, counterexample)` by its
    value)."""
    arrays: dict = {}
    for a, _ in parts:
        for k, v in a.items():
            if v is not None:
                arrays.setdefault(k, []).append(v)
    scalars = {}
    for k, how in reduce.items():
        values = [s[k] for _, s in parts if s.get(k) is not None]
        if how == "sum":
            scalars[k] = sum(values)
        elif how == "max":
            scalars[k] = max(values, key=_first, default=None)
        else:
            raise ValueError(f"merge: {k} reduces by sum or max, not {how!r}")
    return {k: np.concatenate(v) for k, v in arrays.items()}, scalars


def shard_path(folder: Path, tag: str, index: int, shards: int) -> Path:
    return Path(folder) / f"{tag}-shard{index}of{shards}.npz"


def save(path: Path, part: Part) -> None:
    """Write `part` to `path` atomically (a temporary name, then a rename)."""
    path.parent.mkdir(parents=True, exist_ok=True)
    arrays, scalars = part
    tmp = path.with_name(f".tmp-{os.getpid()}-{path.name}")
    with open(tmp, "wb") as f:
        np.savez(f, _scalars=np.array(json.dumps(scalars, default=float)),
                 **{k: v for k, v in arrays.items() if v is not None})
    tmp.rename(path)


def load(path: Path) -> Part:
    with np.load(path) as z:
        return {k: z[k] for k in z.files if k != "_scalars"}, json.loads(str(z["_scalars"]))


def say_missing(folder: Path, missing: int, shards: int) -> None:
    """One line before a merge computes shards itself: how many, and the saved shards of other ids of the same
    output (shards made with other settings or another code version: the id names both, so they are not these)."""
    name = Path(folder).name.rsplit("-", 1)[0]
    others = sorted(d.name for d in Path(folder).parent.glob(f"{name}-*") if d.is_dir() and d != Path(folder))
    print(f"shards: {missing} of {shards} shards of {Path(folder).name} are not saved; computing them here"
          + (f" (saved shards of other ids, from other settings or another code version, are not these: "
             f"{', '.join(others)})" if others else ""), flush=True)


def run_sharded(n_rows: int, chunk: int, s, folder: Path, tag: str, compute: Callable, reduce: dict[str, str],
                desc: str) -> Part | None:
    """`n_rows` rows in chunks of `chunk`, `compute(start, stop, chunk_index, bar) -> Part` per chunk. With
    `s.shard` set: that shard of `s.shards` computed (or found under `folder`) and saved, `None` returned; else
    every shard (found, or computed here and saved when `s.shards > 1`) merged in order. `s.force` recomputes
    saved shards; `s.progress` shows a bar over the rows this process computes (`compute` advances it)."""
    ranges, n = chunk_ranges(n_rows, int(chunk)), int(s.shards)
    wanted = [s.shard] if s.shard is not None else list(range(n))
    paths = {i: shard_path(folder, tag, i, n) for i in wanted}
    found = {i for i in wanted if n > 1 and not s.force and paths[i].is_file()}
    todo = sum(ranges[c][1] - ranges[c][0] for i in wanted if i not in found
               for c in shard_chunks(len(ranges), n, i))
    if s.shard is None and n > 1 and len(found) < n:
        say_missing(folder, n - len(found), n)
    parts = []
    with progress_bar(total=todo, desc=desc, unit="cell", enabled=bool(s.progress)) as bar:
        for i in wanted:
            if i in found:
                parts.append(load(paths[i]))
                continue
            parts.append(merge([compute(*ranges[c], c, bar) for c in shard_chunks(len(ranges), n, i)], reduce))
            if n > 1:
                save(paths[i], parts[-1])
    return None if s.shard is not None else merge(parts, reduce)
