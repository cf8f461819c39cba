"""ε-error maps of the learned perception maps (issue 5, SPEC §2, the paper's Assumption 1 / Lemma 1).

`python -m pipeline.errormap model=<name>` writes `outputs/errormaps/<name>-<id>/` (docs/errormap.md);
`load_error_map(ref)` reads one back for the experiments stage; the math is in `pipeline.errormap.core`.
"""

from pipeline.errormap.stage import load_error_map, run, run_one, summary_table, validate

__all__ = ["load_error_map", "run", "run_one", "summary_table", "validate"]
