"""The ego's side of the rule: its motion under every action and fallback, exactly as highway-env integrates
it, and the lanes it occupies (metres, m/s, seconds)."""

from __future__ import annotations

import math

import numpy as np

from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState

# --------------------------------------------------------------------------------------------
# Ego motion: highway-env's MDPVehicle, integrated exactly as the simulator does.
# --------------------------------------------------------------------------------------------


def speed_to_index(speed: np.ndarray | float, target_speeds: tuple[float, ...]) -> np.ndarray:
    """Index of the target speed closest to ``speed`` [m/s] (MDPVehicle.speed_to_index, rounding included)."""
    ts = target_speeds
    x = (np.asarray(speed, dtype=float) - ts[0]) / (ts[-1] - ts[0])
    return np.clip(np.round(x * (len(ts) - 1)), 0, len(ts) - 1).astype(int)


def action_targets(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """The ego's speed set-point [m/s] after each action (MDPVehicle.act)."""
    ts = dyn.target_speeds
    idx_now = int(speed_to_index(state.ego_speed, ts))
    target = np.full(N_ACTIONS, state.ego_target_speed, dtype=float)
    target[FASTER] = ts[min(idx_now + 1, len(ts) - 1)]
    target[SLOWER] = ts[max(idx_now - 1, 0)]
    return target


def ego_trajectories(state: RoadState, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """Ego positions [m] and speeds [m/s] for every (action, fallback) over the horizon.

    Returns arrays of shape ``(5, MAX_HOLD_DECISIONS + 1, frames + 1)``. Decision 0 applies the
    action (FASTER / SLOWER move the set-point one step from the *current speed's* index, as
    MDPVehicle does; IDLE and lane changes keep the set-point); fallback ``k`` then holds for ``k``
    decisions and sends SLOWER at every later decision. Per frame, as highway-env's
    ``Vehicle.step``: ``x += v·dt`` then ``v += KP_A·(target − v)·dt``.
    """
    ts = np.asarray(dyn.target_speeds, dtype=float)
    n_fb = MAX_HOLD_DECISIONS + 1
    shape = (N_ACTIONS, n_fb)
    v = np.full(shape, state.ego_speed, dtype=float)
    x = np.full(shape, state.ego_x, dtype=float)
    target = np.repeat(action_targets(state, dyn)[:, None], n_fb, axis=1)
    hold = np.arange(n_fb)[None, :]
    frames = dyn.frames_per_decision
    total = dyn.horizon_decisions * frames
    xs = np.empty((*shape, total + 1))
    vs = np.empty((*shape, total + 1))
    xs[..., 0], vs[..., 0] = x, v
    decay = 1.0 - dyn.ego_kp * dyn.frame_dt
    powers = decay ** np.arange(frames + 1)  # v_k = target + (v_0 - target)·decay^k
    # Distance covered since the decision's start: 0, then the running sum of v·dt (written in place:
    # this runs at every decision of every episode, so no temporaries beyond the ones numpy needs).
    covered = np.zeros((*shape, frames + 1))
    for d in range(dyn.horizon_decisions):
        if d >= 1:
            slower = ts[np.maximum(speed_to_index(v, dyn.target_speeds) - 1, 0)]
            target = np.where(d > hold, slower, target)
        sl = slice(d * frames, (d + 1) * frames + 1)
        # Consecutive decisions share a frame: decision d+1's first frame overwrites d's last, as before.
        v_frames, x_frames = vs[..., sl], xs[..., sl]
        np.multiply((v - target)[..., None], powers, out=v_frames)
        v_frames += target[..., None]
        np.cumsum(v_frames[..., :-1], axis=-1, out=covered[..., 1:])
        np.multiply(covered, dyn.frame_dt, out=x_frames)
        x_frames += x[..., None]
        x, v = x_frames[..., -1].copy(), v_frames[..., -1].copy()
    # Beyond the horizon the ego still creeps towards its final set-point: credit the remaining
    # distance of the exponential approach to the last frame so a stopped leader is not missed.
    tail = np.maximum(vs[..., -1] - 0.0, 0.0) / dyn.ego_kp
    xs[..., -1] += tail
    return xs, vs


def action_lanes(state: RoadState, dyn: Dynamics, action: int) -> list[tuple[int, float]]:
    """Lanes the ego occupies under ``action``, each with the time [s] until which it does (inf).

    With the rule's ``crossed_lanes`` also every lane the ego crosses on the way to its target: a lane
    change chained onto one under way (lane 0 → 1, then RIGHT again → 2) takes the ego through lane 1 whole,
    which the leave time of one lane change does not bound (the claim grid found it twice: a second change
    begun before the first ended)."""
    base = {state.ego_lane, state.ego_target_lane}
    if action not in (LANE_LEFT, LANE_RIGHT):
        if dyn.rule.crossed_lanes:
            base |= set(range(min(base), max(base) + 1))
        return [(lane, math.inf) for lane in sorted(base)]
    new_target = final_lane(state, dyn, action)
    low, high = sorted((state.ego_lane, new_target))
    crossed = set(range(low + 1, high)) if dyn.rule.crossed_lanes else set()
    lanes = [(lane, math.inf if lane in crossed else dyn.ego_leave_time) for lane in sorted(base | crossed)]
    return [*[(lane, until) for lane, until in lanes if lane != new_target], (new_target, math.inf)]


def final_lane(state: RoadState, dyn: Dynamics, action: int) -> int:
    """The lane the ego steers for after ``action``: highway-env moves the *target* lane one step (clipped to
    the road), and IDLE, FASTER and SLOWER keep a lane change under way."""
    if action not in (LANE_LEFT, LANE_RIGHT):
        return state.ego_target_lane
    step = -1 if action == LANE_LEFT else 1
    return min(max(state.ego_target_lane + step, 0), dyn.lanes_count - 1)


def available_actions(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """highway-env's ``DiscreteMetaAction.get_available_actions()`` as a bool mask."""
    avail = np.zeros(N_ACTIONS, dtype=bool)
    avail[IDLE] = True
    avail[LANE_LEFT] = state.ego_lane > 0
    avail[LANE_RIGHT] = state.ego_lane < dyn.lanes_count - 1
    avail[FASTER] = state.ego_speed_index < len(dyn.target_speeds) - 1
    avail[SLOWER] = state.ego_speed_index > 0
    return avail


def ego_last_frames(state: RoadState, dyn: Dynamics, available: np.ndarray) -> np.ndarray:
    """(5, lanes) the last frame of the horizon (:attr:`Dynamics.times`) in which the ego occupies each lane
    under each available action (:func:`action_lanes`); −1: never."""
    t = dyn.times
    last = np.full((N_ACTIONS, dyn.lanes_count), -1, dtype=np.int64)
    for a in np.flatnonzero(available):
        for lane, until in action_lanes(state, dyn, int(a)):
            last[a, lane] = max(last[a, lane], int(np.count_nonzero(t <= until)) - 1)  # NaN: never
    return last
