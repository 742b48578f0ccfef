"""The sizes every tier agrees on: the five meta-actions (paper Table 2, highway-env's
``DiscreteMetaAction`` order) and the 26-number state (eq. 3).

Kept apart so that the simulator, the safety model and the agents share them without importing each
other.
"""

from __future__ import annotations

LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = range(5)
ACTION_NAMES: tuple[str, ...] = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
N_ACTIONS = len(ACTION_NAMES)

OBSERVED_VEHICLES = 4
"""Nearest vehicles in the paper's state (Section III.A)."""
FEATURES_PER_VEHICLE = 6
"""δx, δy, δvx, δvy, heading, presence flag."""
OBS_SIZE = OBSERVED_VEHICLES * FEATURES_PER_VEHICLE + 2
"""26: four vehicles plus ego speed and ego heading (the ``lanes`` state has the same size)."""
CONTINUOUS_OBS_SIZE = OBS_SIZE + 2
"""28: eq. 3's 26 numbers, then the ego's offset from its lane's centre and its lane index (continuous actions:
a policy that steers must know where it is in its lane and on the road)."""
