"""Beyond the paper: adversaries through the camera (:mod:`.camera`: the pixel attack and the worst cloud; docs/attacks.md)
and what sets the hysteresis margin (:mod:`.margin`, the geometry margin), with their figures (:mod:`.figures`)."""
