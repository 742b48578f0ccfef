"""The plan family both engines of the committed rule verify: each action's braking onsets, the actions a plan may
start with, and the lanes the ego holds.

Shared by the numpy reference (:mod:`safelane.safety.committed.plans`) and the compiled engine
(:mod:`safelane.safety.committed.compiled`), so neither imports the other. Pure maths.
"""

from __future__ import annotations

import math

import numpy as np

from safelane.core.spaces import LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER
from safelane.safety.ego import available_actions
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState

Lanes = list[tuple[int, float]]
"""The lanes a plan occupies, each with the time [s] until which it does (:func:`safelane.safety.ego.action_lanes`)."""


def onsets(dyn: Dynamics, action: int) -> np.ndarray:
    """(holds,) [s] when each plan of ``action`` first lowers the set-point (its braking onset)."""
    if action == SLOWER:
        return np.zeros(MAX_HOLD_DECISIONS + 1)
    return (1 + np.arange(MAX_HOLD_DECISIONS + 1)) * dyn.decision_period


def plan_actions(state: RoadState, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """(available, verify), each (5,): the actions whose plans are drawn (highway-env's available actions) and
    those whose plans are verified (no lane change when the ego is too slow to leave its lane, docs/safety.md §4)."""
    available = available_actions(state, dyn)
    verify = available.copy()
    if not math.isfinite(dyn.ego_leave_time):
        verify &= ~np.isin(np.arange(N_ACTIONS), (LANE_LEFT, LANE_RIGHT))
    return available, verify


def held_lanes(state: RoadState, held: tuple[int, ...] | None) -> tuple[int, ...]:
    """The lanes the ego holds, the lane it is in first (the one where a car behind is its driver's to avoid):
    ``held`` (a kept plan's, when verified) or, by default, its lane and target lane now."""
    return (int(state.ego_lane), int(state.ego_target_lane)) if not held else tuple(int(h) for h in held)
