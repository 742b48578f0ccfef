"""The five meta-actions of highway-env's ``DiscreteMetaAction`` (paper Table 2), by index.

Kept apart so that the safety model and the agents share the numbering without importing
highway-env.
"""

from __future__ import annotations

LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = range(5)
ACTION_NAMES: tuple[str, ...] = ("LANE_LEFT", "IDLE", "LANE_RIGHT", "FASTER", "SLOWER")
N_ACTIONS = len(ACTION_NAMES)
