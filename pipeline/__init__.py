"""hycontrol-vision: vision-based hybrid control with learned perception maps (package `pipeline`)."""

__version__ = "0.1.0"
