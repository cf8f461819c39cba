"""Figures are redrawn only when what they are drawn from changes: the cached results (by id), the composed
config (minus paths and the run's flags) and the drawing code. A rerun with nothing changed re-uses the files
its index entry (`<paper_dir>/index/<experiment>.json`) lists, when every one of them is still there."""

from __future__ import annotations

import json
from pathlib import Path

from pipeline import tracking

# keys of the composed config that say where or how a run happens, not what a figure shows
NOT_DRAWN = ("paths", "hydra", "force", "publish", "device")


def drawing_key(cfg, results: Path) -> str:
    """Id of a scenario's figures and tables: its results folder, its config and the code that draws."""
    plain = tracking.to_plain_lenient(cfg)
    return tracking.content_id(Path(results).name, {k: v for k, v in plain.items() if k not in NOT_DRAWN},
                               tracking.code_version("experiments", "viz"))


def drawn_entry(view_dir: Path, exp_id: str, key: str) -> dict | None:
    """The index entry of `exp_id` in `view_dir` when it was drawn with `key` and all its files are there."""
    path = Path(view_dir) / "index" / f"{exp_id}.json"
    try:
        entry = json.loads(path.read_text())
    except (OSError, ValueError):
        return None
    files = [Path(view_dir) / f for it in entry.get("items", []) for f in it.get("files", [])]
    if entry.get("drawn") != key or not files or not all(f.is_file() for f in files):
        return None
    return entry
