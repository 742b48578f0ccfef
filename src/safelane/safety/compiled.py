"""The safety model compiled: :func:`safelane.safety.model.evaluate` as one numba kernel per state.

:func:`evaluate_compiled` has ``evaluate``'s signature and returns the same :class:`SafetyResult` —
the same mask, safe, available and fallback, and ``min_gap`` to the bit — in microseconds instead of
a millisecond. :mod:`safelane.safety.model` stays the readable specification; this module follows it
operation by operation and in the same order, so the IEEE-754 arithmetic (no fastmath) rounds the
same way: numpy's ``x**2`` on arrays is ``x*x``, ``np.cumsum`` a sequential sum, ``np.minimum`` /
``np.maximum`` propagate NaN (:func:`_nmin`, :func:`_nmax`), ``np.power`` / ``np.cos`` & co. are
libm's, as numba's calls are (checked: numpy dispatches no SIMD transcendental on this build's
x86-64-v3 baseline; SVML is not used by numba here). The constants that depend only on the dynamics
(frame times, the P-controller's decay powers) are computed by numpy exactly as the reference does,
once per :class:`Dynamics`, and handed to the kernel.

:func:`evaluate_snapshot` is the shield's fast path: it reads a :class:`RoadSnapshot` directly and
builds the :class:`RoadState` arrays inside the kernel (as :func:`safelane.safety.shield.road_state`
does, bit for bit on axis-aligned roads — every highway-env straight road), so no Python object per
vehicle and no ``RoadState`` is built.

Units: metres, m/s, seconds. ``formula="paper"`` (eq. 12, nominal only) is delegated to the numpy
reference: it is a baseline evaluated at decision time, not on the shield's hot path.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from safelane.core import spaces
from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.core.snapshot import RoadSnapshot
from safelane.safety import forecast, model
from safelane.safety.forecast import forecast_gaps, forecast_keys
from safelane.safety.model import Dynamics, Formula, Mode, RoadState, SafetyResult

# The rule's kernel compiles in the forecast's (safelane.safety.forecast): numba's cache watches this file only.
drop_stale_kernel_cache(__file__, (forecast.__file__,))

# The kernels use the action indices as literals (numba freezes globals at compile time, and its disk
# cache only watches this file): check here that they are still the core's.
LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4
N_ACTIONS = 5
# The forecast's ranking as one kernel argument, bit flags (Dynamics.forecast_fallback, forecast_contact_time,
# forecast_lane_changes; the last two mean nothing without the first).
FORECAST_ON, FORECAST_BY_CONTACT_TIME, FORECAST_LANE_CHANGES = 1, 2, 4
N_FALLBACKS = 4  # fallbacks k = 0..MAX_HOLD_DECISIONS (a literal, so the loops over them unroll)
assert (spaces.LANE_LEFT, spaces.IDLE, spaces.LANE_RIGHT, spaces.FASTER, spaces.SLOWER) == (0, 1, 2, 3, 4)
assert spaces.N_ACTIONS == N_ACTIONS and model.MAX_HOLD_DECISIONS + 1 == N_FALLBACKS, "update compiled.py"

# The model's other constants travel as arguments for the same reason (no stale cached kernel).
_TIE_BREAK = np.array(model.TIE_BREAK_ORDER, dtype=np.int64)
_RELEVANCE = float(model.RELEVANCE_RANGE)
_LATERAL = float(model.LATERAL_MOTION_THRESHOLD)
_MIN_ACC_GAIN = float(model.MOBIL_MIN_ACC_GAIN)
# Literals the kernels read as globals (frozen at compile time): checked against the model's here.
IDM_LANE_MARGIN = 1.0
NOT_ZERO = 1e-2
assert (model.IDM_LANE_MARGIN, model.NOT_ZERO) == (IDM_LANE_MARGIN, NOT_ZERO), "update compiled.py"


# --------------------------------------------------------------------------------------------
# numpy's scalar semantics.
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def _nmin(a: float, b: float) -> float:
    """``np.minimum(a, b)``: NaN if either is NaN (Python's ``min`` is not)."""
    return a if (a <= b or a != a) else b


@njit(cache=True, inline="always")
def _nmax(a: float, b: float) -> float:
    """``np.maximum(a, b)``: NaN if either is NaN."""
    return a if (a >= b or a != a) else b


@njit(cache=True, inline="always")
def _speed_index(speed: float, ts: np.ndarray) -> int:
    """``model.speed_to_index`` for one speed (``np.round`` is ``rint``: halves to even)."""
    n = ts.shape[0]
    r = np.rint((speed - ts[0]) / (ts[n - 1] - ts[0]) * (n - 1))
    return int(_nmin(_nmax(r, 0.0), n - 1.0))


@njit(cache=True, inline="always")
def _lane_index(y: float, lane_width: float, lanes_count: int) -> int:
    """``RoadState.lane_of`` for one lateral position [m]."""
    return int(_nmin(_nmax(np.rint(y / lane_width), 0.0), lanes_count - 1.0))


@njit(cache=True, inline="always")
def _idm_behind(
    acc: float, delta: float, dec: float, wanted: float, time_wanted: float, vx: float,
    gap: float, ego_speed: float, ego_target: float,
) -> float:  # fmt: skip
    """``model.idm_acceleration_behind`` for one vehicle (same operations, same order)."""
    target = 1e-2 if abs(ego_target) < 1e-2 else ego_target
    free = acc * (1 - math.pow(_nmax(ego_speed, 0.0) / abs(target), delta))
    ab = -acc * dec
    dv = ego_speed - vx
    d_star = wanted + ego_speed * time_wanted + ego_speed * dv / (2 * np.sqrt(ab))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    q = d_star / d
    return free - acc * (q * q)


@njit(cache=True, error_model="numpy")
def _linear_behind(
    k0: float, k1: float, k2: float, wanted: float, time_wanted: float, own_speed: float,
    gap: float, ego_speed: float, ego_target: float,
) -> float:  # fmt: skip
    """``model.linear_acceleration_behind`` for one vehicle (same operations, same order)."""
    d_safe = wanted + _nmax(ego_speed, 0.0) * time_wanted
    return k0 * (ego_target - ego_speed) + k1 * _nmin(own_speed - ego_speed, 0.0) + k2 * _nmin(gap - d_safe, 0.0)


@njit(cache=True, error_model="numpy")
def _least_desired_gap(
    acc: float, dec: float, wanted: float, time_wanted: float, ego_speed: float, speed_low: float, speed_high: float
) -> float:  # fmt: skip
    """``model.least_desired_gap`` for one vehicle (same operations, same order)."""
    ab = -acc * dec
    base = wanted + ego_speed * time_wanted
    d_hi = base + ego_speed * (ego_speed - speed_high) / (2 * np.sqrt(ab))
    d_lo = base + ego_speed * (ego_speed - speed_low) / (2 * np.sqrt(ab))
    lo, hi = _nmin(d_hi, d_lo), _nmax(d_hi, d_lo)
    if lo > 0.0:
        return lo
    if hi < 0.0:
        return -hi
    return 0.0


@njit(cache=True, error_model="numpy")
def _idm_behind_gap(
    acc: float, delta: float, ego_speed: float, ego_target: float, gap: float, desired_gap: float
) -> float:  # fmt: skip
    """``model.idm_acceleration_behind_gap`` for one vehicle (same operations, same order)."""
    target = 1e-2 if abs(ego_target) < 1e-2 else ego_target
    free = acc * (1 - math.pow(_nmax(ego_speed, 0.0) / abs(target), delta))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    q = desired_gap / d
    return free - acc * (q * q)


@njit(cache=True, error_model="numpy")
def _passing_path(
    out: np.ndarray, i: int, x: np.ndarray, vx: np.ndarray, vy: np.ndarray, brake_max: np.ndarray,
    accel_max: np.ndarray, max_braking_imposed: np.ndarray, dw_all: np.ndarray, tw_all: np.ndarray,
    acc_all: np.ndarray, dec_all: np.ndarray, delta_all: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray,
    lin_k2: np.ndarray, speed_limit: float, ego_xs: np.ndarray, ego_speed: float, powers: np.ndarray,
    frames: int, kv: float, kt: float, t: np.ndarray, cut_in_time: float, first: float, allowance: float,
) -> None:  # fmt: skip
    """``model.passing_positions`` for vehicle ``i`` into ``out`` (same operations, same order): the ego's
    frames from ``ego_xs[f, 0]`` and its speeds as the cut-in criterion takes them."""
    n_t = t.shape[0]
    for j in range(n_t):
        out[j] = np.inf
    b = _nmax(brake_max[i], 1e-6)
    limit = -max_braking_imposed[i]
    accel = _nmax(accel_max[i], 0.0)
    dw, tw = dw_all[i], tw_all[i]
    for f in range(frames + 1):
        tau = t[f]
        if not tau >= first:
            continue
        ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
        # model.required_gap
        if np.isfinite(lin_k0[i]):
            own = math.hypot(vx[i], vy[i]) + accel * tau
            other = lin_k0[i] * (kt - ego_vf) + lin_k1[i] * min(own - ego_vf, 0.0)
            if not (other >= limit and lin_k2[i] > 0.0):
                continue
            d_safe = dw + max(ego_vf, 0.0) * tw
            d_req = max(d_safe - (other - limit) / lin_k2[i], 0.0)
        else:
            acc, delta, dec = acc_all[i], delta_all[i], dec_all[i]
            target = min(max(kt, 0.0), speed_limit)
            target = 1e-2 if abs(target) < 1e-2 else target
            free = acc * (1 - math.pow(max(ego_vf, 0.0) / abs(target), delta))
            room = (free - limit) / acc
            if not room > 0.0:
                continue
            v_lo = max(vx[i] - b * tau, 0.0)
            q = _least_desired_gap(acc, dec, dw, tw, ego_vf, v_lo, vx[i] + accel * tau)
            d_req = q / math.sqrt(room)
        if not np.isfinite(d_req):
            continue
        v = max(vx[i] - b * tau, 0.0)
        start = tau + cut_in_time
        lo = 0
        while lo < n_t and not (t[lo] >= start):
            lo += 1
        for j in range(lo, n_t):
            s = t[j] - tau
            tt = min(s, v / b)
            xj = ((ego_xs[f, 0] + d_req) + (v * tt - 0.5 * b * (tt * tt))) - allowance
            out[j] = _nmin(out[j], xj)


@njit(cache=True, inline="always")
def _braking_from_now(x0: float, v: float, crashed: bool, brake: float, tau: float) -> tuple[float, float]:
    """Position [m] and speed [m/s] at ``tau`` [s] of a vehicle braking at its limit ``brake`` [m/s²] from now,
    from its forward speed (a crashed one stopped): the model's leader braking, same operations, same order."""
    v0 = 0.0 if crashed else _nmax(v, 0.0)
    b = _nmax(1e9 if crashed else brake, 1e-6)
    s = _nmin(tau, v0 / b)
    return x0 + v0 * s - 0.5 * b * (s * s), v0 - b * s


@njit(cache=True, error_model="numpy")
def _incentive_first(
    i: int, r: int, m: int, near: np.ndarray, lanes_near: np.ndarray, x: np.ndarray, vx: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray,
    dw_all: np.ndarray, tw_all: np.ndarray, acc_all: np.ndarray, dec_all: np.ndarray, linear_incentive: bool,
    linear_incentive_braking: bool, ego_xs: np.ndarray, ego_speed: float, kv: float, kt: float,
    powers: np.ndarray, frames: int, t: np.ndarray, min_acc_gain: float,
) -> float:  # fmt: skip
    """``model.incentive_times`` for vehicle ``i`` (row ``r``; same operations, same order): the first frame time
    [s] at which MOBIL's incentive lets it turn in behind the ego; inf: none."""
    v = vx[i]
    linear = np.isfinite(lin_k0[i])
    if linear and not linear_incentive:
        return np.inf
    dw, tw, acc, dec = dw_all[i], tw_all[i], acc_all[i], dec_all[i]
    k1, k2 = lin_k1[i], lin_k2[i]
    d_safe = dw + _nmax(v, 0.0) * tw
    for f in range(frames + 1):
        tau = t[f]
        own_x = x[i] + v * tau
        d = own_x - ego_xs[f, 0]
        if not d <= 0:
            continue
        ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
        if linear:
            ego_term = k1 * _nmin(ego_vf - v, 0.0) + k2 * _nmin(-d - d_safe, 0.0)
            lead = braking = 0.0
            found = False
            for k in range(m):
                ii = near[k]
                if lanes_near[k] == lanes_near[r] and x[ii] > x[i]:
                    lv = vx[ii]
                    term = k1 * _nmin(lv - v, 0.0) + k2 * _nmin(((x[ii] + lv * tau) - own_x) - d_safe, 0.0)
                    lx, lvb = _braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    term_b = k1 * _nmin(lvb - v, 0.0) + k2 * _nmin((lx - own_x) - d_safe, 0.0)
                    if found:
                        lead, braking = _nmin(lead, term), _nmin(braking, term_b)
                    else:
                        lead, braking, found = term, term_b, True
            gains = ego_term - lead >= min_acc_gain
            if linear_incentive_braking:
                gains = gains or ego_term - braking >= min_acc_gain
            if gains:
                return tau
        else:
            lead = 0.0
            found = False
            for k in range(m):
                ii = near[k]
                if lanes_near[k] == lanes_near[r] and x[ii] > x[i]:
                    lv = vx[ii]
                    q = _gap_ratio(dw, tw, acc, dec, v, lv, (x[ii] + lv * tau) - own_x)
                    lead = _nmax(lead, q * q) if found else q * q
                    found = True
            q_ego = _gap_ratio(dw, tw, acc, dec, v, ego_vf, -d)
            if acc * lead - acc * (q_ego * q_ego) >= min_acc_gain:
                return tau
    return np.inf


@njit(cache=True, inline="always")
def _desired_gap_range(
    dw: float, tw: float, root_ab: float, v_lo: float, v_hi: float, front_lo: float, front_hi: float
) -> tuple[float, float]:  # fmt: skip
    """``model._desired_gap_range`` (same operations, same order): the least and largest desired gap [m]."""
    c = 2 * root_ab
    top_lo = dw + v_lo * tw + v_lo * (v_lo - front_lo) / c
    top_hi = dw + v_hi * tw + v_hi * (v_hi - front_lo) / c
    top = top_hi if top_hi > top_lo else top_lo
    vertex = min(max(0.5 * (front_hi - tw * c), v_lo), v_hi)
    bottom = dw + vertex * tw + vertex * (vertex - front_hi) / c
    return bottom, top


@njit(cache=True, error_model="numpy")
def _incentive_first_any_speed(
    i: int, r: int, m: int, near: np.ndarray, lanes_near: np.ndarray, x: np.ndarray, vx: np.ndarray,
    vy: np.ndarray, crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, lin_k0: np.ndarray,
    lin_k1: np.ndarray, lin_k2: np.ndarray, dw_all: np.ndarray, tw_all: np.ndarray, acc_all: np.ndarray,
    dec_all: np.ndarray, linear_incentive: bool, ego_xs: np.ndarray, ego_speed: float, kv: float, kt: float,
    powers: np.ndarray, frames: int, t: np.ndarray, min_acc_gain: float,
) -> float:  # fmt: skip
    """``model.incentive_times_any_speed`` for vehicle ``i`` (row ``r``; same operations, same order): the first
    frame time [s] at which MOBIL's incentive could let it turn in behind the ego; inf: none."""
    linear = np.isfinite(lin_k0[i])
    if linear and not linear_incentive:
        return np.inf
    dw, tw, acc = dw_all[i], tw_all[i], acc_all[i]
    k1, k2 = lin_k1[i], lin_k2[i]
    root_ab = np.sqrt(-acc * dec_all[i])
    v0 = 0.0 if crashed[i] else _nmax(vx[i], 0.0)
    accel = 0.0 if crashed[i] else _nmax(accel_max[i], 0.0)
    speed = 0.0 if crashed[i] else math.hypot(vx[i], vy[i])
    for f in range(frames + 1):
        tau = t[f]
        x_lo, v_lo = _braking_from_now(x[i], vx[i], crashed[i], brake_max[i], tau)
        x_hi = x[i] + v0 * tau + 0.5 * accel * (tau * tau)
        v_hi = speed + accel * tau
        if not x_lo - ego_xs[f, 0] <= 0:
            continue
        ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
        gap_ego = ego_xs[f, 0] - x_lo
        if linear:
            ego_term = k1 * min(ego_vf - v_lo, 0.0) + k2 * min(gap_ego - (dw + v_lo * tw), 0.0)
            lead = 0.0
            found = False
            for k in range(m):
                ii = near[k]
                if lanes_near[k] == lanes_near[r] and x[ii] > x[i]:
                    lx_lo, lv_lo = _braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    term = k1 * _nmin(lv_lo - v_hi, 0.0) + k2 * _nmin((lx_lo - x_hi) - (dw + v_hi * tw), 0.0)
                    lead = _nmin(lead, term) if found else term
                    found = True
            if ego_term - lead >= min_acc_gain:
                return tau
        else:
            lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo, v_hi, ego_vf, ego_vf)
            least = lo if lo > 0.0 else (-hi if hi < 0.0 else 0.0)
            q_ego = least / max(gap_ego, 1e-2)
            ego_term = q_ego * q_ego
            lead = 0.0
            for k in range(m):
                ii = near[k]
                if lanes_near[k] == lanes_near[r] and x[ii] > x[i]:
                    lx_lo, lv_lo = _braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    la = 0.0 if crashed[ii] else _nmax(accel_max[ii], 0.0)
                    lv_hi = (0.0 if crashed[ii] else math.hypot(vx[ii], vy[ii])) + la * tau
                    gap = lx_lo - x_hi
                    if not gap >= 1e-2:
                        lead = np.inf  # the gap may close: IDM's term has no bound
                        break
                    lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo, v_hi, lv_lo, lv_hi)
                    q = max(hi, -lo) / gap
                    lead = max(lead, q * q)
            if acc * lead - acc * ego_term >= min_acc_gain:
                return tau
    return np.inf


@njit(cache=True, inline="always")
def _gap_ratio(
    dw: float, tw: float, acc: float, dec: float, v: float, front_speed: float, gap: float
) -> float:  # fmt: skip
    """``model._gap_ratio`` for one vehicle (same operations, same order)."""
    ab = -acc * dec
    d_star = dw + v * tw + v * (v - front_speed) / (2 * np.sqrt(ab))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    return d_star / d


@njit(cache=True, inline="always")
def _follower_row(
    out: np.ndarray, x0: float, vx: float, acc: float, brake: float, t_r: float, t: np.ndarray
) -> None:  # fmt: skip
    """``model.follower_positions`` for one vehicle into ``out`` (same operations, same order)."""
    v0 = _nmax(vx, 0.0)
    b = _nmax(brake, 1e-6)
    ha = 0.5 * acc
    hb = 0.5 * b
    v1 = v0 + acc * t_r
    stop = v1 / b
    for j in range(t.shape[0]):
        t1 = _nmin(t[j], t_r)
        x1 = x0 + v0 * t1 + ha * (t1 * t1)
        t2 = _nmin(_nmax(t[j] - t_r, 0.0), stop)
        out[j] = x1 + v1 * t2 - hb * (t2 * t2)


# --------------------------------------------------------------------------------------------
# The evaluation.
# --------------------------------------------------------------------------------------------


@njit(cache=True, error_model="numpy")
def _idm_follower_window(
    i: int, x: np.ndarray, vx: np.ndarray, comfort_acc: np.ndarray, comfort_dec: np.ndarray,
    distance_wanted: np.ndarray, time_wanted: np.ndarray, accel_max: np.ndarray, brake_max: np.ndarray,
    idm_delta: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, target_speed: np.ndarray,
    set_point: bool, speed_limit: float,
    ego_xs: np.ndarray, ego_vs: np.ndarray, frame_dt: float, reaction: float, half: float, lo: int, hi: int,
    xf4: np.ndarray, vf4: np.ndarray, worst: np.ndarray,
) -> None:  # fmt: skip
    """``model.idm_follower_positions`` of follower ``i`` against one action's fallbacks (``ego_xs``,
    ``ego_vs``: [frame, fallback]), and its worst gap [m] behind the ego over frames ``lo..hi`` into
    ``worst`` (same operations, same order)."""
    acc = comfort_acc[i]
    two_sqrt_ab = 2.0 * math.sqrt(-acc * comfort_dec[i])
    d0, tw = distance_wanted[i], time_wanted[i]
    a_max, b_max = accel_max[i], brake_max[i]
    v0 = target_speed[i]
    exact = set_point and np.isfinite(v0)
    linear = not math.isnan(lin_k0[i])
    k0, k1, k2 = lin_k0[i], lin_k1[i], lin_k2[i]
    target = _nmin(_nmax(v0, 0.0), speed_limit) if exact else 1.0  # min(max(·)) of Python floats: no NaN here
    if not (abs(target) > NOT_ZERO):
        target = NOT_ZERO if target >= 0.0 else -NOT_ZERO
    target = abs(target)
    delta = idm_delta[i]
    last = ego_xs.shape[0] - 1
    for k in range(N_FALLBACKS):
        xf4[k] = x[i]
        vf4[k] = vx[i]
        worst[k] = math.inf
    for j in range(hi + 1):
        for k in range(N_FALLBACKS):
            o = xf4[k]
            if j == last:  # model: what the follower bound still covers beyond the last frame
                v = _nmax(vf4[k], 0.0)
                v1 = v + a_max * reaction
                o = o + (v * reaction + 0.5 * a_max * (reaction * reaction) + v1 * v1 / (2.0 * max(b_max, 1e-6)))
            if j >= lo:
                worst[k] = _nmin(worst[k], -1.0 * (o - ego_xs[j, k]) - half)
            if j < hi:  # IDMVehicle.act at frame j, then Vehicle.step
                vf = vf4[k]
                if linear:  # model: LinearVehicle.acceleration (only with a known set-point)
                    d_safe = d0 + _nmax(vf, 0.0) * tw
                    acc_f = (
                        k0 * (v0 - vf)
                        + k1 * _nmin(ego_vs[j, k] - vf, 0.0)
                        + k2 * _nmin((ego_xs[j, k] - xf4[k]) - d_safe, 0.0)
                    )
                else:
                    free = acc * (1.0 - (_nmax(vf, 0.0) / target) ** delta) if exact else acc
                    d = ego_xs[j, k] - xf4[k]
                    if not (abs(d) > NOT_ZERO):
                        d = NOT_ZERO if d >= 0.0 else -NOT_ZERO
                    ratio = (d0 + vf * tw + vf * (vf - ego_vs[j, k]) / two_sqrt_ab) / d
                    acc_f = free - acc * (ratio * ratio)
                acc_f = _nmax(_nmin(acc_f, a_max), -b_max)
                xf4[k] = xf4[k] + vf4[k] * frame_dt
                vf4[k] = vf4[k] + acc_f * frame_dt


@njit(cache=True, error_model="numpy")
def _ego_lane_windows(
    y: float, heading: float, ego_length: float, final: int, lanes: int, width: float, dt: float, frames: int,
    speed: float, ego_width: float, body_width: float, kp_lateral: float, kp_heading: float, max_steering: float,
    last: np.ndarray, out_lanes: np.ndarray, out_until: np.ndarray, out_seen: np.ndarray,
) -> int:  # fmt: skip
    """``model.lateral_schedule`` line for line: the lanes into ``out_lanes`` and their times [s] into
    ``out_until``, the lanes the ego leaves seen by MOBIL into ``out_seen`` (``last``: scratch, one entry per
    lane); returns how many."""
    half_length = 0.5 * ego_length
    target_y = final * width
    band = 0.5 * width + IDM_LANE_MARGIN
    for lane in range(lanes):
        last[lane] = -1
        out_seen[lane] = abs(y - lane * width) <= band
    end = frames
    for k in range(frames + 1):
        reach = 0.5 * ego_width * math.cos(heading) + half_length * abs(math.sin(heading))
        alone = True
        for lane in range(lanes):
            if abs(y - lane * width) < reach + 0.5 * body_width:
                last[lane] = k
                alone = alone and lane == final
                if abs(y - lane * width) > band:  # overlapped, but out of MOBIL's sight there
                    out_seen[lane] = False
        end = k
        if k == frames or not speed > 0.0 or (alone and (y - target_y) * heading <= 0.0):
            break
        lateral_speed_command = -kp_lateral * (y - target_y)
        heading_command = math.asin(min(max(lateral_speed_command / speed, -1.0), 1.0))
        heading_ref = min(max(heading_command, -0.25 * math.pi), 0.25 * math.pi)
        heading_rate_command = kp_heading * (heading_ref - heading)
        slip = math.asin(min(max(half_length / speed * heading_rate_command, -1.0), 1.0))
        steering = min(max(math.atan(2.0 * math.tan(slip)), -max_steering), max_steering)
        beta = math.atan(0.5 * math.tan(steering))
        y = y + speed * math.sin(heading + beta) * dt
        heading = heading + speed * math.sin(beta) / half_length * dt
    n = 0
    for lane in range(lanes):
        if lane == final or last[lane] < 0:
            continue
        out_lanes[n] = lane
        out_until[n] = math.inf if last[lane] == end else (last[lane] + 1) * dt + dt
        n += 1
    out_lanes[n] = final
    out_until[n] = math.inf
    out_seen[final] = False
    return n + 1


@njit(cache=True, error_model="numpy")
def _evaluate_rule(
    ego_x: float, ego_speed: float, ego_lane: int, ego_target_lane: int, ego_target_speed: float,
    ego_speed_index: int, ego_length: float, speed_limit: float, ego_y: float, ego_heading: float,
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, target_speed: np.ndarray,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray,
    decision_period: float, frame_dt: float, frames: int, horizon: int, ego_kp: float, lane_width: float,
    lanes_count: int, follower_reaction: float, ego_leave_time: float, ego_lateral_speed: float,
    cut_in_time: float, margin: float,
    relevance: float, lateral_threshold: float, robust: bool, projected_cut_ins: bool, body_extent: bool,
    body_width: float, linear_mobil: bool, reversing_leaders: bool, level_cut_ins: bool, level_incentive: bool,
    level_entering: bool, least_bad_joint: bool, robust_fallback: bool, linear_incentive: bool,
    linear_incentive_braking: bool, reversing_cut_ins: bool, crossed_lanes: bool, lateral_schedule: bool,
    reversing_noses: bool, follower_idm: bool, follower_set_point: bool, finishing_changes: bool,
    cut_in_when_permitted: bool, leaving_lanes_seen: bool,
    permit_any_speed: bool, passing_cut_ins: bool, level_when_incentive: bool, incentive_any_speed: bool,
    nominal_allowance: float, forecast_fallback: int,
    ego_width: float, kp_lateral: float,
    kp_heading: float, max_steering: float, turning_allowance: float,
    min_acc_gain: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """``model.evaluate`` (formula ``kinematic``) of one state: (mask, safe, available, min_gap, fallback)."""
    n_ts = ts.shape[0]
    n_t = t.shape[0]  # frames of the horizon + 1
    total = n_t - 1

    # --- available_actions -------------------------------------------------------------------
    available = np.zeros(N_ACTIONS, dtype=np.bool_)
    available[IDLE] = True
    available[LANE_LEFT] = ego_lane > 0
    available[LANE_RIGHT] = ego_lane < lanes_count - 1
    available[FASTER] = ego_speed_index < n_ts - 1
    available[SLOWER] = ego_speed_index > 0

    # --- action_targets ----------------------------------------------------------------------
    idx_now = _speed_index(ego_speed, ts)
    targets = np.full(N_ACTIONS, ego_target_speed)
    targets[FASTER] = ts[min(idx_now + 1, n_ts - 1)]
    targets[SLOWER] = ts[max(idx_now - 1, 0)]

    # --- ego_trajectories: xs[a, frame, k] (the reference's (5, F, T) transposed, so the gap loop
    # below runs the 4 fallbacks side by side); the speeds only where evaluate reads them ----------
    xs = np.empty((N_ACTIONS, n_t, N_FALLBACKS))
    vs = np.empty((N_ACTIONS, n_t if follower_idm else 0, N_FALLBACKS))  # the speeds, for IDM followers
    v_key = np.empty(N_ACTIONS)  # ego_v[a, 0, frames]: the cut-in key
    v4 = np.empty(N_FALLBACKS)  # per fallback: speed, position, set-point at the decision's start...
    x4 = np.empty(N_FALLBACKS)
    tg4 = np.empty(N_FALLBACKS)
    dv4 = np.empty(N_FALLBACKS)
    vp4 = np.empty(N_FALLBACKS)  # ...the frame's speed and the running sum of the speeds
    cov4 = np.empty(N_FALLBACKS)
    for a in range(N_ACTIONS):
        # IDLE and the lane changes share their set-point (FASTER / SLOWER may too): one trajectory per
        # distinct set-point, copied — the same computation on the same inputs, so the same bits.
        src = -1
        for b in range(a):
            if targets[b] == targets[a]:
                src = b
                break
        if src >= 0:
            xs[a] = xs[src]
            if follower_idm:
                vs[a] = vs[src]
            v_key[a] = v_key[src]
            continue
        for k in range(N_FALLBACKS):
            v4[k], x4[k], tg4[k] = ego_speed, ego_x, targets[a]
        for d in range(horizon):
            base = d * frames
            for k in range(N_FALLBACKS):
                if d > k:  # fallback k sends SLOWER from decision k + 1 on (its hold is over)
                    tg4[k] = ts[max(_speed_index(v4[k], ts) - 1, 0)]
                dv4[k] = v4[k] - tg4[k]
                # Frame 0 of the decision: covered = 0, so x = 0·dt + x. The reference writes it over
                # the previous decision's last frame: for the speed that is (v − target)·1 + target,
                # which can differ from v in the last bit — and ego_v[a, 0, frames] is read below.
                xs[a, base, k] = 0.0 * frame_dt + x4[k]
                vp4[k] = dv4[k] * powers[0] + tg4[k]
                if follower_idm:
                    vs[a, base, k] = vp4[k]
            if d == 1:
                v_key[a] = vp4[0]
            for j in range(1, frames + 1):
                p = powers[j]
                for k in range(N_FALLBACKS):  # the 4 fallbacks side by side: independent chains
                    # np.cumsum: out[0] = in[0], then out[j] = out[j − 1] + in[j] (sequential).
                    cov4[k] = vp4[k] if j == 1 else cov4[k] + vp4[k]
                    vp4[k] = dv4[k] * p + tg4[k]
                    xs[a, base + j, k] = cov4[k] * frame_dt + x4[k]
                    if follower_idm:
                        vs[a, base + j, k] = vp4[k]
            if d == 0:
                v_key[a] = vp4[0]  # kept when the horizon is a single decision
            for k in range(N_FALLBACKS):
                x4[k] = xs[a, base + frames, k]
                v4[k] = vp4[k]
        for k in range(N_FALLBACKS):
            xs[a, total, k] += _nmax(v4[k] - 0.0, 0.0) / ego_kp  # the exponential tail beyond the horizon

    # --- nearby vehicles and their worst-case motion -------------------------------------------
    n = x.shape[0]
    near = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if abs(x[i] - ego_x) < relevance and np.isfinite(x[i]):
            near[m] = i
            m += 1
    other_x = np.empty((m, n_t))  # leaders brake, followers surge (only the one used is computed)
    is_ahead = np.empty(m, dtype=np.bool_)
    half = np.empty(m)
    lanes_near = np.empty(m, dtype=np.int64)
    t_last = t[n_t - 1]
    t_r = follower_reaction if not (t_last < follower_reaction) else t_last  # Python's min()
    for r in range(m):
        i = near[r]
        half[r] = 0.5 * (length[i] + ego_length)
        lanes_near[r] = _lane_index(y[i], lane_width, lanes_count)
        is_ahead[r] = x[i] - ego_x >= 0
        if is_ahead[r]:  # braking_positions; a crashed vehicle is a wall where it stands
            v_signed = 0.0 if crashed[i] else vx[i]
            # model.evaluate's turning_leaders: a moving leader brakes along its path (its speed), less
            # what a lane change can cost along the road (turning_allowance > 0 when the option is on).
            turning = turning_allowance > 0.0 and v_signed > 0.0
            if turning:
                v_signed = math.sqrt(vx[i] * vx[i] + vy[i] * vy[i])
            v0 = _nmax(v_signed, 0.0)
            b = _nmax(1e9 if crashed[i] else brake_max[i], 1e-6)
            stop = v0 / b
            hb = 0.5 * b
            back = reversing_leaders and v_signed < 0.0  # a leader rolling backwards keeps its speed
            # model.evaluate's turning_in_nominal (nominal's leader bound): the looser of braking along the road
            # and along its path less the allowance (nominal_allowance > 0 when the option is on).
            looser = nominal_allowance > 0.0 and v_signed > 0.0
            v_path = math.sqrt(vx[i] * vx[i] + vy[i] * vy[i]) if looser else 0.0
            stop_path = v_path / b
            for j in range(n_t):
                tt = _nmin(t[j], stop)
                other_x[r, j] = x[i] + v0 * tt - hb * (tt * tt)
                if back:
                    other_x[r, j] = other_x[r, j] + v_signed * t[j]
                if turning:
                    other_x[r, j] = other_x[r, j] - turning_allowance
                if looser:
                    tt = _nmin(t[j], stop_path)
                    other_x[r, j] = _nmax(other_x[r, j], (x[i] + v_path * tt - hb * (tt * tt)) - nominal_allowance)
        else:  # follower_positions
            _follower_row(other_x[r], x[i], vx[i], accel_max[i], brake_max[i], t_r, t)
    # level_cut_ins: a car turning in behind the ego follows it, wherever it is now (ahead rows too).
    level_rows = robust and level_cut_ins
    foll_x = np.empty((m if level_rows else 0, n_t))
    for r in range(foll_x.shape[0]):
        if is_ahead[r]:
            i = near[r]
            _follower_row(foll_x[r], x[i], vx[i], accel_max[i], brake_max[i], t_r, t)
        else:
            foll_x[r] = other_x[r]
    # model.idm_followers: the IDM car right behind the ego in its lane, nothing between them in IDM's band.
    by_idm = np.zeros(m, dtype=np.bool_)
    if follower_idm:
        centre = ego_lane * lane_width
        band = 0.5 * lane_width + IDM_LANE_MARGIN
        for r in range(m):
            i = near[r]
            if not (
                x[i] < ego_x and not crashed[i] and can_change_lane[i]
                and (math.isnan(lin_k0[i]) or (follower_set_point and np.isfinite(target_speed[i])))
                and abs(heading[i]) <= lateral_threshold and abs(vy[i]) <= 0.3 and lanes_near[r] == ego_lane
            ):  # fmt: skip
                continue
            clear = True
            for j in range(n):
                if j != i and abs(y[j] - centre) <= band and x[j] >= x[i] and x[j] <= ego_x:
                    clear = False
                    break
            by_idm[r] = clear
    xf4 = np.empty(N_FALLBACKS)  # an IDM follower's position and speed per fallback
    vf4 = np.empty(N_FALLBACKS)

    # --- _occupancy: (row, lane, nominal); every entry starts at t = 0 -------------------------
    occ_row = np.empty(4 * m, dtype=np.int64)
    occ_lane = np.empty(4 * m, dtype=np.int64)
    occ_nominal = np.empty(4 * m, dtype=np.bool_)
    n_occ = 0
    projected = np.full(m, -10, dtype=np.int64)  # the lane a sideways-moving vehicle moves to (-10: none)
    for r in range(m):
        i = near[r]
        own = lanes_near[r]
        occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, own, True
        n_occ += 1
        nxt = -10
        if abs(heading[i]) > lateral_threshold or abs(vy[i]) > 0.3:
            direction = 1 if vy[i] > 0 else -1
            nxt = own + direction
            if 0 <= nxt < lanes_count:
                projected[r] = nxt
            # model.finishing_change: moving forward toward its own lane's centre, short of it
            finishing = finishing_changes and vx[i] >= 0.0 and (own * lane_width - y[i]) * direction > 0.0
            if finishing:
                nxt = -10  # a cut-in candidate from its own lane instead (MOBIL-filtered)
            elif robust and 0 <= nxt < lanes_count:
                occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, nxt, False
                n_occ += 1
        if robust and reversing_noses and vx[i] < 0.0 and abs(heading[i]) > lateral_threshold:
            nose = own + (1 if heading[i] > 0 else -1)  # model._occupancy: the lane its nose points to
            if nose != nxt and 0 <= nose < lanes_count:
                occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, nose, False
                n_occ += 1
        if robust and body_extent:  # model._occupancy: every lane the rotated body overlaps
            reach = abs(0.5 * length[i] * math.sin(heading[i])) + abs(0.5 * body_width * math.cos(heading[i]))
            for side in (own - 1, own + 1):
                if side == nxt or not (0 <= side < lanes_count):
                    continue
                centre, half_lane = side * lane_width, 0.5 * lane_width
                if y[i] + reach > centre - half_lane and y[i] - reach < centre + half_lane:
                    occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, side, False
                    n_occ += 1

    # Windows are contiguous ranges of the increasing frame times: [first t >= start, last t <= until]
    # (NaN bounds give empty ranges, as the reference's comparisons do).
    lo_now = 0
    while lo_now < n_t and not (t[lo_now] >= 0.0):
        lo_now += 1
    lo_cut = 0
    while lo_cut < n_t and not (t[lo_cut] >= cut_in_time):
        lo_cut += 1

    inf = math.inf
    joint_gap = np.full((N_ACTIONS, N_FALLBACKS), inf)
    ahead_gap = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_joint = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_ahead = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_ok = np.ones(N_ACTIONS, dtype=np.bool_)
    worst = np.empty(N_FALLBACKS)
    # _cut_in_candidates, memoised on its key as the reference does (IDLE and the lane changes share it).
    keys = np.empty((N_ACTIONS, 3))
    n_keys = 0
    permitted = np.zeros((N_ACTIONS, m), dtype=np.bool_)
    permit_lo = np.zeros((N_ACTIONS, m), dtype=np.int64)  # cut_in_when_permitted: a cut-in's first frame
    permit_first = np.full((N_ACTIONS, m), inf)  # the same as a time [s] (model.permit_times)
    pass_x = np.empty(n_t)  # passing_cut_ins: one car's leader path (model.passing_positions)
    unfiltered = np.zeros((N_ACTIONS, m), dtype=np.bool_)
    level = np.zeros((N_ACTIONS, m), dtype=np.bool_)  # level with or behind the ego (level_cut_ins)
    level_any = np.zeros((N_ACTIONS, m), dtype=np.bool_)  # the same, no incentive filter (level_entering)
    ego_lanes = np.empty(lanes_count + 1, dtype=np.int64)
    ego_until = np.empty(lanes_count + 1)  # [s] until when the ego is in the lane (inf: for good)
    ego_hi = np.empty(lanes_count + 1, dtype=np.int64)  # the last frame of that window (t <= until)
    ego_last = np.full((N_ACTIONS, lanes_count), -1, dtype=np.int64)  # per action: the last frame in each lane
    last_frame = np.empty(lanes_count, dtype=np.int64)
    ego_seen = np.zeros(lanes_count, dtype=np.bool_)  # leaving_lanes_seen: lanes MOBIL still sees the ego in
    hi_leave = n_t - 1
    while hi_leave >= 0 and not (t[hi_leave] <= ego_leave_time):
        hi_leave -= 1
    hi_inf = n_t - 1
    target_clip = 0.0
    for a in range(N_ACTIONS):
        if not available[a]:
            continue
        # _action_lanes: the sorted set {ego_lane, ego_target_lane} (with crossed_lanes every lane between
        # them), then a lane change's new lane (model.final_lane); with lateral_schedule, model.ego_lane_windows.
        lane_change = (a == LANE_LEFT) | (a == LANE_RIGHT)
        final = ego_target_lane
        if lane_change:
            final = min(max(ego_target_lane + (-1 if a == LANE_LEFT else 1), 0), lanes_count - 1)
        lo_l, hi_l = min(ego_lane, ego_target_lane), max(ego_lane, ego_target_lane)
        n_el = 0
        if lateral_schedule:
            n_el = _ego_lane_windows(
                ego_y, ego_heading, ego_length, final, lanes_count, lane_width, frame_dt, n_t - 1,
                ego_lateral_speed, ego_width, body_width, kp_lateral, kp_heading, max_steering, last_frame,
                ego_lanes, ego_until, ego_seen,
            )  # fmt: skip
            for e in range(n_el):  # the times are the schedule's: find each window's last frame
                hi_e = n_t - 1
                while hi_e >= 0 and not (t[hi_e] <= ego_until[e]):
                    hi_e -= 1
                ego_hi[e] = hi_e
        elif not lane_change:
            for lane in range(lo_l, hi_l + 1):
                if lane == lo_l or lane == hi_l or crossed_lanes:  # noqa: SIM109 (numba)
                    ego_lanes[n_el], ego_hi[n_el] = lane, hi_inf
                    n_el += 1
        else:
            lo_x, hi_x = min(ego_lane, final), max(ego_lane, final)  # crossed: strictly between
            for lane in range(min(lo_l, lo_x), max(hi_l, hi_x) + 1):
                if lane == final:
                    continue
                crossed = crossed_lanes and lo_x < lane < hi_x
                if crossed or lane == lo_l or lane == hi_l:  # noqa: SIM109 (numba) still overlapped until it has left
                    ego_lanes[n_el], ego_hi[n_el] = lane, hi_inf if crossed else hi_leave
                    n_el += 1
            ego_lanes[n_el], ego_hi[n_el] = final, hi_inf
            n_el += 1
        for e in range(n_el):  # forecast_fallback: model.ego_last_frames
            ego_last[a, ego_lanes[e]] = max(ego_last[a, ego_lanes[e]], ego_hi[e])

        slot = -1
        if robust:
            kx, kv, kt = xs[a, frames, 0], v_key[a], targets[a]
            for s in range(n_keys):
                if keys[s, 0] == kx and keys[s, 1] == kv and keys[s, 2] == kt:
                    slot = s
                    break
            if slot < 0:
                slot = n_keys
                keys[slot, 0], keys[slot, 1], keys[slot, 2] = kx, kv, kt
                n_keys += 1
                target_clip = _nmin(_nmax(kt, 0.0), speed_limit)  # np.clip(ego_target, 0, speed_limit)
                for r in range(m):
                    i = near[r]
                    can = can_change_lane[i] and abs(vx[i]) >= 1.0
                    d_now = x[i] - ego_x
                    d_end = x[i] + vx[i] * decision_period - kx
                    ahead_c = d_now > 0 or d_end > 0
                    unfiltered[slot, r] = can and ahead_c
                    level_any[slot, r] = can and (d_now <= 0 or d_end <= 0)
                    if level_rows and level_incentive and not np.isfinite(lin_k0[i]):
                        # model.turn_in_incentive: MOBIL's gain behind the ego, now or at the end.
                        dw, tw, v = idm_distance_wanted[i], idm_time_wanted[i], vx[i]
                        acc, dec = idm_comfort_acc[i], idm_comfort_dec[i]
                        lead_now = lead_end = 0.0  # the largest (d*/d)² over the vehicles ahead in its lane
                        found = False
                        for k in range(m):
                            lx = x[near[k]]
                            if lanes_near[k] == lanes_near[r] and lx > x[i]:
                                lv = vx[near[k]]
                                q = _gap_ratio(dw, tw, acc, dec, v, lv, lx - x[i])
                                gap_end = (lx + lv * decision_period) - (x[i] + v * decision_period)
                                qe = _gap_ratio(dw, tw, acc, dec, v, lv, gap_end)
                                if found:
                                    lead_now, lead_end = _nmax(lead_now, q * q), _nmax(lead_end, qe * qe)
                                else:
                                    lead_now, lead_end, found = q * q, qe * qe, True
                        q_en = _gap_ratio(dw, tw, acc, dec, v, ego_speed, -d_now)
                        q_ee = _gap_ratio(dw, tw, acc, dec, v, kv, -d_end)
                        gain_now = acc * lead_now - acc * (q_en * q_en)
                        gain_end = acc * lead_end - acc * (q_ee * q_ee)
                        level[slot, r] = can and (
                            (d_now <= 0 and gain_now >= min_acc_gain) or (d_end <= 0 and gain_end >= min_acc_gain)
                        )
                    elif level_rows and level_incentive and linear_incentive:
                        # model.linear_turn_in_incentive: the linear model's gain behind the ego.
                        k1, k2, v = lin_k1[i], lin_k2[i], vx[i]
                        d_safe = idm_distance_wanted[i] + _nmax(v, 0.0) * idm_time_wanted[i]
                        lead_now = lead_end = 0.0  # the most negative term over the vehicles ahead in its lane
                        found = False
                        for k in range(m):
                            lx = x[near[k]]
                            if lanes_near[k] == lanes_near[r] and lx > x[i]:
                                lv = vx[near[k]]
                                closing = k1 * _nmin(lv - v, 0.0)
                                gap_end = (lx + lv * decision_period) - (x[i] + v * decision_period)
                                an = closing + k2 * _nmin((lx - x[i]) - d_safe, 0.0)
                                ae = closing + k2 * _nmin(gap_end - d_safe, 0.0)
                                if found:
                                    lead_now, lead_end = _nmin(lead_now, an), _nmin(lead_end, ae)
                                else:
                                    lead_now, lead_end, found = an, ae, True
                        ego_now = k1 * _nmin(ego_speed - v, 0.0) + k2 * _nmin(-d_now - d_safe, 0.0)
                        ego_end = k1 * _nmin(kv - v, 0.0) + k2 * _nmin(-d_end - d_safe, 0.0)
                        gain_now = ego_now - lead_now
                        gain_end = ego_end - lead_end
                        level[slot, r] = can and (
                            (d_now <= 0 and gain_now >= min_acc_gain) or (d_end <= 0 and gain_end >= min_acc_gain)
                        )
                        if linear_incentive_braking and can and not level[slot, r]:
                            # model.linear_turn_in_incentive_braking: at every frame of the decision, the
                            # vehicles ahead of it in its lane braking at their maximum, itself at constant speed.
                            for f in range(frames + 1):
                                tau = t[f]
                                own_x = x[i] + v * tau
                                d = own_x - xs[a, f, 0]
                                if not d <= 0:
                                    continue
                                ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
                                ego_term = k1 * _nmin(ego_vf - v, 0.0) + k2 * _nmin(-d - d_safe, 0.0)
                                lead_term = 0.0
                                found = False
                                for k in range(m):
                                    ii = near[k]
                                    if lanes_near[k] == lanes_near[r] and x[ii] > x[i]:
                                        lx, lv = _braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                                        term = k1 * _nmin(lv - v, 0.0) + k2 * _nmin((lx - own_x) - d_safe, 0.0)
                                        lead_term = _nmin(lead_term, term) if found else term
                                        found = True
                                if ego_term - lead_term >= min_acc_gain:
                                    level[slot, r] = True
                                    break
                    else:
                        level[slot, r] = level_any[slot, r]
                    if reversing_cut_ins and can and vx[i] < 0.0:  # model._cut_in_candidates: any lane change
                        level[slot, r] = level[slot, r] or level_any[slot, r]
                    if can and ahead_c:
                        acc, delta, dec = idm_comfort_acc[i], idm_delta[i], idm_comfort_dec[i]
                        dw, tw = idm_distance_wanted[i], idm_time_wanted[i]
                        limit = -max_braking_imposed[i]
                        if np.isfinite(lin_k0[i]) and not linear_mobil:  # the earlier rule: any cut-in
                            ok = True
                        elif np.isfinite(lin_k0[i]):  # model.linear_acceleration_behind, now then at the end
                            k0, k1, k2, own = lin_k0[i], lin_k1[i], lin_k2[i], math.hypot(vx[i], vy[i])
                            ok = _linear_behind(k0, k1, k2, dw, tw, own, d_now, ego_speed, kt) >= limit
                            if not ok:
                                ok = _linear_behind(k0, k1, k2, dw, tw, own, d_end, kv, kt) >= limit
                        else:
                            ok = _idm_behind(acc, delta, dec, dw, tw, vx[i], d_now, ego_speed, target_clip) >= limit
                            if not ok:  # the end-of-period check only matters when the one of now fails
                                ok = _idm_behind(acc, delta, dec, dw, tw, vx[i], d_end, kv, target_clip) >= limit
                        permitted[slot, r] = ok or (reversing_cut_ins and vx[i] < 0.0)
                        if cut_in_when_permitted:
                            # model.permit_times: the first frame MOBIL allows it, the car at its fastest.
                            t_first = inf
                            if np.isfinite(lin_k0[i]) and not linear_mobil:
                                t_first = 0.0
                            else:
                                accel = _nmax(accel_max[i], 0.0)
                                for f in range(frames + 1):
                                    tau = t[f]
                                    d = (x[i] + vx[i] * tau + 0.5 * accel * tau * tau) - xs[a, f, 0]
                                    ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
                                    if np.isfinite(lin_k0[i]):
                                        own = math.hypot(vx[i], vy[i]) + accel * tau
                                        af = _linear_behind(lin_k0[i], lin_k1[i], lin_k2[i], dw, tw, own, d, ego_vf, kt)
                                    elif permit_any_speed:  # model.permit_times: IDM at its loosest speed
                                        v_lo = _nmax(vx[i] - _nmax(brake_max[i], 1e-6) * tau, 0.0)
                                        q = _least_desired_gap(acc, dec, dw, tw, ego_vf, v_lo, vx[i] + accel * tau)
                                        af = _idm_behind_gap(acc, delta, ego_vf, target_clip, d, q) if d > 0.0 else -inf
                                    else:
                                        af = _idm_behind(
                                            acc, delta, dec, dw, tw, vx[i] + accel * tau, d, ego_vf, target_clip
                                        )
                                    if af >= limit:
                                        t_first = tau
                                        break
                            if reversing_cut_ins and vx[i] < 0.0:
                                t_first = 0.0
                            permitted[slot, r] = t_first < inf
                            permit_first[slot, r] = t_first
                            start = cut_in_time + t_first
                            lo_p = 0
                            while lo_p < n_t and not (t[lo_p] >= start):
                                lo_p += 1
                            permit_lo[slot, r] = lo_p
                    else:
                        permitted[slot, r] = False

        # Every conflict: (row, window, nominal). The order of the reference's pairs only matters to
        # its min / max reductions, which are order-free here (NaN propagates either way).
        n_cut = n_occ + (n_el * m if robust else 0)
        n_conf = n_cut + (n_el * m if level_rows else 0)
        for c in range(n_conf):
            follows = False
            passing = False
            if c < n_occ:
                r, lane_c, nominal = occ_row[c], occ_lane[c], occ_nominal[c]
                lo = lo_now
            elif c >= n_cut:  # level_cut_ins: a car level with or behind the ego turning in behind it
                e_idx, r = divmod(c - n_cut, m)
                lane_c = ego_lanes[e_idx]
                occupied = (lane_c == ego_lane) | (lane_c == ego_target_lane)
                occupied = occupied or (lateral_schedule and leaving_lanes_seen and ego_seen[lane_c])
                # model._cut_in_candidates: MOBIL's incentive is judged with the ego in the lane, which a
                # lane it is only entering does not hold (level_entering: any level car there).
                turning = level[slot, r] if occupied or not level_entering else level_any[slot, r]
                if not (turning and abs(lanes_near[r] - lane_c) == 1):
                    continue
                nominal = False
                follows = True
                lo = lo_cut
                if level_when_incentive and level_incentive and occupied:  # model.incentive_times(_any_speed)
                    if incentive_any_speed:
                        t_inc = _incentive_first_any_speed(
                            near[r], r, m, near, lanes_near, x, vx, vy, crashed, brake_max, accel_max, lin_k0,
                            lin_k1, lin_k2, idm_distance_wanted, idm_time_wanted, idm_comfort_acc, idm_comfort_dec,
                            linear_incentive, xs[a], ego_speed, v_key[a], targets[a], powers, frames, t, min_acc_gain,
                        )  # fmt: skip
                    else:
                        t_inc = _incentive_first(
                            near[r], r, m, near, lanes_near, x, vx, crashed, brake_max, lin_k0, lin_k1, lin_k2,
                            idm_distance_wanted, idm_time_wanted, idm_comfort_acc, idm_comfort_dec, linear_incentive,
                            linear_incentive_braking, xs[a], ego_speed, v_key[a], targets[a], powers, frames, t,
                            min_acc_gain,
                        )  # fmt: skip
                    if t_inc < inf:
                        start = cut_in_time + t_inc
                        lo = 0
                        while lo < n_t and not (t[lo] >= start):
                            lo += 1
            else:
                e_idx, r = divmod(c - n_occ, m)
                lane_c = ego_lanes[e_idx]
                occupied = (lane_c == ego_lane) | (lane_c == ego_target_lane)
                occupied = occupied or (lateral_schedule and leaving_lanes_seen and ego_seen[lane_c])
                cand = permitted[slot, r] if occupied else unfiltered[slot, r]
                adjacent = abs(lanes_near[r] - lane_c) == 1
                if projected_cut_ins and not adjacent:
                    adjacent = abs(projected[r] - lane_c) == 1
                if not (cand and adjacent):
                    continue
                nominal = False
                lo = permit_lo[slot, r] if cut_in_when_permitted and occupied else lo_cut
                i = near[r]
                passing = (
                    passing_cut_ins and cut_in_when_permitted and occupied and not is_ahead[r] and vx[i] >= 0.0
                    and (linear_mobil or not np.isfinite(lin_k0[i]))
                )  # fmt: skip
                if passing:  # model.passing_positions: behind now, it cuts in only ahead of the ego
                    _passing_path(
                        pass_x, i, x, vx, vy, brake_max, accel_max, max_braking_imposed, idm_distance_wanted,
                        idm_time_wanted, idm_comfort_acc, idm_comfort_dec, idm_delta, lin_k0, lin_k1, lin_k2,
                        speed_limit, xs[a], ego_speed, powers, frames, v_key[a], targets[a], t, cut_in_time,
                        permit_first[slot, r], turning_allowance,
                    )  # fmt: skip
            for e in range(n_el):
                if ego_lanes[e] != lane_c:
                    continue
                hi = ego_hi[e]
                ahead_r = (is_ahead[r] and not follows) or passing
                sign = 1.0 if ahead_r else -1.0
                motion = foll_x if follows else other_x
                h = half[r]
                if passing:
                    w0 = w1 = w2 = w3 = inf
                    for j in range(lo, hi + 1):
                        o = pass_x[j]
                        w0 = _nmin(w0, (o - xs[a, j, 0]) - h)
                        w1 = _nmin(w1, (o - xs[a, j, 1]) - h)
                        w2 = _nmin(w2, (o - xs[a, j, 2]) - h)
                        w3 = _nmin(w3, (o - xs[a, j, 3]) - h)
                    worst[0], worst[1], worst[2], worst[3] = w0, w1, w2, w3
                elif by_idm[r] and not follows and lane_c == ego_lane:
                    _idm_follower_window(
                        near[r], x, vx, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
                        accel_max, brake_max, idm_delta, lin_k0, lin_k1, lin_k2, target_speed, follower_set_point,
                        speed_limit, xs[a], vs[a], frame_dt, follower_reaction, h, lo, hi, xf4, vf4, worst,
                    )  # fmt: skip
                else:
                    # The where(window, gap, inf).min(axis=-1) of the reference: the window's running minimum,
                    # the 4 fallbacks side by side (independent chains; min is exact in any order).
                    w0 = w1 = w2 = w3 = inf
                    for j in range(lo, hi + 1):
                        o = motion[r, j]
                        w0 = _nmin(w0, sign * (o - xs[a, j, 0]) - h)
                        w1 = _nmin(w1, sign * (o - xs[a, j, 1]) - h)
                        w2 = _nmin(w2, sign * (o - xs[a, j, 2]) - h)
                        w3 = _nmin(w3, sign * (o - xs[a, j, 3]) - h)
                    worst[0], worst[1], worst[2], worst[3] = w0, w1, w2, w3
                best_f = -inf
                for f in range(N_FALLBACKS):
                    joint_gap[a, f] = _nmin(joint_gap[a, f], worst[f])
                    if ahead_r:
                        ahead_gap[a, f] = _nmin(ahead_gap[a, f], worst[f])
                    if nominal:
                        nominal_joint[a, f] = _nmin(nominal_joint[a, f], worst[f])
                        if ahead_r:
                            nominal_ahead[a, f] = _nmin(nominal_ahead[a, f], worst[f])
                    best_f = worst[f] if f == 0 else _nmax(best_f, worst[f])
                if nominal and not (best_f >= margin):
                    nominal_ok[a] = False

    # --- the verdict ----------------------------------------------------------------------------
    best_gap = np.empty(N_ACTIONS)
    safe = np.empty(N_ACTIONS, dtype=np.bool_)
    for a in range(N_ACTIONS):
        g = joint_gap[a, 0]
        for f in range(1, N_FALLBACKS):
            g = _nmax(g, joint_gap[a, f])
        best_gap[a] = g if available[a] else -inf
        safe[a] = ((best_gap[a] >= margin) if robust else nominal_ok[a]) and available[a]
    if not np.isfinite(ego_leave_time):
        safe[LANE_LEFT] = safe[LANE_RIGHT] = False
        nominal_ok[LANE_LEFT] = nominal_ok[LANE_RIGHT] = False
    if safe.any():
        return safe.copy(), safe, available, best_gap, False
    pool = nominal_ok & available
    if robust and robust_fallback:  # model.evaluate: every available action, by its robust gaps
        pool = available
        ahead_of, gaps_of = ahead_gap, joint_gap
    elif robust and pool.any():
        ahead_of, gaps_of = ahead_gap, joint_gap
    else:
        pool = available
        ahead_of, gaps_of = nominal_ahead, nominal_joint
    if least_bad_joint:  # model.evaluate: the gap to everybody first
        ahead_of, gaps_of = gaps_of, ahead_of
    # model.forecast_ranking: the forecast's keys, ranked first (0 for every action: no forecast).
    forecast = np.zeros(N_ACTIONS)
    if forecast_fallback & FORECAST_ON:
        by_contact_time = (forecast_fallback & FORECAST_BY_CONTACT_TIME) != 0
        lane_changes = (forecast_fallback & FORECAST_LANE_CHANGES) != 0
        gaps, contact_time = forecast_gaps(
            xs.transpose((0, 2, 1)), ego_last, available, frame_dt, ego_x, ego_length, lanes_count, lane_width,
            speed_limit, x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta, idm_comfort_acc,
            idm_comfort_dec, idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2, target_speed,
            by_contact_time, lane_changes, can_change_lane, max_braking_imposed, ego_lane,
        )  # fmt: skip
        horizon_s = frame_dt * (xs.shape[1] - 1)
        forecast = forecast_keys(gaps, contact_time, margin, horizon_s, decision_period, by_contact_time)
    # least_bad_action: the largest (forecast, ahead gap, gap, −rank), compared as Python compares tuples.
    choice = IDLE
    found = False
    b0 = b1 = b2 = 0.0
    b3 = 0
    for rank in range(tie_break.shape[0]):
        a = tie_break[rank]
        if not pool[a]:
            continue
        g1, g2 = ahead_of[a, 0], gaps_of[a, 0]
        for f in range(1, N_FALLBACKS):
            g1, g2 = _nmax(g1, ahead_of[a, f]), _nmax(g2, gaps_of[a, f])
        k0, k1, k2, k3 = forecast[a], _nmin(g1, 1e6), _nmin(g2, 1e6), -rank
        better = True
        if found:
            better = k0 > b0 if k0 != b0 else (k1 > b1 if k1 != b1 else (k2 > b2 if k2 != b2 else k3 > b3))
        if better:
            found, b0, b1, b2, b3, choice = True, k0, k1, k2, k3, a
    mask = np.zeros(N_ACTIONS, dtype=np.bool_)
    mask[choice] = True
    return mask, safe, available, best_gap, True


@njit(cache=True, error_model="numpy")
def _evaluate(
    ego_x: float, ego_speed: float, ego_lane: int, ego_target_lane: int, ego_target_speed: float,
    ego_speed_index: int, ego_length: float, speed_limit: float, ego_y: float, ego_heading: float,
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, target_speed: np.ndarray,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray,
    decision_period: float, frame_dt: float, frames: int, horizon: int, ego_kp: float, lane_width: float,
    lanes_count: int, follower_reaction: float, ego_leave_time: float, ego_lateral_speed: float,
    cut_in_time: float, margin: float,
    relevance: float, lateral_threshold: float, robust: bool, projected_cut_ins: bool, body_extent: bool,
    body_width: float, linear_mobil: bool, reversing_leaders: bool, level_cut_ins: bool, level_incentive: bool,
    level_entering: bool, least_bad_joint: bool, robust_fallback: bool, straight_fallback: bool,
    linear_incentive: bool, linear_incentive_braking: bool, reversing_cut_ins: bool, crossed_lanes: bool,
    lateral_schedule: bool, reversing_noses: bool, follower_idm: bool, follower_set_point: bool,
    finishing_changes: bool, cut_in_when_permitted: bool, leaving_lanes_seen: bool,
    permit_any_speed: bool, passing_cut_ins: bool, level_when_incentive: bool, incentive_any_speed: bool,
    turning_in_nominal: bool, forecast_fallback: int,
    ego_width: float,
    kp_lateral: float,
    kp_heading: float, max_steering: float, turning_allowance: float,
    min_acc_gain: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """:func:`_evaluate_rule`, and with ``straight_fallback`` (``model.evaluate``) a state the turning
    allowance leaves without a safe action gets the mask of the rule without it. The allowance is robust only
    (``model.evaluate``: nominal keeps the straight leader bound)."""
    allowance = turning_allowance
    if not robust:
        allowance = 0.0
    # turning_in_nominal: nominal's leader bound, in nominal mode and in robust's straight fallback
    nominal_allowance = turning_allowance if turning_in_nominal else 0.0
    main_nominal_allowance = 0.0 if robust else nominal_allowance  # robust: turning_leaders' own bound
    # With the straight fallback below, a fallback state's mask is the straight rule's: the main rule's least-bad
    # choice is discarded, so its forecast (about 0.06 ms) is not run (model.evaluate returns first).
    straight = robust and straight_fallback and turning_allowance > 0.0
    main_forecast = 0 if straight else forecast_fallback
    out = _evaluate_rule(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, ego_length, speed_limit,
        ego_y, ego_heading,
        x, y, vx, vy, heading, length, crashed, brake_max, accel_max, can_change_lane, idm_delta,
        idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, max_braking_imposed,
        lin_k0, lin_k1, lin_k2, target_speed, ts, t, powers, tie_break, decision_period, frame_dt, frames, horizon,
        ego_kp,
        lane_width, lanes_count, follower_reaction, ego_leave_time, ego_lateral_speed, cut_in_time, margin, relevance,
        lateral_threshold, robust, projected_cut_ins, body_extent, body_width, linear_mobil, reversing_leaders,
        level_cut_ins, level_incentive, level_entering, least_bad_joint, robust_fallback, linear_incentive,
        linear_incentive_braking, reversing_cut_ins, crossed_lanes, lateral_schedule,
        reversing_noses, follower_idm, follower_set_point, finishing_changes,
        cut_in_when_permitted, leaving_lanes_seen, permit_any_speed, passing_cut_ins, level_when_incentive,
        incentive_any_speed,
        main_nominal_allowance, main_forecast,
        ego_width, kp_lateral,
        kp_heading, max_steering, allowance, min_acc_gain,
    )  # fmt: skip
    if not (out[4] and straight):
        return out
    straight_out = _evaluate_rule(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, ego_length, speed_limit,
        ego_y, ego_heading,
        x, y, vx, vy, heading, length, crashed, brake_max, accel_max, can_change_lane, idm_delta,
        idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, max_braking_imposed,
        lin_k0, lin_k1, lin_k2, target_speed, ts, t, powers, tie_break, decision_period, frame_dt, frames, horizon,
        ego_kp,
        lane_width, lanes_count, follower_reaction, ego_leave_time, ego_lateral_speed, cut_in_time, margin, relevance,
        lateral_threshold, robust, projected_cut_ins, body_extent, body_width, linear_mobil, reversing_leaders,
        level_cut_ins, level_incentive, level_entering, least_bad_joint, robust_fallback, linear_incentive,
        linear_incentive_braking, reversing_cut_ins, crossed_lanes, lateral_schedule,
        reversing_noses, follower_idm, follower_set_point, finishing_changes,
        cut_in_when_permitted, leaving_lanes_seen, permit_any_speed, passing_cut_ins, level_when_incentive,
        incentive_any_speed,
        nominal_allowance, forecast_fallback,
        ego_width, kp_lateral,
        kp_heading, max_steering, 0.0, min_acc_gain,
    )  # fmt: skip
    return straight_out[0].copy(), out[1], out[2], out[3], True


@njit(cache=True, error_model="numpy")
def _evaluate_snapshot(
    position: np.ndarray, speed: np.ndarray, heading: np.ndarray, length: np.ndarray, crashed: np.ndarray,
    brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray, idm_delta: np.ndarray,
    idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray,
    idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, target_speed: np.ndarray,
    ego: int, ego_lane: int, ego_target_lane: int, ego_target_speed: float, ego_speed_index: int,
    origin: np.ndarray, direction: np.ndarray, lateral: np.ndarray, lane_heading: float, speed_limit: float,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray,
    decision_period: float, frame_dt: float, frames: int, horizon: int, ego_kp: float, lane_width: float,
    lanes_count: int, follower_reaction: float, ego_leave_time: float, ego_lateral_speed: float,
    cut_in_time: float, margin: float,
    relevance: float, lateral_threshold: float, robust: bool, projected_cut_ins: bool, body_extent: bool,
    body_width: float, linear_mobil: bool, reversing_leaders: bool, level_cut_ins: bool, level_incentive: bool,
    level_entering: bool, least_bad_joint: bool, robust_fallback: bool, straight_fallback: bool,
    linear_incentive: bool, linear_incentive_braking: bool, reversing_cut_ins: bool, crossed_lanes: bool,
    lateral_schedule: bool, reversing_noses: bool, follower_idm: bool, follower_set_point: bool,
    finishing_changes: bool, cut_in_when_permitted: bool, leaving_lanes_seen: bool,
    permit_any_speed: bool, passing_cut_ins: bool, level_when_incentive: bool, incentive_any_speed: bool,
    turning_in_nominal: bool, forecast_fallback: int,
    ego_width: float,
    kp_lateral: float,
    kp_heading: float, max_steering: float, ego_speed_magnitude: bool,
    turning_allowance: float,
    min_acc_gain: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """``shield.road_state`` then :func:`_evaluate`, without building the state in Python.

    The projections on the lane frame are written as ``p·d = p₀d₀ + p₁d₁``: the reference's ``@``
    (BLAS) may round differently for an oblique frame, so the caller only comes here for the
    axis-aligned one, where every order gives the same bits.
    """
    n = speed.shape[0]
    e0 = position[ego, 0] - origin[0]
    e1 = position[ego, 1] - origin[1]
    ego_x = e0 * direction[0] + e1 * direction[1]
    # shield.road_state: the controller's speed, or (the earlier rule) its component along the road.
    ego_speed = speed[ego] if ego_speed_magnitude else speed[ego] * math.cos(heading[ego] - lane_heading)
    keep = np.empty(n, dtype=np.int64)
    xk = np.empty(n)
    m = 0
    for k in range(n):  # the other bodies (static objects included) within range, in order
        if k == ego:
            continue
        xv = (position[k, 0] - origin[0]) * direction[0] + (position[k, 1] - origin[1]) * direction[1]
        if abs(xv - ego_x) < relevance and np.isfinite(xv):
            keep[m] = k
            xk[m] = xv
            m += 1
    keep, x = keep[:m], xk[:m].copy()
    y = np.empty(m)
    vx = np.empty(m)
    vy = np.empty(m)
    rel_heading = np.empty(m)
    for r in range(m):
        k = keep[r]
        y[r] = (position[k, 0] - origin[0]) * lateral[0] + (position[k, 1] - origin[1]) * lateral[1]
        h = heading[k] - lane_heading
        c, s = np.cos(h), np.sin(h)
        vx[r] = speed[k] * c
        vy[r] = speed[k] * s
        rel_heading[r] = np.arctan2(s, c)
    ego_y = e0 * lateral[0] + e1 * lateral[1]  # road_state's ego_rel @ lateral (axis-aligned: exact)
    return _evaluate(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, length[ego], speed_limit,
        ego_y, heading[ego] - lane_heading, x, y, vx, vy, rel_heading, length[keep], crashed[keep], brake_max[keep],
        accel_max[keep],
        can_change_lane[keep], idm_delta[keep], idm_comfort_acc[keep], idm_comfort_dec[keep],
        idm_distance_wanted[keep], idm_time_wanted[keep], max_braking_imposed[keep],
        lin_k0[keep], lin_k1[keep], lin_k2[keep], target_speed[keep],
        ts, t, powers, tie_break, decision_period, frame_dt, frames, horizon, ego_kp, lane_width, lanes_count,
        follower_reaction, ego_leave_time, ego_lateral_speed, cut_in_time, margin, relevance, lateral_threshold, robust,
        projected_cut_ins, body_extent, body_width, linear_mobil, reversing_leaders, level_cut_ins, level_incentive,
        level_entering, least_bad_joint, robust_fallback, straight_fallback, linear_incentive,
        linear_incentive_braking, reversing_cut_ins, crossed_lanes, lateral_schedule,
        reversing_noses, follower_idm, follower_set_point, finishing_changes,
        cut_in_when_permitted, leaving_lanes_seen, permit_any_speed, passing_cut_ins, level_when_incentive,
        incentive_any_speed,
        turning_in_nominal, forecast_fallback,
        ego_width, kp_lateral,
        kp_heading, max_steering, turning_allowance, min_acc_gain,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Python entries.
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def _horizon_arrays(
    frame_dt: float, frames: int, horizon: int, ego_kp: float, target_speeds: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(target speeds [m/s], frame times [s], decay powers) computed by numpy exactly as the reference does."""
    ts = np.asarray(target_speeds, dtype=float)
    t = np.arange(horizon * frames + 1) * frame_dt  # Dynamics.times
    powers = (1.0 - ego_kp * frame_dt) ** np.arange(frames + 1)  # ego_trajectories' decay^k
    for a in (ts, t, powers):
        a.flags.writeable = False
    return ts, t, powers


def _check(mode: str, formula: str) -> None:
    if mode not in ("nominal", "robust"):
        raise ValueError(f"mode: got {mode!r}; allowed: 'nominal', 'robust'")
    if formula not in ("kinematic", "paper"):
        raise ValueError(f"formula: got {formula!r}; allowed: 'kinematic', 'paper'")


_ARGS: dict[tuple[int, float], tuple[Dynamics, tuple]] = {}
"""The kernel's dynamics arguments per (Dynamics object, leave time): the shield evaluates one Dynamics
for a whole episode with a handful of leave times, and building them costs as much as a small kernel."""


def _dynamics_args(dyn: Dynamics, ego_leave_time: float, ego_lateral_speed: float) -> tuple:
    key = (id(dyn), ego_leave_time, ego_lateral_speed)
    hit = _ARGS.get(key)
    if hit is not None and hit[0] is dyn:  # the entry holds dyn, so its id is not reused meanwhile
        return hit[1]
    ts, t, powers = _horizon_arrays(
        dyn.frame_dt, dyn.frames_per_decision, dyn.horizon_decisions, dyn.ego_kp, dyn.target_speeds
    )
    args = (
        ts, t, powers, _TIE_BREAK, dyn.decision_period, dyn.frame_dt, dyn.frames_per_decision,
        dyn.horizon_decisions, dyn.ego_kp, dyn.lane_width, dyn.lanes_count, dyn.follower_reaction,
        ego_leave_time, ego_lateral_speed, dyn.cut_in_time, dyn.margin, _RELEVANCE, _LATERAL,
    )  # fmt: skip
    if len(_ARGS) >= 256:
        _ARGS.clear()
    _ARGS[key] = (dyn, args)
    return args


snapshot_kernel = _evaluate_snapshot
"""The njit kernel behind :func:`evaluate_snapshot` (its arguments: the snapshot's arrays, the ego's
lane, target lane, set-point [m/s] and speed index, the lane frame, then :func:`kernel_constants`'s
fields around ``ego_leave_time`` and ``ego_lateral_speed``): for a caller that evaluates many scenes inside one
numba call."""


class KernelConstants(NamedTuple):
    """A :class:`Dynamics` as :data:`snapshot_kernel` takes it (everything but ``ego_leave_time`` and
    ``ego_lateral_speed``, the per-state two)."""

    ts: np.ndarray
    t: np.ndarray
    powers: np.ndarray
    tie_break: np.ndarray
    decision_period: float
    frame_dt: float
    frames: int
    horizon: int
    ego_kp: float
    lane_width: float
    lanes_count: int
    follower_reaction: float
    cut_in_time: float
    margin: float
    relevance: float
    lateral_threshold: float
    projected_cut_ins: bool
    body_extent: bool
    body_width: float
    linear_mobil: bool
    reversing_leaders: bool
    level_cut_ins: bool
    level_incentive: bool
    level_entering: bool
    least_bad_joint: bool
    robust_fallback: bool
    straight_fallback: bool
    linear_incentive: bool
    linear_incentive_braking: bool
    reversing_cut_ins: bool
    crossed_lanes: bool
    lateral_schedule: bool
    reversing_noses: bool
    follower_idm: bool
    follower_set_point: bool
    finishing_changes: bool
    cut_in_when_permitted: bool
    leaving_lanes_seen: bool
    permit_any_speed: bool
    passing_cut_ins: bool
    level_when_incentive: bool
    incentive_any_speed: bool
    turning_in_nominal: bool
    forecast_fallback: int  # forecast_level
    ego_width: float
    kp_lateral: float
    kp_heading: float
    max_steering: float
    ego_speed_magnitude: bool
    turning_allowance: float
    min_acc_gain: float


def forecast_level(dyn: Dynamics) -> int:
    """``dyn``'s forecast options as the kernels take them: 0 (worst-case keys only) or :data:`FORECAST_ON`
    with :data:`FORECAST_BY_CONTACT_TIME` and :data:`FORECAST_LANE_CHANGES` as set."""
    if not dyn.forecast_fallback:
        return 0
    contact = FORECAST_BY_CONTACT_TIME if dyn.forecast_contact_time else 0
    return FORECAST_ON | contact | (FORECAST_LANE_CHANGES if dyn.forecast_lane_changes else 0)


def kernel_constants(dyn: Dynamics) -> KernelConstants:
    """``dyn``'s constants in :data:`snapshot_kernel`'s form (the arrays computed as the reference does)."""
    args = _dynamics_args(dyn, dyn.ego_leave_time, dyn.ego_lateral_speed)
    return KernelConstants(
        *args[:12],
        *args[14:],
        dyn.projected_cut_ins,
        dyn.body_extent,
        dyn.body_width,
        dyn.linear_mobil,
        dyn.reversing_leaders,
        dyn.level_cut_ins,
        dyn.level_incentive,
        dyn.level_entering,
        dyn.least_bad_joint,
        dyn.robust_fallback,
        dyn.straight_fallback,
        dyn.linear_incentive,
        dyn.linear_incentive_braking,
        dyn.reversing_cut_ins,
        dyn.crossed_lanes,
        dyn.lateral_schedule,
        dyn.reversing_noses,
        dyn.follower_idm,
        dyn.follower_set_point,
        dyn.finishing_changes,
        dyn.cut_in_when_permitted,
        dyn.leaving_lanes_seen,
        dyn.permit_any_speed,
        dyn.passing_cut_ins,
        dyn.level_when_incentive,
        dyn.incentive_any_speed,
        dyn.turning_in_nominal,
        forecast_level(dyn),
        dyn.ego_width,
        dyn.kp_lateral,
        dyn.kp_heading,
        dyn.max_steering,
        dyn.ego_speed_magnitude,
        model.turning_allowance(dyn),
        _MIN_ACC_GAIN,
    )


def _result(out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]) -> SafetyResult:
    mask, safe, available, min_gap, fallback = out
    return SafetyResult(mask, safe, available, bool(fallback), min_gap)


def evaluate_compiled(
    state: RoadState, dyn: Dynamics, mode: Mode = "robust", formula: Formula = "kinematic"
) -> SafetyResult:
    """The safety mask of ``state`` — :func:`safelane.safety.model.evaluate`, compiled.

    Same arguments (positions in metres, speeds in m/s, times in seconds), same errors, same result:
    mask, safe, available and fallback identical, ``min_gap`` [m] bit for bit. ``formula="paper"`` in
    nominal mode is computed by the numpy reference (eq. 12 is a baseline off the hot path; robust
    mode ignores the formula, as the reference does).
    """
    _check(mode, formula)
    if mode == "nominal" and formula == "paper":
        return model.evaluate(state, dyn, mode, formula)
    s = state
    out = _evaluate(
        s.ego_x, s.ego_speed, s.ego_lane, s.ego_target_lane, s.ego_target_speed, s.ego_speed_index,
        s.ego_length, s.speed_limit, s.ego_y, s.ego_heading, s.x, s.y, s.vx, s.vy, s.heading, s.length, s.crashed,
        s.brake_max,
        s.accel_max, s.can_change_lane, s.idm_delta, s.idm_comfort_acc, s.idm_comfort_dec,
        s.idm_distance_wanted, s.idm_time_wanted, s.max_braking_imposed, s.linear_speed_gain,
        s.linear_speed_difference_gain, s.linear_distance_gain, model.set_points(s),
        *_dynamics_args(dyn, dyn.ego_leave_time, dyn.ego_lateral_speed), mode == "robust", dyn.projected_cut_ins,
        dyn.body_extent,
        dyn.body_width, dyn.linear_mobil, dyn.reversing_leaders, dyn.level_cut_ins, dyn.level_incentive,
        dyn.level_entering, dyn.least_bad_joint, dyn.robust_fallback, dyn.straight_fallback, dyn.linear_incentive,
        dyn.linear_incentive_braking, dyn.reversing_cut_ins, dyn.crossed_lanes, dyn.lateral_schedule,
        dyn.reversing_noses, dyn.follower_idm, dyn.follower_set_point, dyn.finishing_changes,
        dyn.cut_in_when_permitted, dyn.leaving_lanes_seen, dyn.permit_any_speed, dyn.passing_cut_ins,
        dyn.level_when_incentive, dyn.incentive_any_speed, dyn.turning_in_nominal, forecast_level(dyn), dyn.ego_width,
        dyn.kp_lateral, dyn.kp_heading,
        dyn.max_steering, model.turning_allowance(dyn), _MIN_ACC_GAIN,
    )  # fmt: skip
    return _result(out)


def axis_aligned(snap: RoadSnapshot) -> bool:
    """Whether the snapshot's lane frame is x along the road, y across (every highway-env straight road):
    there :func:`evaluate_snapshot` reproduces ``road_state``'s projections bit for bit."""
    d, lat = snap.lane_direction, snap.lane_lateral
    return bool(d[0] == 1.0 and d[1] == 0.0 and lat[0] == 0.0 and lat[1] == 1.0)


def evaluate_snapshot(
    snap: RoadSnapshot,
    dyn: Dynamics,
    mode: Mode = "robust",
    *,
    lane_heading: float,
    ego_leave_time: float,
    ego_lateral_speed: float = math.nan,
) -> SafetyResult:
    """``evaluate_compiled(road_state(snap, dyn.ego_speed_magnitude), replace(dyn, ego_leave_time=...), mode)``
    in one kernel.

    The shield's fast path (formula ``kinematic``): the :class:`RoadState` is built inside the kernel,
    bit for bit as :func:`safelane.safety.shield.road_state` builds it, for an :func:`axis_aligned`
    snapshot (the caller checks). ``lane_heading`` [rad]: ``atan2`` of the lane direction, computed
    once per episode; ``ego_leave_time`` [s] and ``ego_lateral_speed`` [m/s] replace ``dyn``'s.
    """
    _check(mode, "kinematic")
    e = snap.ego
    out = _evaluate_snapshot(
        snap.position, snap.speed, snap.heading, snap.length, snap.crashed, snap.brake_max, snap.accel_max,
        snap.can_change_lane, snap.idm_delta, snap.idm_comfort_acc, snap.idm_comfort_dec,
        snap.idm_distance_wanted, snap.idm_time_wanted, snap.max_braking_imposed, snap.linear_speed_gain,
        snap.linear_speed_difference_gain, snap.linear_distance_gain, snap.target_speed,
        e, int(snap.lane[e]), int(snap.target_lane[e]), snap.ego_target_speed, snap.ego_speed_index,
        snap.lane_origin, snap.lane_direction, snap.lane_lateral, lane_heading, snap.speed_limit,
        *_dynamics_args(dyn, ego_leave_time, ego_lateral_speed), mode == "robust", dyn.projected_cut_ins,
        dyn.body_extent,
        dyn.body_width, dyn.linear_mobil, dyn.reversing_leaders, dyn.level_cut_ins, dyn.level_incentive,
        dyn.level_entering, dyn.least_bad_joint, dyn.robust_fallback, dyn.straight_fallback, dyn.linear_incentive,
        dyn.linear_incentive_braking, dyn.reversing_cut_ins, dyn.crossed_lanes, dyn.lateral_schedule,
        dyn.reversing_noses, dyn.follower_idm, dyn.follower_set_point, dyn.finishing_changes,
        dyn.cut_in_when_permitted, dyn.leaving_lanes_seen, dyn.permit_any_speed, dyn.passing_cut_ins,
        dyn.level_when_incentive, dyn.incentive_any_speed, dyn.turning_in_nominal, forecast_level(dyn), dyn.ego_width,
        dyn.kp_lateral, dyn.kp_heading,
        dyn.max_steering, dyn.ego_speed_magnitude,
        model.turning_allowance(dyn),
        _MIN_ACC_GAIN,
    )  # fmt: skip
    return _result(out)
