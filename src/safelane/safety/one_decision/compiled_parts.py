"""The pieces of the compiled rule: numpy's scalar semantics and the per-vehicle kernels that
:mod:`safelane.safety.one_decision.compiled_rule` calls, each one function of
:mod:`safelane.safety.one_decision.reference` (or a part of one) for one vehicle, with the same operations in the same
order (bit-identical; metres, m/s, seconds).

The literals below are read by the kernels as globals, which numba freezes at compile time:
:mod:`safelane.safety.one_decision.compiled` checks them against the model's.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.safety.one_decision import forecast
from safelane.safety.one_decision.forecast import accelerated

# incentive_first compiles forecast.accelerated in: numba's cache watches this file only.
drop_stale_kernel_cache(__file__, (forecast.__file__,))

LANE_LEFT, IDLE, LANE_RIGHT, FASTER, SLOWER = 0, 1, 2, 3, 4
N_ACTIONS = 5
N_FALLBACKS = 4  # fallbacks k = 0..MAX_HOLD_DECISIONS (a literal, so the loops over them unroll)
IDM_LANE_MARGIN = 1.0
NOT_ZERO = 1e-2


# --------------------------------------------------------------------------------------------
# numpy's scalar semantics.
# --------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def nmin(a: float, b: float) -> float:
    """``np.minimum(a, b)`` to the bit: NaN if either is, and ``b`` when they compare equal (numpy's loops return
    the second of −0.0 and 0.0; Python's ``min`` is neither)."""
    return a if (a < b or a != a) else b


@njit(cache=True, inline="always")
def nmax(a: float, b: float) -> float:
    """``np.maximum(a, b)`` to the bit (:func:`nmin`'s conventions)."""
    return a if (a > b or a != a) else b


@njit(cache=True, inline="always")
def speed_index(speed: float, ts: np.ndarray) -> int:
    """``model.speed_to_index`` for one speed (``np.round`` is ``rint``: halves to even)."""
    n = ts.shape[0]
    r = np.rint((speed - ts[0]) / (ts[n - 1] - ts[0]) * (n - 1))
    return int(nmin(nmax(r, 0.0), n - 1.0))


@njit(cache=True, inline="always")
def lane_index(y: float, lane_width: float, lanes_count: int) -> int:
    """``RoadState.lane_of`` for one lateral position [m]."""
    return int(nmin(nmax(np.rint(y / lane_width), 0.0), lanes_count - 1.0))


@njit(cache=True, inline="always")
def idm_behind(
    acc: float, delta: float, dec: float, wanted: float, time_wanted: float, vx: float,
    gap: float, ego_speed: float, ego_target: float,
) -> float:  # fmt: skip
    """``model.idm_acceleration_behind`` for one vehicle (same operations, same order)."""
    target = 1e-2 if abs(ego_target) < 1e-2 else ego_target
    free = acc * (1 - math.pow(nmax(ego_speed, 0.0) / abs(target), delta))
    ab = -acc * dec
    dv = ego_speed - vx
    d_star = wanted + ego_speed * time_wanted + ego_speed * dv / (2 * np.sqrt(ab))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    q = d_star / d
    return free - acc * (q * q)


@njit(cache=True, error_model="numpy")
def linear_behind(
    k0: float, k1: float, k2: float, wanted: float, time_wanted: float, own_speed: float,
    gap: float, ego_speed: float, ego_target: float,
) -> float:  # fmt: skip
    """``model.linear_acceleration_behind`` for one vehicle (same operations, same order)."""
    d_safe = wanted + nmax(ego_speed, 0.0) * time_wanted
    return k0 * (ego_target - ego_speed) + k1 * nmin(own_speed - ego_speed, 0.0) + k2 * nmin(gap - d_safe, 0.0)


@njit(cache=True, error_model="numpy")
def least_desired_gap(
    acc: float, dec: float, wanted: float, time_wanted: float, ego_speed: float, speed_low: float, speed_high: float
) -> float:  # fmt: skip
    """``model.least_desired_gap`` for one vehicle (same operations, same order)."""
    ab = -acc * dec
    base = wanted + ego_speed * time_wanted
    d_hi = base + ego_speed * (ego_speed - speed_high) / (2 * np.sqrt(ab))
    d_lo = base + ego_speed * (ego_speed - speed_low) / (2 * np.sqrt(ab))
    lo, hi = nmin(d_hi, d_lo), nmax(d_hi, d_lo)
    if lo > 0.0:
        return lo
    if hi < 0.0:
        return -hi
    return 0.0


@njit(cache=True, error_model="numpy")
def idm_behind_gap(
    acc: float, delta: float, ego_speed: float, ego_target: float, gap: float, desired_gap: float
) -> float:  # fmt: skip
    """``model.idm_acceleration_behind_gap`` for one vehicle (same operations, same order)."""
    target = 1e-2 if abs(ego_target) < 1e-2 else ego_target
    free = acc * (1 - math.pow(nmax(ego_speed, 0.0) / abs(target), delta))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    q = desired_gap / d
    return free - acc * (q * q)


@njit(cache=True, error_model="numpy")
def passing_path(
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
    b = nmax(brake_max[i], 1e-6)
    limit = -max_braking_imposed[i]
    accel = nmax(accel_max[i], 0.0)
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
            q = least_desired_gap(acc, dec, dw, tw, ego_vf, v_lo, vx[i] + accel * tau)
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
            out[j] = nmin(out[j], xj)


@njit(cache=True, inline="always")
def braking_from_now(x0: float, v: float, crashed: bool, brake: float, tau: float) -> tuple[float, float]:
    """Position [m] and speed [m/s] at ``tau`` [s] of a vehicle braking at its limit ``brake`` [m/s²] from now,
    from its forward speed (a crashed one stopped): the model's leader braking, same operations, same order."""
    v0 = 0.0 if crashed else nmax(v, 0.0)
    b = nmax(1e9 if crashed else brake, 1e-6)
    s = nmin(tau, v0 / b)
    return x0 + v0 * s - 0.5 * b * (s * s), v0 - b * s


@njit(cache=True, error_model="numpy")
def incentive_first(
    i: int, r: int, m: int, near: np.ndarray, lanes_near: np.ndarray, band_near: np.ndarray, x: np.ndarray,
    vx: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray,
    dw_all: np.ndarray, tw_all: np.ndarray, acc_all: np.ndarray, dec_all: np.ndarray, linear_incentive: bool,
    linear_incentive_braking: bool, ego_xs: np.ndarray, ego_speed: float, kv: float, kt: float,
    powers: np.ndarray, frames: int, t: np.ndarray, min_acc_gain: float, now_acc: np.ndarray, accelerations: bool,
) -> float:  # fmt: skip
    """``model.incentive_times`` for vehicle ``i`` (row ``r``; same operations, same order): the first frame time
    [s] at which MOBIL's incentive lets it turn in behind the ego; inf: none. ``accelerations``: also with every
    car at its acceleration now (``now_acc`` [m/s²], per state row; ``model._gains_accelerating``)."""
    v = vx[i]
    linear = np.isfinite(lin_k0[i])
    if linear and not linear_incentive:
        return np.inf
    dw, tw, acc, dec = dw_all[i], tw_all[i], acc_all[i], dec_all[i]
    k1, k2 = lin_k1[i], lin_k2[i]
    d_safe = dw + nmax(v, 0.0) * tw
    for f in range(frames + 1):
        tau = t[f]
        own_x = x[i] + v * tau
        d = own_x - ego_xs[f, 0]
        if not d <= 0:
            continue
        ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
        if linear:
            ego_term = k1 * nmin(ego_vf - v, 0.0) + k2 * nmin(-d - d_safe, 0.0)
            lead = braking = 0.0
            found = False
            for k in range(m):
                ii = near[k]
                if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and x[ii] > x[i]:
                    lv = vx[ii]
                    term = k1 * nmin(lv - v, 0.0) + k2 * nmin(((x[ii] + lv * tau) - own_x) - d_safe, 0.0)
                    lx, lvb = braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    term_b = k1 * nmin(lvb - v, 0.0) + k2 * nmin((lx - own_x) - d_safe, 0.0)
                    if found:
                        lead, braking = nmin(lead, term), nmin(braking, term_b)
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
                if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and x[ii] > x[i]:
                    lv = vx[ii]
                    q = gap_ratio(dw, tw, acc, dec, v, lv, (x[ii] + lv * tau) - own_x)
                    lead = nmax(lead, q * q) if found else q * q
                    found = True
            q_ego = gap_ratio(dw, tw, acc, dec, v, ego_vf, -d)
            if acc * lead - acc * (q_ego * q_ego) >= min_acc_gain:
                return tau
            if accelerations:
                own_x, own_v = accelerated(x[i], v, now_acc[i], tau)
                ex = ego_xs[f, 0]
                if own_x - ex <= 0:
                    lead = 0.0
                    found = False
                    for k in range(m):
                        ii = near[k]
                        if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and x[ii] > x[i]:
                            lx, lv = accelerated(x[ii], vx[ii], now_acc[ii], tau)
                            q = gap_ratio(dw, tw, acc, dec, own_v, lv, lx - own_x)
                            lead = nmax(lead, q * q) if found else q * q
                            found = True
                    q_ego = gap_ratio(dw, tw, acc, dec, own_v, ego_vf, ex - own_x)
                    if acc * lead - acc * (q_ego * q_ego) >= min_acc_gain:
                        return tau
    return np.inf


@njit(cache=True, error_model="numpy")
def polite_first(
    i: int, r: int, m: int, near: np.ndarray, lanes_near: np.ndarray, band_near: np.ndarray, lane: int,
    x: np.ndarray, vx: np.ndarray, p: float, dw: float, tw: float, acc: float, dec: float, ego_xs: np.ndarray,
    ego_speed: float, kv: float, kt: float, powers: np.ndarray, frames: int, t: np.ndarray, min_acc_gain: float,
) -> bool:  # fmt: skip
    """``model.polite_turn_ins`` for vehicle ``i`` (row ``r``, politeness ``p`` > 0, its IDM constants ``dw`` [m],
    ``tw`` [s], ``acc``, ``dec`` [m/s²]) turning into ``lane`` (same operations, same order): whether its followers'
    gain lets it turn in behind the ego at some frame of the decision."""
    v = vx[i]
    old = lanes_near[r]
    for f in range(frames + 1):
        tau = t[f]
        own_x = x[i] + v * tau
        ego_x = ego_xs[f, 0]
        d = own_x - ego_x
        if not d <= 0:
            continue
        ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
        lead = 0.0
        found = False
        new_front = new_rear = old_front = old_rear = -2  # a row of near; -1: the ego; -2: none
        pos_nf = pos_nr = pos_of = pos_or = 0.0
        # The new lane's neighbours: the ego first, then the others in order (model._neighbours' ties).
        if own_x <= ego_x:
            new_front, pos_nf = -1, ego_x
        else:
            new_rear, pos_nr = -1, ego_x
        for k in range(m):
            ii = near[k]
            if (lanes_near[k] == old or band_near[k] == old) and x[ii] > x[i]:  # incentive_first's leaders
                lv = vx[ii]
                q = gap_ratio(dw, tw, acc, dec, v, lv, (x[ii] + lv * tau) - own_x)
                lead = nmax(lead, q * q) if found else q * q
                found = True
            if k == r:
                continue
            pos = x[ii] + vx[ii] * tau
            if lanes_near[k] == lane or band_near[k] == lane:
                if own_x <= pos and (new_front == -2 or pos <= pos_nf):
                    new_front, pos_nf = k, pos
                if pos < own_x and (new_rear == -2 or pos > pos_nr):
                    new_rear, pos_nr = k, pos
            if lanes_near[k] == old or band_near[k] == old:
                if own_x <= pos and (old_front == -2 or pos <= pos_of):
                    old_front, pos_of = k, pos
                if pos < own_x and (old_rear == -2 or pos > pos_or):
                    old_rear, pos_or = k, pos
        q_ego = gap_ratio(dw, tw, acc, dec, v, ego_vf, -d)
        own_gain = acc * lead - acc * (q_ego * q_ego)
        new_change = 0.0
        if new_rear != -2:
            v_rear = ego_vf if new_rear == -1 else vx[near[new_rear]]
            before = 0.0
            if new_front != -2:
                v_front = ego_vf if new_front == -1 else vx[near[new_front]]
                q = gap_ratio(dw, tw, acc, dec, v_rear, v_front, pos_nf - pos_nr)
                before = acc * (q * q)
            q = gap_ratio(dw, tw, acc, dec, v_rear, v, own_x - pos_nr)
            new_change = before - acc * (q * q)
        old_change = 0.0
        if old_rear != -2:
            v_rear = vx[near[old_rear]]
            after = 0.0
            if old_front != -2:
                q = gap_ratio(dw, tw, acc, dec, v_rear, vx[near[old_front]], pos_of - pos_or)
                after = acc * (q * q)
            q = gap_ratio(dw, tw, acc, dec, v_rear, v, own_x - pos_or)
            old_change = acc * (q * q) - after
        polite = p * (new_change + old_change)
        if polite > 0.0 and own_gain + polite >= min_acc_gain:
            return True
    return False


@njit(cache=True, inline="always")
def desired_gap_range(
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
def incentive_first_any_speed(
    i: int, r: int, m: int, near: np.ndarray, lanes_near: np.ndarray, band_near: np.ndarray, x: np.ndarray,
    vx: np.ndarray,
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
    v0 = 0.0 if crashed[i] else nmax(vx[i], 0.0)
    accel = 0.0 if crashed[i] else nmax(accel_max[i], 0.0)
    speed = 0.0 if crashed[i] else math.hypot(vx[i], vy[i])
    for f in range(frames + 1):
        tau = t[f]
        x_lo, v_lo = braking_from_now(x[i], vx[i], crashed[i], brake_max[i], tau)
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
                if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and x[ii] > x[i]:
                    lx_lo, lv_lo = braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    term = k1 * nmin(lv_lo - v_hi, 0.0) + k2 * nmin((lx_lo - x_hi) - (dw + v_hi * tw), 0.0)
                    lead = nmin(lead, term) if found else term
                    found = True
            if ego_term - lead >= min_acc_gain:
                return tau
        else:
            lo, hi = desired_gap_range(dw, tw, root_ab, v_lo, v_hi, ego_vf, ego_vf)
            least = lo if lo > 0.0 else (-hi if hi < 0.0 else 0.0)
            q_ego = least / max(gap_ego, 1e-2)
            ego_term = q_ego * q_ego
            lead = 0.0
            for k in range(m):
                ii = near[k]
                if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and x[ii] > x[i]:
                    lx_lo, lv_lo = braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                    la = 0.0 if crashed[ii] else nmax(accel_max[ii], 0.0)
                    lv_hi = (0.0 if crashed[ii] else math.hypot(vx[ii], vy[ii])) + la * tau
                    gap = lx_lo - x_hi
                    if not gap >= 1e-2:
                        lead = np.inf  # the gap may close: IDM's term has no bound
                        break
                    lo, hi = desired_gap_range(dw, tw, root_ab, v_lo, v_hi, lv_lo, lv_hi)
                    q = max(hi, -lo) / gap
                    lead = max(lead, q * q)
            if acc * lead - acc * ego_term >= min_acc_gain:
                return tau
    return np.inf


@njit(cache=True, inline="always")
def gap_ratio(
    dw: float, tw: float, acc: float, dec: float, v: float, front_speed: float, gap: float
) -> float:  # fmt: skip
    """``model._gap_ratio`` for one vehicle (same operations, same order)."""
    ab = -acc * dec
    d_star = dw + v * tw + v * (v - front_speed) / (2 * np.sqrt(ab))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    return d_star / d


@njit(cache=True, inline="always")
def follower_row(
    out: np.ndarray, x0: float, vx: float, acc: float, brake: float, t_r: float, t: np.ndarray
) -> None:  # fmt: skip
    """``model.follower_positions`` for one vehicle into ``out`` (same operations, same order)."""
    v0 = nmax(vx, 0.0)
    b = nmax(brake, 1e-6)
    ha = 0.5 * acc
    hb = 0.5 * b
    v1 = v0 + acc * t_r
    stop = v1 / b
    for j in range(t.shape[0]):
        t1 = nmin(t[j], t_r)
        x1 = x0 + v0 * t1 + ha * (t1 * t1)
        t2 = nmin(nmax(t[j] - t_r, 0.0), stop)
        out[j] = x1 + v1 * t2 - hb * (t2 * t2)


@njit(cache=True, error_model="numpy")
def idm_follower_window(
    i: int, x: np.ndarray, vx: np.ndarray, comfort_acc: np.ndarray, comfort_dec: np.ndarray,
    distance_wanted: np.ndarray, time_wanted: np.ndarray, accel_max: np.ndarray, brake_max: np.ndarray,
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
    last = ego_xs.shape[0] - 1
    for k in range(N_FALLBACKS):
        xf4[k] = x[i]
        vf4[k] = vx[i]
        worst[k] = math.inf
    for j in range(hi + 1):
        for k in range(N_FALLBACKS):
            o = xf4[k]
            if j == last:  # model: what the follower bound still covers beyond the last frame
                v = nmax(vf4[k], 0.0)
                v1 = v + a_max * reaction
                o = o + (v * reaction + 0.5 * a_max * (reaction * reaction) + v1 * v1 / (2.0 * max(b_max, 1e-6)))
            if j >= lo:
                worst[k] = nmin(worst[k], -1.0 * (o - ego_xs[j, k]) - half)
            if j < hi:  # IDMVehicle.act at frame j, then Vehicle.step
                vf = vf4[k]
                d = ego_xs[j, k] - xf4[k]
                if not (abs(d) > NOT_ZERO):
                    d = NOT_ZERO if d >= 0.0 else -NOT_ZERO
                ratio = (d0 + vf * tw + vf * (vf - ego_vs[j, k]) / two_sqrt_ab) / d
                acc_f = acc - acc * (ratio * ratio)  # the free-road term at its largest, acc
                acc_f = nmax(nmin(acc_f, a_max), -b_max)
                xf4[k] = xf4[k] + vf4[k] * frame_dt
                vf4[k] = vf4[k] + acc_f * frame_dt
