"""Experiments stage (SPEC §4): closed loop with the CNN in the loop; every paper figure and table."""

from pipeline.experiments.measure import CameraMeasure, FollowerTarget, LeaderTrack, OracleMap

__all__ = ["CameraMeasure", "FollowerTarget", "LeaderTrack", "OracleMap"]
