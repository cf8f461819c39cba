"""Experiments stage (SPEC §4): the closed loop with the CNN in the loop; every paper figure and table.

`python -m pipeline.experiments experiment=<id>`: a scenario (:mod:`.theory`, :mod:`.camera_loop`,
:mod:`.generalisation`; built from its bundle in conf/experiment/) computes (:mod:`.context`), its results are cached by id, and its figures are drawn
(:mod:`.figures`) into the paper folder (:mod:`.report`).
"""
