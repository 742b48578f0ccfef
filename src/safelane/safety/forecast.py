"""A nominal forecast of the traffic, to rank the fallback's choices when no action is safe.

The rule (:mod:`safelane.safety.model`) decides what is *safe* from worst cases only. When nothing is safe
it still has to pick one action, and ranking the unsafe actions by their worst-case gaps alone drives badly:
in a spawned squeeze — a leader close ahead braking for its own leader, an empty lane beside — the worst
case says every action collides and SLOWER collides least, while the planner that knows the future changes
lane at once and drives through (issue 15, the claim campaign's 567 crashes from unsafe spawns: 402 of
them driven through by the foresight planner, ``examples/spawn_foresight.py``).

:func:`forecast_gaps` predicts what the others will most likely do instead: every vehicle keeps its lane
(the one it is heading to, if it is moving sideways) and drives by its own law — IDM, or the linear model
of Linear, Aggressive and Defensive drivers, with its own parameters and set-point, accelerations clipped
to ``[−brake_max, accel_max]`` as highway-env clips them — behind its leader in that lane, the ego among
them wherever the ego's action takes it. It is the same integration highway-env runs (acceleration from
the current state, then ``x += v·dt``, ``v += a·dt``). Without ``lane_changes`` no lane change is predicted;
with it (``Dynamics.forecast_lane_changes``, experimental, off: measured worse, docs/safety.md §6r) every car
that may change lane runs MOBIL at every frame (highway-env runs it once a second, at a phase the snapshot does
not carry) with its own law — its new follower must not have to brake harder than its ``max_braking_imposed``,
and its own gain must reach highway-env's IDM threshold, :data:`MOBIL_MIN_ACC_GAIN` (Aggressive and Defensive
drivers ask for 1 m/s², which the snapshot does not tell apart) — and, once it starts, counts in both lanes for
:data:`LANE_CHANGE_TIME`, then in its new lane; the ego is in the lane highway-env's neighbour search sees it in
(its own until it has left it). A body
without a set-point (a static object; a hand-built state's unknown one) keeps its speed, and a wreck stands. The
forecast never makes an action safe; it only orders the least-bad choice (``Dynamics.forecast_fallback``).
With ``Dynamics.forecast_contact_time`` (experimental, off: measured worse, docs/safety.md §6r) an action the
forecast sees collide ranks by *when*: the more whole decisions before its first contact, the higher (contacts
within one decision rank alike).

One numba kernel serves both engines (the numpy reference and the compiled rule call the same function on
the same arrays), so their fallback choices are the same bits.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

FORECAST_RANGE = 150.0
"""[m] Vehicles farther than this from the ego along the road are left out of the forecast."""
SIDEWAYS_LOOKAHEAD = 1.0
"""[s] A vehicle moving sideways is taken to follow the lane its lateral speed reaches in this time."""
LANE_CHANGE_TIME = 2.0
"""[s] With lane changes, a car that starts one counts in both lanes this long, then in its new lane only (an
assumption, not fitted to highway-env's lateral controller)."""
MOBIL_MIN_ACC_GAIN = 0.2
"""[m/s²] MOBIL's threshold in the forecast: highway-env's IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN (its POLITENESS
is 0, so only the car's own gain counts)."""


@njit(cache=True, inline="always")
def _lane(y: float, lane_width: float, lanes_count: int) -> int:
    """The lane whose centre is nearest ``y`` [m] (lane i's centre at ``i · lane_width``), clipped to the road."""
    lane = int(np.rint(y / lane_width))
    return min(max(lane, 0), lanes_count - 1)


@njit(cache=True, inline="always")
def _not_zero(x: float) -> float:
    """highway-env's ``utils.not_zero``: ``x`` moved away from 0 to at least 1e-2 in magnitude."""
    if abs(x) > 1e-2:
        return x
    return 1e-2 if x >= 0 else -1e-2


@njit(cache=True, error_model="numpy")
def forecast_gaps(
    xs: np.ndarray, ego_last_frame: np.ndarray, available: np.ndarray, frame_dt: float, ego_x: float,
    ego_length: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray, y: np.ndarray,
    vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray, by_contact_time: bool, lane_changes: bool,
    can_change_lane: np.ndarray, max_braking_imposed: np.ndarray, ego_lane: int,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """Per action (two (5,) arrays): the smallest bumper-to-bumper gap [m] to any vehicle in a lane the ego
    occupies, under the action's best fallback, if the others drive as forecast (module docstring) — ``-inf``
    for an unavailable action, ``inf`` where nobody shares a lane with the ego (and for every available action
    of a state without the driver models' arrays) — and the time [s] of that fallback's first contact (a
    negative gap; ``inf``: none). The best fallback has the largest gap; with ``by_contact_time``, a fallback
    without contact beats every one with, and among those with contact the later first contact wins.

    ``xs``: (5, fallbacks, frames + 1) the ego's positions [m] (``model.ego_trajectories``; the last frame,
    which credits the ego's creep beyond the horizon, is not used); ``ego_last_frame``: (5, lanes) the last
    frame the ego occupies each lane under each action (−1: never); ``available``: (5,) bool. The other
    vehicles' arrays are the :class:`~safelane.safety.model.RoadState`'s (metres, m/s, m/s²; ``lin_k0``
    NaN: an IDM driver; ``target_speed`` NaN or absent: a body with no known law — highway-env's static objects
    have none — which keeps its speed). ``lane_changes``: the others may change lane by MOBIL (module
    docstring; ``can_change_lane``, ``max_braking_imposed`` [m/s²] per vehicle, ``ego_lane`` the lane the ego is
    in now).
    """
    n_actions, n_fallbacks = xs.shape[0], xs.shape[1]
    out = np.full(n_actions, -math.inf)
    contact_time = np.full(n_actions, math.inf)
    if not _complete(x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
                     idm_comfort_dec, idm_distance_wanted, idm_time_wanted):  # fmt: skip
        for a in range(n_actions):
            if available[a]:
                out[a] = math.inf
        return out, contact_time
    # The vehicles that can share a lane with the ego: those in (or heading to) a lane it may occupy; with lane
    # changes, those in any lane.
    changes = lane_changes and can_change_lane.shape[0] == x.shape[0] and max_braking_imposed.shape[0] == x.shape[0]
    used = np.zeros(lanes_count, dtype=np.bool_)
    for a in range(n_actions):
        if available[a]:
            for lane in range(lanes_count):
                if ego_last_frame[a, lane] >= 0 or changes:
                    used[lane] = True
    pick, lane_now, lane_to, leader, set_point, v0 = _select(
        used, ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy, target_speed
    )
    no_history = np.empty((0, 0))
    for a in range(n_actions):
        if not available[a]:
            continue
        best_gap, best_contact = -math.inf, -1
        for k in range(n_fallbacks):
            smallest, contact = _rollout(
                xs[a, k], ego_last_frame[a], frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0,
                x, vx, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
                idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, changes, can_change_lane,
                max_braking_imposed, lanes_count, ego_lane, speed_limit, no_history,
            )  # fmt: skip
            if by_contact_time and k > 0 and (best_contact < 0) != (contact < 0):
                better = contact < 0  # no contact beats any contact
            elif by_contact_time and contact >= 0 and best_contact >= 0 and contact != best_contact:
                better = contact > best_contact  # the later first contact
            else:
                better = k == 0 or smallest > best_gap
            if better:
                best_gap, best_contact = smallest, contact
        out[a] = best_gap
        if best_contact >= 0:
            contact_time[a] = best_contact * frame_dt
    return out, contact_time


@njit(cache=True, error_model="numpy")
def forecast_keys(
    gaps: np.ndarray, contact_time: np.ndarray, margin: float, horizon: float, decision_period: float,
    by_contact_time: bool,
) -> np.ndarray:  # fmt: skip
    """The least-bad choice's first key per action from :func:`forecast_gaps`' ``gaps`` [m] and
    ``contact_time`` [s]: the gap capped at ``margin`` [m], and for a forecast collision (a negative or NaN gap)
    −1 whatever its depth — the depth of a forecast overlap is no measure of harm — or, ``by_contact_time``,
    ``−2 + (whole decisions before the first contact) · decision_period / horizon`` (``horizon`` [s]: the
    forecast's length), in [−2, −1): an action that buys more decisions before its forecast contact ranks higher,
    and contacts within the same decision rank alike (the shield cannot act in between; the worst-case keys, the
    gap to the vehicles ahead first, then decide). One function for both engines, so their keys are the same
    bits."""
    keys = np.empty(gaps.shape[0])
    for a in range(gaps.shape[0]):
        if gaps[a] >= 0.0:
            keys[a] = min(gaps[a], margin)
        elif not by_contact_time:
            keys[a] = -1.0
        elif math.isfinite(contact_time[a]):
            decisions = math.floor(contact_time[a] / decision_period + 1e-9)
            keys[a] = -2.0 + min(decisions * decision_period / horizon, 1.0)
        else:  # a NaN gap, or -inf (unavailable): the lowest key
            keys[a] = -2.0
    return keys


@njit(cache=True, error_model="numpy")
def forecast_paths(
    ego_path: np.ndarray, ego_last_frame: np.ndarray, frame_dt: float, ego_x: float, ego_length: float,
    lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray, y: np.ndarray, vx: np.ndarray,
    vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray, lane_changes: bool, can_change_lane: np.ndarray,
    max_braking_imposed: np.ndarray, ego_lane: int,
) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """One ego trajectory's forecast, whole: (the forecast vehicles' indices into the arrays, their positions
    [m] at every frame but the last (vehicles × frames), the smallest bumper gap [m] to the ego).

    ``ego_path``: (frames + 1,) the ego's positions [m]; ``ego_last_frame``: (lanes,) the last frame the ego
    occupies each lane (−1: never); the rest as :func:`forecast_gaps`. Every vehicle within range counts
    (not only those that can meet the ego), so the whole forecast can be compared with a simulator; with
    ``lane_changes``, the positions are along the road whatever lane the car has moved to.
    """
    if not _complete(x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
                     idm_comfort_dec, idm_distance_wanted, idm_time_wanted):  # fmt: skip
        raise ValueError("forecast_paths: the state lacks the other vehicles' driver models (brake_max, idm_*, ...)")
    used = np.ones(lanes_count, dtype=np.bool_)
    pick, lane_now, lane_to, leader, set_point, v0 = _select(
        used, ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy, target_speed
    )
    history = np.empty((pick.shape[0], ego_path.shape[0] - 1))
    changes = lane_changes and can_change_lane.shape[0] == x.shape[0] and max_braking_imposed.shape[0] == x.shape[0]
    smallest, _contact = _rollout(
        ego_path, ego_last_frame, frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0, x, vx,
        length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted,
        idm_time_wanted, lin_k0, lin_k1, lin_k2, changes, can_change_lane, max_braking_imposed, lanes_count,
        ego_lane, speed_limit, history,
    )  # fmt: skip
    return pick, history, smallest


@njit(cache=True)
def _complete(
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray,
    brake_max: np.ndarray, accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray,
    idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray,
) -> bool:  # fmt: skip
    """Whether every per-vehicle array the forecast needs has an entry per vehicle (a hand-built RoadState
    may leave the driver models out)."""
    n = x.shape[0]
    ok = crashed.shape[0] == n
    for field in (y, vx, vy, length, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
                  idm_distance_wanted, idm_time_wanted):  # fmt: skip
        ok = ok and field.shape[0] == n
    return ok


@njit(cache=True, error_model="numpy")
def _select(
    used: np.ndarray, ego_x: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray,
    y: np.ndarray, vx: np.ndarray, vy: np.ndarray, target_speed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The vehicles within :data:`FORECAST_RANGE` in (or heading to) a ``used`` lane: their indices, the lane
    they are in and the one they follow, their leader there (an index into these; −1: none), their set-point
    [m/s] and IDM's (clipped to ``speed_limit``); NaN for a body with no set-point."""
    n_all = x.shape[0]
    pick = np.empty(n_all, dtype=np.int64)
    lane_now = np.empty(n_all, dtype=np.int64)
    lane_to = np.empty(n_all, dtype=np.int64)
    m = 0
    for i in range(n_all):
        if not abs(x[i] - ego_x) < FORECAST_RANGE:
            continue
        now = _lane(y[i], lane_width, lanes_count)
        to = _lane(y[i] + vy[i] * SIDEWAYS_LOOKAHEAD, lane_width, lanes_count)
        if used[now] or used[to]:
            pick[m], lane_now[m], lane_to[m] = i, now, to
            m += 1
    # Each vehicle's leader in the lane it follows: the next one ahead there (lanes are kept and IDM does
    # not pass, so the order of the start holds).
    leader = np.full(m, -1, dtype=np.int64)
    for r in range(m):
        best = math.inf
        for q in range(m):
            if q != r and lane_to[q] == lane_to[r]:
                d = x[pick[q]] - x[pick[r]]
                if (d > 0.0 or (d == 0.0 and q > r)) and d < best:
                    best, leader[r] = d, q
    set_points = target_speed.shape[0] == n_all
    set_point = np.full(m, np.nan)  # the driver's own (the linear model reads it unclipped)
    v0 = np.full(m, np.nan)
    for r in range(m):
        i = pick[r]
        if set_points and math.isfinite(target_speed[i]):
            set_point[r] = target_speed[i]
            v0[r] = min(max(set_point[r], 0.0), speed_limit)  # IDM clips the set-point to the lane's limit
    return pick[:m].copy(), lane_now[:m].copy(), lane_to[:m].copy(), leader, set_point, v0


@njit(cache=True, error_model="numpy")
def _rollout(
    ego_path: np.ndarray, ego_last: np.ndarray, frame_dt: float, ego_length: float, pick: np.ndarray,
    lane_now_start: np.ndarray, lane_to_start: np.ndarray, leader: np.ndarray, set_point: np.ndarray,
    v0: np.ndarray, x: np.ndarray, vx: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, lane_changes: bool, can_change_lane: np.ndarray, max_braking_imposed: np.ndarray,
    lanes_count: int, ego_lane: int, speed_limit: float, history: np.ndarray,
) -> tuple[float, int]:  # fmt: skip
    """Drive the ``pick``ed vehicles frame by frame beside one ego path (``ego_last``: the last frame it is in
    each lane) and return the smallest bumper gap [m] to the ego in a lane it occupies and the first frame with a
    negative one (−1: none); ``history`` (vehicles × frames, or empty) receives their positions [m]. Each car
    follows ``leader`` (the order of the start); with ``lane_changes`` it may change lane (:func:`_mobil`), counts
    in both lanes for :data:`LANE_CHANGE_TIME`, and its leader is found again every frame: the nearest car ahead
    in the lane it follows."""
    m = pick.shape[0]
    n_t = ego_path.shape[0]
    record = history.shape[0] == m and m > 0
    linear = lin_k0.shape[0] == x.shape[0] and lin_k1.shape[0] == x.shape[0] and lin_k2.shape[0] == x.shape[0]
    pos = np.empty(m)
    spd = np.empty(m)
    acc = np.empty(m)
    lane_now = lane_now_start.copy()
    lane_to = lane_to_start.copy()
    change_end = np.full(m, -1, dtype=np.int64)
    for r in range(m):
        pos[r], spd[r] = x[pick[r]], vx[pick[r]]
    smallest = math.inf
    contact = -1
    for f in range(n_t - 1):
        ex = ego_path[f]
        for r in range(m):
            if change_end[r] == f:
                lane_now[r] = lane_to[r]
            if record:
                history[r, f] = pos[r]
            if ego_last[lane_now[r]] >= f or ego_last[lane_to[r]] >= f:
                gap = abs(pos[r] - ex) - 0.5 * (length[pick[r]] + ego_length)
                smallest = min(smallest, gap)
                if gap < 0.0 and contact < 0:
                    contact = f
        if f == n_t - 2:
            break
        ev = (ego_path[f + 1] - ex) / frame_dt  # the ego's speed over the frame
        if lane_changes:
            _mobil(
                f, ex, ev, ego_last, ego_lane, frame_dt, pick, lane_now, lane_to, change_end, pos, spd, set_point, v0,
                crashed, can_change_lane, max_braking_imposed, lanes_count, speed_limit, linear, lin_k0, lin_k1,
                lin_k2, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
            )  # fmt: skip
        for r in range(m):
            i = pick[r]
            if crashed[i] or not math.isfinite(set_point[r]):  # a wreck, or a body with no known law
                acc[r] = 0.0
                continue
            if lane_changes:  # the nearest ahead in the lane it follows (a changing car counts in both)
                d, v_front, has_front = math.inf, 0.0, False
                for q in range(m):
                    if q != r and (lane_to[q] == lane_to[r] or lane_now[q] == lane_to[r]):
                        dd = pos[q] - pos[r]
                        if (dd > 0.0 or (dd == 0.0 and q > r)) and dd < d:
                            d, v_front, has_front = dd, spd[q], True
            else:
                q = leader[r]
                has_front = q >= 0
                d = pos[q] - pos[r] if has_front else math.inf
                v_front = spd[q] if has_front else 0.0
            if ego_last[lane_to[r]] >= f and ex > pos[r] and ex - pos[r] < d:
                has_front, d, v_front = True, ex - pos[r], ev  # the ego is its leader
            a_r = _law(
                i, spd[r], set_point[r], v0[r], has_front, d, v_front, linear, lin_k0, lin_k1, lin_k2, idm_delta,
                idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
            )  # fmt: skip
            acc[r] = min(max(a_r, -brake_max[i]), accel_max[i])  # IDMVehicle.act clips to ±ACC_MAX
        for r in range(m):  # Vehicle.step: the position with the frame's speed, then the speed
            pos[r] += spd[r] * frame_dt
            spd[r] += acc[r] * frame_dt
    return smallest, contact


@njit(cache=True, error_model="numpy")
def _mobil(
    f: int, ex: float, ev: float, ego_last: np.ndarray, ego_lane: int, frame_dt: float, pick: np.ndarray,
    lane_now: np.ndarray, lane_to: np.ndarray, change_end: np.ndarray, pos: np.ndarray, spd: np.ndarray,
    set_point: np.ndarray, v0: np.ndarray, crashed: np.ndarray, can_change_lane: np.ndarray,
    max_braking_imposed: np.ndarray, lanes_count: int, speed_limit: float, linear: bool, lin_k0: np.ndarray,
    lin_k1: np.ndarray, lin_k2: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray,
    idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray,
) -> None:  # fmt: skip
    """One frame of IDMVehicle.change_lane_policy / mobil (POLITENESS 0) for the forecast's cars at frame ``f``
    (the ego at ``ex`` [m], ``ev`` [m/s]): every car that may change lane and is in one lane tries the side lanes
    (highway-env's order: the lower index first) and starts the first change MOBIL accepts — ``lane_to`` and
    ``change_end`` (the frame it is in its new lane only) are written in place."""
    m = pick.shape[0]
    # The ego's lane as highway-env's neighbour search sees it: its own until it has left it. (The bumper gaps
    # count it in every lane it touches.)
    seen_lane = ego_lane
    if ego_last[ego_lane] < f:
        for lane in range(lanes_count):
            if ego_last[lane] >= f:
                seen_lane = lane
                break
    for r in range(m):  # IDMVehicle.change_lane_policy / mobil, POLITENESS 0
        i = pick[r]
        if crashed[i] or not can_change_lane[i] or not math.isfinite(set_point[r]):
            continue
        if lane_now[r] != lane_to[r] or abs(spd[r]) < 1.0:
            continue
        d_old, v_old, has_old = math.inf, 0.0, False
        for q in range(m):
            if q != r and (lane_now[q] == lane_now[r] or lane_to[q] == lane_now[r]):
                dd = pos[q] - pos[r]
                if dd > 0.0 and dd < d_old:
                    d_old, v_old, has_old = dd, spd[q], True
        if seen_lane == lane_now[r] and ex > pos[r] and ex - pos[r] < d_old:
            d_old, v_old, has_old = ex - pos[r], ev, True
        own_now = _law(
            i, spd[r], set_point[r], v0[r], has_old, d_old, v_old, linear, lin_k0, lin_k1, lin_k2, idm_delta,
            idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
        )  # fmt: skip
        for side in (-1, 1):
            lane = lane_now[r] + side
            if lane < 0 or lane >= lanes_count:
                continue
            d_ahead, v_ahead, has_ahead = math.inf, 0.0, False
            d_behind, v_behind, set_behind, has_behind = math.inf, 0.0, 0.0, False
            for q in range(m):
                if q != r and (lane_now[q] == lane or lane_to[q] == lane):
                    dd = pos[q] - pos[r]
                    if dd > 0.0 and dd < d_ahead:
                        d_ahead, v_ahead, has_ahead = dd, spd[q], True
                    elif dd <= 0.0 and -dd < d_behind:
                        own = set_point[q] if math.isfinite(set_point[q]) else spd[q]
                        d_behind, v_behind, set_behind, has_behind = -dd, spd[q], own, True
            if seen_lane == lane:  # the ego: its set-point taken as its speed (the forecast has no other)
                dd = ex - pos[r]
                if dd > 0.0 and dd < d_ahead:
                    d_ahead, v_ahead, has_ahead = dd, ev, True
                elif dd <= 0.0 and -dd < d_behind:
                    d_behind, v_behind, set_behind, has_behind = -dd, ev, ev, True
            if has_behind:  # the new follower must not brake harder than max_braking_imposed
                imposed = _law(
                    i, v_behind, set_behind, min(max(set_behind, 0.0), speed_limit), True, d_behind, spd[r], linear,
                    lin_k0, lin_k1, lin_k2, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted,
                    idm_time_wanted,
                )  # fmt: skip
                if imposed < -max_braking_imposed[i]:
                    continue
            own_there = _law(
                i, spd[r], set_point[r], v0[r], has_ahead, d_ahead, v_ahead, linear, lin_k0, lin_k1, lin_k2,
                idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
            )  # fmt: skip
            if own_there - own_now >= MOBIL_MIN_ACC_GAIN:
                lane_to[r] = lane
                change_end[r] = f + round(LANE_CHANGE_TIME / frame_dt)
                break


@njit(cache=True, error_model="numpy")
def _law(
    i: int, v: float, set_point: float, v0: float, has_front: bool, d: float, v_front: float, linear: bool,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray,
    idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray,
) -> float:  # fmt: skip
    """Vehicle ``i``'s law (its parameters) applied to a car at ``v`` [m/s] with set-point ``set_point`` (IDM's,
    clipped to the lane's limit: ``v0``) behind a front car ``d`` [m] ahead centre to centre at ``v_front``, as
    highway-env's ``i.acceleration(ego_vehicle=that car, front_vehicle=front)``: LinearVehicle's, or IDM's."""
    if linear and math.isfinite(lin_k0[i]):  # LinearVehicle.acceleration
        d_safe = idm_distance_wanted[i] + max(v, 0.0) * idm_time_wanted[i]
        a_r = lin_k0[i] * (set_point - v)
        if has_front:
            a_r += lin_k1[i] * min(v_front - v, 0.0) + lin_k2[i] * min(d - d_safe, 0.0)
        return a_r
    # IDMVehicle.acceleration (d: centre to centre, as highway-env's lane_distance_to)
    comfort = idm_comfort_acc[i]
    a_r = comfort * (1.0 - math.pow(max(v, 0.0) / abs(_not_zero(v0)), idm_delta[i]))
    if has_front:
        ab = -comfort * idm_comfort_dec[i]
        d_star = idm_distance_wanted[i] + v * idm_time_wanted[i] + v * (v - v_front) / (2 * math.sqrt(ab))
        a_r -= comfort * (d_star / _not_zero(d)) ** 2
    return a_r
