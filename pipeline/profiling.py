"""Where a stage's time goes (issue 30): named phases summed over a process, written as one JSON line.

    with phase("render"):
        imgs = camera.render(...)

`make paper` sets `PIPELINE_PROFILE=<file>` for each job it starts; at the end of its work a stage calls
:func:`record` with its job's name, and the phases it timed (rendering, inference, computing, drawing, ...)
are appended to that file as one JSON line. `make paper` joins them with each job's wall and CPU time into
`profile.md` beside the paper's index (:mod:`pipeline.paper_profile`). Without the variable nothing is
written; the timers cost two `perf_counter` calls per phase.
"""

from __future__ import annotations

import json
import os
import time
from collections import defaultdict
from contextlib import contextmanager

ENV = "PIPELINE_PROFILE"
_TIMES: dict[str, float] = defaultdict(float)


@contextmanager
def phase(name: str):
    """Add the time spent inside the block to phase `name` (phases may nest: a nested one is counted in both)."""
    t0 = time.perf_counter()
    try:
        yield
    finally:
        _TIMES[name] += time.perf_counter() - t0


def reset() -> None:
    _TIMES.clear()


def record(job: str, **extra) -> None:
    """Append `{"job", "phases", **extra}` to the file `$PIPELINE_PROFILE` names (nothing when unset), and reset."""
    path = os.environ.get(ENV)
    if path:
        line = json.dumps({"job": job, "phases": {k: round(v, 3) for k, v in _TIMES.items()}, **extra})
        with open(path, "a", encoding="utf-8") as fh:  # one short line per write: appends do not interleave
            fh.write(line + "\n")
    reset()


def read_phases(path) -> dict[str, dict]:
    """What each job recorded in `path` (the JSON lines of :func:`record`), by job name; {} without the file."""
    out: dict[str, dict] = {}
    if os.path.isfile(path):
        with open(path, encoding="utf-8") as fh:
            for line in fh:
                try:
                    row = json.loads(line)
                except ValueError:  # a line cut by a killed job
                    continue
                out[row["job"]] = row
    return out
