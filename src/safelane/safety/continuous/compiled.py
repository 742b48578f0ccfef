"""The committed rule for continuous controls, compiled: an action's plans rolled out and verified in one numba
kernel, bit-identical to the numpy reference (:func:`safelane.safety.continuous.plans.verify_action`).

Each kernel follows its reference operation by operation: libm's functions (``math``), the float32 arithmetic of
highway-env's ``lmap`` (NumPy's rules for a float32 with a Python number: the number is rounded to float32 and the
operation done in float32), and the committed rule's gaps kernel
(:func:`safelane.safety.committed.compiled.car_gaps_kernel`) for the cars. ``tests/test_continuous_shield.py``
checks it against the reference on recorded states and random actions.

Units: metres, m/s, radians, seconds.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.safety.committed import compiled as committed_compiled
from safelane.safety.committed.compiled import (
    CarArrays,
    car_gaps_kernel,
    carried_arrays,
    chunk_bounds,
    dynamics_arrays,
)
from safelane.safety.committed.sets import CarSets
from safelane.safety.continuous.controls import HEADING_WEIGHT, STOPPED_SPEED, ControlLimits
from safelane.safety.continuous.plans import EGO_WIDTH, ControlPlan, Trajectory
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState

drop_stale_kernel_cache(__file__, (committed_compiled.__file__,))

# The limits as the kernels read them: float64 ranges and speeds, then the float32 images of lmap's operands.
L_ACC_LOW, L_ACC_HIGH, L_STEER_LOW, L_STEER_HIGH, L_MIN_SPEED, L_MAX_SPEED, L_BETA_LIMIT = range(7)
F_ACC_LOW, F_ACC_SPAN, F_STEER_LOW, F_STEER_SPAN = range(4)


class LimitArrays(NamedTuple):
    """:class:`ControlLimits` as the kernels read them: ``wide`` (7,) float64 (ranges, speeds, the steepest slip
    angle the steering range allows) and ``narrow`` (4,) float32 (each range's low end and span, rounded to float32
    as ``lmap`` rounds them)."""

    wide: np.ndarray
    narrow: np.ndarray


def limit_arrays(limits: ControlLimits) -> LimitArrays:
    """The kernels' view of ``limits``."""
    a_low, a_high = limits.acceleration_range
    s_low, s_high = limits.steering_range
    beta_limit = min(abs(math.atan(0.5 * math.tan(s))) for s in (s_low, s_high))
    wide = np.array([a_low, a_high, s_low, s_high, limits.min_speed, limits.max_speed, beta_limit], dtype=np.float64)
    narrow = np.array([a_low, a_high - a_low, s_low, s_high - s_low], dtype=np.float32)
    return LimitArrays(wide, narrow)


@njit(cache=True, inline="always")
def _lmap(value: np.float32, low: np.float32, span: np.float32) -> float:
    """``lmap(value, [-1, 1], [low, low + span])`` in float32, as NumPy computes it for a float32 ``value``."""
    shifted = np.float32(value + np.float32(1.0))
    scaled = np.float32(np.float32(shifted * span) / np.float32(2.0))
    return np.float64(np.float32(low + scaled))  # float64 from here on (numba keeps float() of a float32 float32)


@njit(cache=True, inline="always")
def _normalised(control: float, low: float, high: float) -> np.float32:
    """:func:`~safelane.safety.continuous.controls.normalised`."""
    return np.float32(min(max((control - low) * 2.0 / (high - low) - 1.0, -1.0), 1.0))


@njit(cache=True, error_model="numpy")
def _roll_out(ego: np.ndarray, acceleration: float, steering: float, frames: int, dt: float, min_speed: float,
              max_speed: float, length: float, out: np.ndarray, first: int) -> None:  # fmt: skip
    """:func:`~safelane.safety.continuous.controls.roll_out` on ``ego`` (x, y, heading, speed), in place; each
    frame's state written to ``out[first + j]``."""
    x, y, heading, speed = ego[0], ego[1], ego[2], ego[3]
    acc = acceleration
    beta = math.atan(1 / 2 * math.tan(steering))
    sin_beta = math.sin(beta)
    for j in range(frames):
        if speed > max_speed:
            acc = min(acc, 1.0 * (max_speed - speed))
        elif speed < min_speed:
            acc = max(acc, 1.0 * (min_speed - speed))
        hb = heading + beta
        x += speed * math.cos(hb) * dt
        y += speed * math.sin(hb) * dt
        heading += speed * sin_beta / (length / 2) * dt
        speed += acc * dt
        out[first + j, 0], out[first + j, 1], out[first + j, 2], out[first + j, 3] = x, y, heading, speed
    ego[0], ego[1], ego[2], ego[3] = x, y, heading, speed


@njit(cache=True, error_model="numpy")
def _decision_distance(speed: float, acceleration: float, frames: int, dt: float, min_speed: float,
                       max_speed: float) -> float:  # fmt: skip
    """:func:`~safelane.safety.continuous.controls.decision_distance`."""
    acc, total = acceleration, 0.0
    for _ in range(frames):
        if speed > max_speed:
            acc = min(acc, 1.0 * (max_speed - speed))
        elif speed < min_speed:
            acc = max(acc, 1.0 * (min_speed - speed))
        total += speed * dt
        speed += acc * dt
    return total


@njit(cache=True, error_model="numpy")
def _fail_safe(ego: np.ndarray, lane_centre: float, braking: bool, period: float, frames: int, dt: float,
               wide: np.ndarray, narrow: np.ndarray, length: float, out: np.ndarray) -> None:  # fmt: skip
    """:func:`~safelane.safety.continuous.controls.fail_safe_action` into ``out`` (2,) float32."""
    low, high = wide[L_ACC_LOW], wide[L_ACC_HIGH]
    wanted = -ego[3] / period if braking else 0.0
    a_norm = _normalised(wanted, low, high)
    acceleration = _lmap(a_norm, narrow[F_ACC_LOW], narrow[F_ACC_SPAN])
    path = _decision_distance(ego[3], acceleration, frames, dt, wide[L_MIN_SPEED], wide[L_MAX_SPEED])
    steering = 0.0
    if path > 1e-3:
        drift = ego[1] - lane_centre + path * ego[2]
        drift_gain = path * (1.0 + path / length)
        heading_drift = path * ego[2]
        heading_gain = 2.0 * path * path / length
        beta = -(drift * drift_gain + HEADING_WEIGHT * heading_drift * heading_gain) / (
            drift_gain * drift_gain + HEADING_WEIGHT * heading_gain * heading_gain)
        beta_limit = wide[L_BETA_LIMIT]
        beta = max(-beta_limit, min(beta_limit, beta))
        steering = math.atan(2.0 * math.tan(beta))
    out[0] = a_norm
    out[1] = _normalised(steering, wide[L_STEER_LOW], wide[L_STEER_HIGH])


@njit(cache=True, error_model="numpy")
def trajectory_kernel(ego0: np.ndarray, first: np.ndarray, hold: int, replay: np.ndarray, decisions: int,
                      frames: int, dt: float, period: float, lane_width: float, lanes_count: int, wide: np.ndarray,
                      narrow: np.ndarray, length: float) -> tuple[np.ndarray, np.ndarray, int]:  # fmt: skip
    """(states (decisions·frames + 1, 4), actions (decisions, 2) float32, the plan's lane) of
    :func:`~safelane.safety.continuous.plans.plan_trajectory` (``replay`` empty) or of
    :func:`~safelane.safety.continuous.plans.replay_trajectory` (``replay`` its actions; lane −1)."""
    states = np.empty((decisions * frames + 1, 4))
    actions = np.empty((decisions, 2), dtype=np.float32)
    ego = ego0.copy()
    states[0] = ego
    lane = -1
    n_replay = replay.shape[0]
    for d in range(decisions):
        if n_replay > 0:
            k = min(d, n_replay - 1)
            actions[d, 0], actions[d, 1] = replay[k, 0], replay[k, 1]
        elif d == 0:
            actions[d, 0], actions[d, 1] = first[0], first[1]
        else:
            if lane < 0:
                lane = int(min(max(math.floor(ego[1] / lane_width + 0.5), 0), lanes_count - 1))
            _fail_safe(ego, lane * lane_width, d > hold, period, frames, dt, wide, narrow, length, actions[d])
        acceleration = _lmap(actions[d, 0], narrow[F_ACC_LOW], narrow[F_ACC_SPAN])
        steering = _lmap(actions[d, 1], narrow[F_STEER_LOW], narrow[F_STEER_SPAN])
        _roll_out(ego, acceleration, steering, frames, dt, wide[L_MIN_SPEED], wide[L_MAX_SPEED], length, states,
                  1 + d * frames)  # fmt: skip
    return states, actions, lane


@njit(cache=True, error_model="numpy")
def lanes_kernel(states: np.ndarray, lane_width: float, lanes_count: int, length: float, t: np.ndarray, dt: float
                 ) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """(lane ids, until [s], excess reach [m]) of :func:`~safelane.safety.continuous.plans.occupied_lanes` and
    :func:`~safelane.safety.continuous.plans.reach_excess` (``dt`` [s]: a frame)."""
    half = 0.5 * lane_width
    last = np.full(lanes_count, -1, dtype=np.int64)
    final = t.shape[0] - 1
    along = 0.0
    drift = 0.0
    n = states.shape[0]
    for j in range(n):
        x, y, heading, speed = states[j, 0], states[j, 1], states[j, 2], states[j, 3]
        reach = abs(0.5 * length * math.sin(heading)) + abs(0.5 * EGO_WIDTH * math.cos(heading))
        sweep = speed * math.sin(heading) * dt
        low = y - reach + min(sweep, 0.0)
        high = y + reach + max(sweep, 0.0)
        for lane in range(lanes_count):
            centre = lane * lane_width
            if high > centre - half and low < centre + half:
                last[lane] = min(j + 1, final)
        along = max(along, abs(0.5 * length * math.cos(heading)) + abs(0.5 * EGO_WIDTH * math.sin(heading)))
        if j + 1 < n:
            drift = max(drift, abs(x + speed * math.cos(heading) * dt - states[j + 1, 0]))
    count = 0
    for lane in range(lanes_count):
        if last[lane] >= 0:
            count += 1
    ids = np.empty(count, dtype=np.int64)
    until = np.empty(count)
    k = 0
    for lane in range(lanes_count):
        if last[lane] >= 0:
            ids[k] = lane
            until[k] = np.inf if last[lane] == final else t[last[lane]]
            k += 1
    return ids, until, max(along - 0.5 * length, 0.0) + drift


@njit(cache=True, error_model="numpy")
def _trajectory_gaps(states: np.ndarray, onset: float, held_a: int, held_b: int, last_frame: int, check_stop: bool,
                     x_lo: np.ndarray, x_hi: np.ndarray, entry: np.ndarray, now: np.ndarray,
                     carried_lane: np.ndarray, carried_high: np.ndarray, x: np.ndarray, half: np.ndarray,
                     ahead: np.ndarray, own_lane: np.ndarray, speed: np.ndarray, accel_max: np.ndarray,
                     brake_max: np.ndarray, fv_min: np.ndarray, fv_max: np.ndarray, t: np.ndarray,
                     follower_reaction: float, lane_width: float, lanes_count: int, length: float,
                     order: np.ndarray, least: bool, lo_min: np.ndarray, hi_max: np.ndarray, floor: float,
                     dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(gaps (cars,) or (1,) −inf, lane ids, until) of :func:`~safelane.safety.continuous.plans.trajectory_gap`;
    with ``least`` only their least is the reference's (``car_gaps_kernel`` skips the cars that cannot lower it,
    visiting them in ``order``; ``lo_min``/``hi_max``: :func:`chunk_bounds`), and only whether it is below
    ``floor`` once it is (the kernel stops there)."""
    ids, until, excess = lanes_kernel(states, lane_width, lanes_count, length, t, dt)
    n = x.shape[0]
    ego_x = np.empty((1, states.shape[0]))
    for j in range(states.shape[0]):
        ego_x[0, j] = states[j, 0]
    onsets = np.full(1, onset)
    worst = car_gaps_kernel(x_lo, x_hi, entry, now, ego_x, onsets, ids, until, held_a, held_b, last_frame,
                            carried_lane, carried_high, x, half, ahead, own_lane, speed, accel_max, brake_max, fv_min,
                            fv_max, t, follower_reaction, order, least, lo_min, hi_max, floor)
    gaps = np.empty(n)
    for i in range(n):
        gaps[i] = worst[i, 0] - excess
    half_lane = 0.5 * lane_width
    top = (lanes_count - 1) * lane_width + half_lane
    on_road = True
    for j in range(states.shape[0]):
        y = states[j, 1]
        if not (y >= -half_lane and y <= top):
            on_road = False
    moving = check_stop and abs(states[states.shape[0] - 1, 3]) > STOPPED_SPEED
    if not on_road or moving:
        gaps = np.full(max(n, 1), -np.inf)
    return gaps, ids, until


@njit(cache=True, error_model="numpy")
def verify_kernel(ego0: np.ndarray, action: np.ndarray, ego_lane: int, margin: float, decisions: int, frames: int,
                  dt: float, period: float, lane_width: float, lanes_count: int, wide: np.ndarray,
                  narrow: np.ndarray, length: float, x_lo: np.ndarray, x_hi: np.ndarray, entry: np.ndarray,
                  now: np.ndarray, x: np.ndarray, half: np.ndarray, ahead: np.ndarray, own_lane: np.ndarray,
                  speed: np.ndarray, accel_max: np.ndarray, brake_max: np.ndarray, fv_min: np.ndarray,
                  fv_max: np.ndarray, t: np.ndarray, follower_reaction: float, order: np.ndarray, lo_min: np.ndarray,
                  hi_max: np.ndarray):  # fmt: skip
    """:func:`~safelane.safety.continuous.plans.verify_action`: (hold, gap, states, actions, lane ids, until,
    plan lane, onset) of the first plan that keeps ``margin``; hold −1: none. The cars in ``order`` (nearest
    first), with their :func:`chunk_bounds`, so that the far ones are skipped."""
    empty = np.empty((0, 2), dtype=np.float32)
    no_lane = np.zeros(x.shape[0], dtype=np.int64)
    no_high = np.empty((0, t.shape[0]))
    for hold in range(MAX_HOLD_DECISIONS + 1):
        states, actions, lane = trajectory_kernel(ego0, action, hold, empty, decisions, frames, dt, period,
                                                  lane_width, lanes_count, wide, narrow, length)  # fmt: skip
        acceleration = _lmap(actions[0, 0], narrow[F_ACC_LOW], narrow[F_ACC_SPAN])
        onset = 0.0 if acceleration < 0.0 else (1 + hold) * period
        gaps, ids, until = _trajectory_gaps(states, onset, ego_lane, lane, t.shape[0] - 1, True, x_lo, x_hi, entry,
                                            now, no_lane, no_high, x, half, ahead, own_lane, speed, accel_max,
                                            brake_max, fv_min, fv_max, t, follower_reaction, lane_width,
                                            lanes_count, length, order, True, lo_min, hi_max, margin, dt)  # fmt: skip
        gap = np.inf if gaps.shape[0] == 0 else gaps.min()
        if gap >= margin:
            return hold, gap, states, actions, ids, until, lane, onset
    return -1, -np.inf, np.empty((0, 4)), empty, np.empty(0, dtype=np.int64), np.empty(0), -1, 0.0


class StateArrays(NamedTuple):
    """What the kernels read of one state's cars and sets, computed once per state."""

    cars: CarArrays
    order: np.ndarray
    lo_min: np.ndarray
    hi_max: np.ndarray


def state_arrays(state: RoadState, sets: CarSets, cars: CarArrays) -> StateArrays:
    """The :class:`StateArrays` of ``state`` against ``sets``."""
    return StateArrays(cars, *chunk_bounds(cars.x, float(state.ego_x), sets.x_lo, sets.x_hi))


def _ego(state: RoadState) -> np.ndarray:
    """(x, y, heading, speed) of the ego in ``state``, as the reference reads them."""
    return np.array([float(state.ego_x), float(state.ego_y), float(state.ego_heading), float(state.ego_speed)])


def verify_action_compiled(state: RoadState, dyn: Dynamics, limits: LimitArrays, sets: CarSets,
                           arrays: StateArrays, action: np.ndarray) -> ControlPlan | None:  # fmt: skip
    """:func:`~safelane.safety.continuous.plans.verify_action`, compiled (the same bits); ``limits``:
    :func:`limit_arrays`; ``arrays``: :func:`state_arrays` of ``state`` and ``sets``."""
    t = dynamics_arrays(dyn).times
    hold, gap, states, actions, ids, until, lane, onset = verify_kernel(
        _ego(state), np.asarray(action, dtype=np.float32), int(state.ego_lane), float(dyn.margin),
        dyn.horizon_decisions, dyn.frames_per_decision, float(dyn.frame_dt), float(dyn.decision_period),
        float(dyn.lane_width), int(dyn.lanes_count), limits.wide, limits.narrow, float(state.ego_length),
        sets.x_lo, sets.x_hi, sets.entry, np.asarray(sets.now, dtype=np.bool_), *arrays.cars, t,
        float(dyn.follower_reaction), arrays.order, arrays.lo_min, arrays.hi_max,
    )  # fmt: skip
    if hold < 0:
        return None
    lanes = tuple((int(i), float(u)) for i, u in zip(ids, until, strict=True))
    return ControlPlan(actions, states[:, 0].copy(), lanes, float(onset), (int(state.ego_lane), int(lane)),
                       t.size - 1, float(gap))  # fmt: skip


def tail_gap_compiled(state: RoadState, dyn: Dynamics, limits: LimitArrays, sets: CarSets, cars: CarArrays,
                      actions: np.ndarray, onset: float, held: tuple[int, int], until_frame: int,
                      carried_followers: dict[int, tuple[int, np.ndarray]]
                      ) -> tuple[np.ndarray, tuple[tuple[int, float], ...], Trajectory]:  # fmt: skip
    """(gaps, lanes, trajectory) of a kept plan's tail ``actions`` replayed from ``state``: the reference's
    :func:`~safelane.safety.continuous.plans.replay_trajectory` then
    :func:`~safelane.safety.continuous.plans.trajectory_gap`, compiled (the same bits)."""
    t = dynamics_arrays(dyn).times
    states, out, _ = trajectory_kernel(
        _ego(state), np.zeros(2, dtype=np.float32), 0, np.ascontiguousarray(actions, dtype=np.float32),
        dyn.horizon_decisions, dyn.frames_per_decision, float(dyn.frame_dt), float(dyn.decision_period),
        float(dyn.lane_width), int(dyn.lanes_count), limits.wide, limits.narrow, float(state.ego_length),
    )  # fmt: skip
    n = state.n
    carried_lane, carried_high = carried_arrays(carried_followers, n, t.size)
    gaps, ids, until = _trajectory_gaps(
        states, float(onset), int(held[0]), int(held[1]), int(until_frame), False, sets.x_lo, sets.x_hi, sets.entry,
        np.asarray(sets.now, dtype=np.bool_), carried_lane, carried_high, *cars, t, float(dyn.follower_reaction),
        float(dyn.lane_width), int(dyn.lanes_count), float(state.ego_length), np.arange(n), False, np.empty((0, 0)),
        np.empty((0, 0)), -np.inf, float(dyn.frame_dt),
    )  # fmt: skip
    lanes = tuple((int(i), float(u)) for i, u in zip(ids, until, strict=True))
    return gaps, lanes, Trajectory(states, out)
