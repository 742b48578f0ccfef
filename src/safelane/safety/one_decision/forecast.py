"""A nominal forecast of the traffic, to rank the fallback's choices when no action is safe.

The rule (:mod:`safelane.safety.one_decision.reference`) decides what is *safe* from worst cases only. When nothing is
safe it still has to pick one action, and ranking the unsafe actions by their worst-case gaps alone drives badly: in a
spawned squeeze — a leader close ahead braking for its own leader, an empty lane beside — the worst case says every
action collides and SLOWER collides least, while the planner that knows the future changes lane at once and drives
through (the claim campaign's 567 crashes from unsafe spawns: 402 of them driven through by the foresight planner,
``research/spawn_foresight.py``).

:func:`forecast_gaps` predicts what the others will most likely do instead: every vehicle keeps its lane
(the one it is heading to, if it is moving sideways) and drives by its own law — IDM, or the linear model
of Linear, Aggressive and Defensive drivers, with its own parameters and set-point, accelerations clipped
to ``[−brake_max, accel_max]`` as highway-env clips them — behind its leader in that lane, the ego among
them wherever the ego's action takes it. It is the same integration highway-env runs (acceleration from
the current state, then ``x += v·dt``, ``v += a·dt``). No lane change is predicted. A body without a
set-point (a static object; a hand-built state's unknown one) keeps its speed, and a wreck stands. The
forecast never makes an action safe; it only orders the least-bad choice (the rule's ``forecast_fallback``).

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
    lin_k2: np.ndarray, target_speed: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """Per action ((5,) array): the smallest bumper-to-bumper gap [m] to any vehicle in a lane the ego
    occupies, under the action's best fallback (the largest gap), if the others drive as forecast (module
    docstring) — ``-inf`` for an unavailable action, ``inf`` where nobody shares a lane with the ego (and for
    every available action of a state without the driver models' arrays).

    ``xs``: (5, fallbacks, frames + 1) the ego's positions [m] (``model.ego_trajectories``; the last frame,
    which credits the ego's creep beyond the horizon, is not used); ``ego_last_frame``: (5, lanes) the last
    frame the ego occupies each lane under each action (−1: never); ``available``: (5,) bool. The other
    vehicles' arrays are the :class:`~safelane.safety.one_decision.reference.RoadState`'s (metres, m/s, m/s²; ``lin_k0``
    NaN: an IDM driver; ``target_speed`` NaN or absent: a body with no known law — highway-env's static objects
    have none — which keeps its speed).
    """
    return forecast_gaps_of(
        xs, ego_last_frame, available, available, frame_dt, ego_x, ego_length, lanes_count, lane_width, speed_limit,
        x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
        idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, target_speed,
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def forecast_gaps_of(
    xs: np.ndarray, ego_last_frame: np.ndarray, available: np.ndarray, wanted: np.ndarray, frame_dt: float,
    ego_x: float, ego_length: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray,
    y: np.ndarray, vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`forecast_gaps`, rolled out only for the ``wanted`` actions ((5,) bool, within ``available``;
    every other action's entry is ``-inf``): the least-bad choice reads the keys of its pool only, and one
    action's four rollouts cost more than the rest of the rule. The vehicles forecast are still those that can
    share a lane with the ego under any ``available`` action, so a wanted action's gap is :func:`forecast_gaps`'
    to the bit."""
    return _forecast(
        xs, ego_last_frame, available, wanted, frame_dt, ego_x, ego_length, lanes_count, lane_width, speed_limit, x,
        y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
        idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, target_speed, math.nan,
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def forecast_keys_of(
    xs: np.ndarray, ego_last_frame: np.ndarray, available: np.ndarray, wanted: np.ndarray, frame_dt: float,
    ego_x: float, ego_length: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray,
    y: np.ndarray, vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray, margin: float,
) -> np.ndarray:  # fmt: skip
    """``forecast_keys(forecast_gaps_of(…), margin)`` to the bit, cheaper: the keys [m] read only the gap capped at
    ``margin`` and its sign, so an action's fallbacks stop once one keeps ``margin``, and a rollout stops once its
    gap's key can no longer beat the best key found (its gap only shrinks); a later fallback whose path is the
    stopped one's up to that frame would stop there too and is not rolled out."""
    return _forecast(
        xs, ego_last_frame, available, wanted, frame_dt, ego_x, ego_length, lanes_count, lane_width, speed_limit, x,
        y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
        idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, target_speed, margin,
    )  # fmt: skip


@njit(cache=True, error_model="numpy")
def _forecast(
    xs: np.ndarray, ego_last_frame: np.ndarray, available: np.ndarray, wanted: np.ndarray, frame_dt: float,
    ego_x: float, ego_length: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray,
    y: np.ndarray, vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray, margin: float,
) -> np.ndarray:  # fmt: skip
    """:func:`forecast_gaps_of` (``margin`` NaN: every gap [m]) or :func:`forecast_keys_of` (the keys)."""
    keys_only = not math.isnan(margin)
    n_actions, n_fallbacks = xs.shape[0], xs.shape[1]
    out = np.full(n_actions, -math.inf)
    if not _complete(x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
                     idm_comfort_dec, idm_distance_wanted, idm_time_wanted):  # fmt: skip
        for a in range(n_actions):
            if available[a] and wanted[a]:
                out[a] = math.inf
        return forecast_keys(out, margin) if keys_only else out
    # The vehicles that can share a lane with the ego: those in (or heading to) a lane it may occupy.
    used = np.zeros(lanes_count, dtype=np.bool_)
    for a in range(n_actions):
        if available[a]:
            for lane in range(lanes_count):
                if ego_last_frame[a, lane] >= 0:
                    used[lane] = True
    pick, lane_now, lane_to, leader, set_point, v0 = _select(
        used, ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy, target_speed
    )
    no_history = np.empty((0, 0))
    # Once per scene, every forecast vehicle driven with the ego in no lane (``free``, their positions per frame):
    # a vehicle that follows a lane the ego never enters under an action drives so under that action — its
    # leaders follow the same lane — so each rollout drives only the vehicles of the ego's lanes and reads the
    # others' positions here (the same operations on the same values: the same bits).
    m = pick.shape[0]
    free = np.empty((m, xs.shape[2] - 1))
    never = np.full(lanes_count, -1, dtype=np.int64)
    _rollout(
        xs[0, 0], never, frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0, x, vx, length,
        crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted,
        idm_time_wanted, lin_k0, lin_k1, lin_k2, free, no_history,
    )  # fmt: skip
    # An action's fallbacks hold its set-point for 0..3 decisions: fallback k + 1 drives as fallback k up to the
    # frame their paths part, so its rollout starts from k's state there (saved on the way; the same bits).
    n_t = xs.shape[2]
    pos, spd = np.empty(m), np.empty(m)
    saved_pos, saved_spd = np.empty(m), np.empty(m)
    # The keys read a gap only up to the margin and its sign, so rollouts may stop early (finite inputs only: a
    # NaN would make the gaps' order, and so their keys, depend on which rollouts ran).
    early = keys_only and _finite(xs) and _finite(x) and _finite(vx)
    for a in range(n_actions):
        if not (available[a] and wanted[a]):
            continue
        best_gap, best_key = -math.inf, -1.0
        start, saved_smallest = 0, math.inf
        k = 0
        while k < n_fallbacks:
            if early and best_key >= margin:
                break  # a fallback keeps the margin: the action's key is the margin whatever the others'
            if start == 0:
                smallest = math.inf
                for r in range(m):
                    pos[r], spd[r] = x[pick[r]], vx[pick[r]]
            else:
                smallest = saved_smallest
                for r in range(m):
                    pos[r], spd[r] = saved_pos[r], saved_spd[r]
            save_at = -1
            if k + 1 < n_fallbacks:  # the frame at whose start fallback k + 1's state is still k's
                same = 0
                while same < n_t and xs[a, k, same] == xs[a, k + 1, same]:
                    same += 1
                part = min(same - 1, n_t - 2)
                if part >= start and part >= 1:
                    save_at = part
            stop_key = best_key if early else math.nan
            smallest, saved, stopped = _drive(
                xs[a, k], ego_last_frame[a], frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0,
                length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec,
                idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, no_history, free, pos, spd, smallest,
                start, save_at, saved_pos, saved_spd, stop_key,
            )  # fmt: skip
            if stopped < 0:
                if k == 0 or smallest > best_gap:
                    best_gap = smallest
                if smallest >= 0.0:
                    best_key = max(best_key, min(smallest, margin))
                start, saved_smallest = (save_at, saved) if save_at >= 0 else (0, math.inf)
                k += 1
                continue
            # Fallback k's key cannot beat the best. A later fallback on k's path up to frame ``stopped`` has the
            # same vehicles and gaps up to there (they depend on the ego's positions so far only): it would stop
            # there too.
            driven, k = k, k + 1
            while k < n_fallbacks and _same_path(xs[a, k], xs[a, driven], stopped):
                k += 1
            if k == driven + 1 and save_at >= 0 and stopped >= save_at:
                start, saved_smallest = save_at, saved  # the state k starts from was saved on the way
            else:
                start, saved_smallest = 0, math.inf
        out[a] = best_key if early else best_gap
    return forecast_keys(out, margin) if keys_only else out


@njit(cache=True, inline="always")
def _finite(values: np.ndarray) -> bool:
    """Whether every entry of ``values`` is finite."""
    for v in values.flat:  # noqa: SIM110 (a loop numba compiles; all() over a generator it does not)
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True, inline="always")
def _same_path(path: np.ndarray, other: np.ndarray, last: int) -> bool:
    """Whether two ego paths [m] are the same bits at frames ``0..last``."""
    for f in range(last + 1):  # noqa: SIM110 (a loop numba compiles)
        if path[f] != other[f]:
            return False
    return True


@njit(cache=True, error_model="numpy")
def forecast_keys(gaps: np.ndarray, margin: float) -> np.ndarray:
    """The least-bad choice's first key per action from :func:`forecast_gaps`' ``gaps`` [m]: the gap capped at
    ``margin`` [m], and −1 for a forecast collision (a negative or NaN gap) whatever its depth — the depth of a
    forecast overlap is no measure of harm (the worst-case keys, the gap to the vehicles ahead first, then
    decide). One function for both engines, so their keys are the same bits."""
    keys = np.empty(gaps.shape[0])
    for a in range(gaps.shape[0]):
        if gaps[a] >= 0.0:
            keys[a] = min(gaps[a], margin)
        else:
            keys[a] = -1.0
    return keys


@njit(cache=True, error_model="numpy")
def forecast_paths(
    ego_path: np.ndarray, ego_last_frame: np.ndarray, frame_dt: float, ego_x: float, ego_length: float,
    lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray, y: np.ndarray, vx: np.ndarray,
    vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, float]:  # fmt: skip
    """One ego trajectory's forecast, whole: (the forecast vehicles' indices into the arrays, their positions
    [m] at every frame but the last (vehicles × frames), the smallest bumper gap [m] to the ego).

    ``ego_path``: (frames + 1,) the ego's positions [m]; ``ego_last_frame``: (lanes,) the last frame the ego
    occupies each lane (−1: never); the rest as :func:`forecast_gaps`. Every vehicle within range counts
    (not only those that can meet the ego), so the whole forecast can be compared with a simulator.
    """
    if not _complete(x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
                     idm_comfort_dec, idm_distance_wanted, idm_time_wanted):  # fmt: skip
        raise ValueError("forecast_paths: the state lacks the other vehicles' driver models (brake_max, idm_*, ...)")
    used = np.ones(lanes_count, dtype=np.bool_)
    pick, lane_now, lane_to, leader, set_point, v0 = _select(
        used, ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy, target_speed
    )
    history = np.empty((pick.shape[0], ego_path.shape[0] - 1))
    smallest = _rollout(
        ego_path, ego_last_frame, frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0, x, vx,
        length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted,
        idm_time_wanted, lin_k0, lin_k1, lin_k2, history, np.empty((0, 0)),
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
    lane_now: np.ndarray, lane_to: np.ndarray, leader: np.ndarray, set_point: np.ndarray,
    v0: np.ndarray, x: np.ndarray, vx: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, history: np.ndarray, free: np.ndarray,
) -> float:  # fmt: skip
    """Drive the ``pick``ed vehicles frame by frame beside one ego path (``ego_last``: the last frame it is in
    each lane) and return the smallest bumper gap [m] to the ego in a lane it occupies; ``history`` (vehicles ×
    frames, or empty) receives their positions [m]. Each car follows ``leader`` (the order of the start).
    ``free`` (vehicles × frames, or empty): the positions [m] of the vehicles driven with the ego in no lane; a
    vehicle that follows a lane the ego never occupies takes its positions from there instead of being driven."""
    m = pick.shape[0]
    pos = np.empty(m)
    spd = np.empty(m)
    for r in range(m):
        pos[r], spd[r] = x[pick[r]], vx[pick[r]]
    none = np.empty(0)
    smallest, _, _ = _drive(
        ego_path, ego_last, frame_dt, ego_length, pick, lane_now, lane_to, leader, set_point, v0, length, crashed,
        brake_max, accel_max, idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
        lin_k0, lin_k1, lin_k2, history, free, pos, spd, math.inf, 0, -1, none, none,
    )  # fmt: skip
    return smallest


@njit(cache=True, error_model="numpy")
def _drive(
    ego_path: np.ndarray, ego_last: np.ndarray, frame_dt: float, ego_length: float, pick: np.ndarray,
    lane_now: np.ndarray, lane_to: np.ndarray, leader: np.ndarray, set_point: np.ndarray, v0: np.ndarray,
    length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, idm_delta: np.ndarray,
    idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray,
    idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, history: np.ndarray,
    free: np.ndarray, pos: np.ndarray, spd: np.ndarray, smallest: float, start: int, save_at: int,
    save_pos: np.ndarray, save_spd: np.ndarray, stop_key: float = math.nan,
) -> tuple[float, float, int]:  # fmt: skip
    """:func:`_rollout` from the start of frame ``start``, the vehicles at ``pos`` [m] and ``spd`` [m/s] (changed
    in place) and the smallest gap so far ``smallest`` [m]: (the smallest gap [m], the smallest gap at the start of
    frame ``save_at``, whose positions and speeds go to ``save_pos``, ``save_spd``; inf when ``save_at`` is −1;
    the frame at which the rollout stopped early, −1 when it ran to the end).

    ``stop_key`` (a :func:`forecast_keys` key in [−1, margin), NaN: never stop): stop once the smallest gap's key
    is at most ``stop_key`` — the gap only shrinks, so its key can no longer exceed ``stop_key``."""
    m = pick.shape[0]
    n_t = ego_path.shape[0]
    record = history.shape[0] == m and m > 0
    use_free = free.shape[0] == m and m > 0
    n_all = crashed.shape[0]  # every vehicle's (the callers checked _complete)
    linear = lin_k0.shape[0] == n_all and lin_k1.shape[0] == n_all and lin_k2.shape[0] == n_all
    acc = np.empty(m)
    saved = math.inf
    for f in range(start, n_t - 1):
        if f == save_at:
            for r in range(m):
                save_pos[r], save_spd[r] = pos[r], spd[r]
            saved = smallest
        ex = ego_path[f]
        for r in range(m):
            if use_free and ego_last[lane_to[r]] < 0:
                pos[r] = free[r, f]
            if record:
                history[r, f] = pos[r]
            if ego_last[lane_now[r]] >= f or ego_last[lane_to[r]] >= f:
                gap = abs(pos[r] - ex) - 0.5 * (length[pick[r]] + ego_length)
                smallest = min(smallest, gap)
        if not math.isnan(stop_key) and (smallest < 0.0 or smallest <= stop_key):  # key −1, or a key ≤ stop_key
            return smallest, saved, f
        if f == n_t - 2:
            break
        ev = (ego_path[f + 1] - ex) / frame_dt  # the ego's speed over the frame
        for r in range(m):
            i = pick[r]
            if use_free and ego_last[lane_to[r]] < 0:
                continue  # read from free
            if crashed[i] or not math.isfinite(set_point[r]):  # a wreck, or a body with no known law
                acc[r] = 0.0
                continue
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
            if use_free and ego_last[lane_to[r]] < 0:
                continue
            pos[r] += spd[r] * frame_dt
            spd[r] += acc[r] * frame_dt
    return smallest, saved, -1


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


@njit(cache=True, error_model="numpy")
def current_accelerations(
    ego_x: float, lanes_count: int, lane_width: float, speed_limit: float, x: np.ndarray, y: np.ndarray,
    vx: np.ndarray, vy: np.ndarray, length: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, target_speed: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """[m/s²] Each vehicle's acceleration now, as the forecast's first frame has it (its law behind its leader in the
    lane it follows, the ego left out, clipped as highway-env clips it): 0 for a wreck, a body without a known law,
    one beyond :data:`FORECAST_RANGE`, and every vehicle of a state without the driver models' arrays. Both engines
    call this one kernel, so their accelerations are the same bits."""
    n = x.shape[0]
    out = np.zeros(n)
    if not _complete(x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
                     idm_comfort_dec, idm_distance_wanted, idm_time_wanted):  # fmt: skip
        return out
    used = np.ones(lanes_count, dtype=np.bool_)
    pick, _, _, leader, set_point, v0 = _select(used, ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy,
                                                target_speed)  # fmt: skip
    linear = lin_k0.shape[0] == n and lin_k1.shape[0] == n and lin_k2.shape[0] == n
    for r in range(pick.shape[0]):
        i = pick[r]
        if crashed[i] or not math.isfinite(set_point[r]):
            continue
        q = leader[r]
        has_front = q >= 0
        d = x[pick[q]] - x[i] if has_front else math.inf
        v_front = vx[pick[q]] if has_front else 0.0
        a_r = _law(i, vx[i], set_point[r], v0[r], has_front, d, v_front, linear, lin_k0, lin_k1, lin_k2, idm_delta,
                   idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted)  # fmt: skip
        out[i] = min(max(a_r, -brake_max[i]), accel_max[i])
    return out


@njit(cache=True, inline="always")
def accelerated(x: float, v: float, a: float, tau: float) -> tuple[float, float]:
    """Position [m] and speed [m/s] after ``tau`` [s] of a body at ``x``, ``v`` keeping acceleration ``a`` [m/s²]; a
    body braking forward stops (and stays) where its speed reaches 0."""
    t = tau
    if a < 0.0 and v > 0.0:
        t = min(tau, v / -a)
    return x + v * t + 0.5 * a * (t * t), v + a * t
