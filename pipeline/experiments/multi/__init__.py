"""Beyond the paper: several obstacles (:mod:`.fields`) and the unicycle (:mod:`.unicycle`), with their figures
(docs/multi.md)."""
