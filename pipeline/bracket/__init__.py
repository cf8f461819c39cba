"""The closed loop bracketed from both sides (SPEC §5.4, §5.5): per controller and start cell, a falsifier's
`ε_hi` (an error signal within it makes the run fail) and a certificate's `ε_lo` (no signal within it does)."""
