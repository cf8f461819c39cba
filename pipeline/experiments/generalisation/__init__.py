"""Beyond the paper: how perception maps generalise across cloud levels (:mod:`.maps`; docs/experiments.md)."""
