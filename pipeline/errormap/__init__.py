"""ε-error maps of the learned perception maps (SPEC §2, the paper's Assumption 1 / Lemma 1).

`python -m pipeline.errormap maps=<name>` writes `outputs/errormaps/<name>-<id>/` (docs/errormap.md);
:func:`pipeline.errormap.read.load_error_map` reads one back for the experiments stage.
"""
