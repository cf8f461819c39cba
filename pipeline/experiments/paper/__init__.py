"""The paper's figures and tables (SPEC §4): the scenarios on the true state (:mod:`.theory`), the camera in the loop
(:mod:`.camera_loop`), and their figures (:mod:`.figures`, :mod:`.scheme`, :mod:`.animation`)."""
