"""`python -m pipeline.data.verify [dataset=<ref>]` (`make verify-data`): re-hash datasets against their manifests.

Prints one line per missing, truncated or altered file (with its path) and exits non-zero when anything
is wrong; `dataset=` limits the check to one dataset (a name means the dataset the current config renders
for it, as in every stage; or an id, name-id or path).
"""

from __future__ import annotations

import sys
from pathlib import Path

from omegaconf import DictConfig

from pipeline import tracking
from pipeline.cli import stage_main
from pipeline.errors import DatasetError
from pipeline.lineage import debug_overrides, resolve_dataset


def incomplete(root: Path) -> list[Path]:
    """Final-named folders under `root` (not temporaries) that have no manifest: a damaged dataset."""
    if not root.is_dir():
        return []
    return sorted(d for d in root.iterdir()
                  if d.is_dir() and not d.name.startswith(".") and not (d / tracking.MANIFEST).is_file())


def verify_datasets(datasets_dir, dataset=None, full: bool = True, echo=print, overrides=()) -> dict[str, list[str]]:
    """Problems per dataset folder (empty lists: all good). `echo` gets one line per dataset/problem. A name means
    the dataset the current config renders for it (with `overrides`, e.g. `debug=tiny`), as everywhere else."""
    root = Path(datasets_dir)
    if dataset is not None:
        folders = [resolve_dataset(dataset, root, overrides, check=False)]
    else:
        folders = sorted(tracking.entries(root), key=lambda d: d.name)
        tracking.stale_temporaries(root, remove=False, echo=lambda s: echo(f"note: {s}"))
    report = {}
    if dataset is None:
        for d in incomplete(root):
            report[str(d)] = [f"{d}: no {tracking.MANIFEST} (not a finished dataset: delete it or re-render it)"]
            echo(f"FAIL {d.name}: no {tracking.MANIFEST}")
    for folder in folders:
        problems = tracking.verify(folder, full=full)
        report[str(folder)] = problems
        if problems:
            echo(f"FAIL {folder.name}: {len(problems)} problem(s)")
            for line in problems:
                echo(f"  {line}")
        else:
            n = len(tracking.read_manifest(folder).get("files", {}))
            echo(f"ok   {folder.name}: {n} files match the manifest")
    return report


def run(cfg: DictConfig) -> dict:
    root = Path(cfg.paths.datasets_dir)
    report = verify_datasets(root, cfg.get("dataset"), full=bool(cfg.get("full", True)),
                             overrides=debug_overrides(cfg))
    bad = {k: v for k, v in report.items() if v}
    if not report:
        print(f"verify: no datasets under {root} (run `make data`)")
    if bad:
        n = sum(len(v) for v in bad.values())
        raise DatasetError(f"{n} problem(s) in {len(bad)} of {len(report)} dataset(s) under {root}")
    return {"datasets": list(report), "problems": bad}


main = stage_main("verify_data", run="pipeline.data.verify:run")


if __name__ == "__main__":
    sys.exit(main())
