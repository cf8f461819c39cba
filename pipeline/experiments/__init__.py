"""Experiments stage (SPEC §4): the closed loop with the CNN in the loop; every paper figure and table.

`python -m pipeline.experiments experiment=<id>`: a scenario (:mod:`.paper`, :mod:`.attacks`, :mod:`.multi`,
:mod:`.generalisation`; built from its bundle in conf/experiment/) computes (:mod:`.context`), its results (:mod:`.results`) are cached by id, and its figures are drawn
(beside each scenario) into the paper folder (:mod:`.report`).
"""
