"""Helpers several test modules share. `computed_once`: a value the xdist workers of one `make test` compute once: the first worker to ask computes and pickles it under
the session's shared temporary folder (a file lock keeps the others waiting), the others read it. Without xdist
(`worker_id == "master"`) it is computed in place: there is no session folder shared with nobody else."""

from __future__ import annotations

import pickle
import re
from pathlib import Path

from filelock import FileLock


def computed_once(tmp_path_factory, worker_id: str, name: str, make):
    if worker_id == "master":
        return make()
    path = tmp_path_factory.getbasetemp().parent / f"{name}.pkl"  # pytest-N/: this session's, shared by its workers
    with FileLock(str(path) + ".lock"):
        if path.is_file():
            return pickle.loads(path.read_bytes())
        value = make()
        path.write_bytes(pickle.dumps(value))
        return value


def index_links(index: Path) -> set[str]:
    """The targets of the markdown links of a paper folder's `index.md`."""
    return set(re.findall(r"\]\(([^)]+)\)", index.read_text()))
