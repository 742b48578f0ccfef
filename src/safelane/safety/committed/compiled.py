"""The committed shield's arithmetic compiled: the reachable sets, the ego's plans and every car's worst gap to
them, as numba kernels bit-identical to the numpy reference (:mod:`safelane.safety.committed`,
:mod:`safelane.safety.committed.sets`).

Each kernel follows its reference function operation by operation and in the same order, so the IEEE-754 arithmetic (no
fastmath) rounds the same way (the conventions of :mod:`safelane.safety.one_decision.compiled`: ``np.minimum`` /
``np.maximum`` propagate NaN, ``x**2`` on arrays is ``x*x``, ``np.power`` and ``np.sqrt`` are libm's). What is per car
and cheap (the lanes a car is in, its entry times, its speed bounds, the turning shortfall) stays numpy and is shared by
both engines; the loops over frames, plans and cars are here. ``tests/test_committed_engines.py`` checks every kernel
against its reference on hypothesis states and both simulators' episodes.

Units: metres, m/s, seconds.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.safety.committed.plan_family import Lanes, held_lanes, onsets, plan_actions
from safelane.safety.committed.sets import (
    ESCAPE_TOLERANCE,
    LANE_CHANGES_BEGUN,
    MAX_SPEED,
    CarSets,
    lane_change_allowance,
    lane_crossing_time,
    path_speed,
    rows_in,
    speed_bounds,
)
from safelane.safety.ego import action_lanes, action_targets
from safelane.safety.one_decision import compiled_parts
from safelane.safety.one_decision.compiled_parts import N_ACTIONS, N_FALLBACKS, nmax, nmin, speed_index
from safelane.safety.world import LATERAL_MOTION_THRESHOLD, Dynamics, RoadState

drop_stale_kernel_cache(__file__, (compiled_parts.__file__,))

_BIG = np.finfo(np.float64).max  # np.nan_to_num's image of +inf
CHUNK = 8
"""Frames per chunk of the cheap bound that lets the plans' kernel skip cars far from every plan."""


@njit(cache=True, inline="always")
def _nan_to_num(z: float) -> float:
    """``np.nan_to_num`` of one number."""
    if z != z:
        return 0.0
    if z == np.inf:
        return _BIG
    if z == -np.inf:
        return -_BIG
    return z


@njit(cache=True, inline="always")
def _rise_distance(v: float, a: float, v_max: float, t: float) -> float:
    """``committed_sets.rise``'s distance [m] for one time."""
    t_top = nmax(v_max - v, 0.0) / nmax(a, 1e-9)
    tt = nmin(t, t_top)
    return v * tt + 0.5 * a * tt * tt + v_max * nmax(t - t_top, 0.0)


@njit(cache=True, inline="always")
def _fall_distance(v: float, b: float, v_min: float, t: float) -> float:
    """``committed_sets.fall``'s distance [m] for one time."""
    t_low = nmax(v - v_min, 0.0) / nmax(b, 1e-9)
    tt = nmin(t, t_low)
    return v * tt - 0.5 * b * tt * tt + v_min * nmax(t - t_low, 0.0)


@njit(cache=True, error_model="numpy")
def sets_kernel(
    x: np.ndarray, v: np.ndarray, a: np.ndarray, b: np.ndarray, v_min: np.ndarray, v_max: np.ndarray,
    allowance: np.ndarray, t: np.ndarray, law_rows: np.ndarray, law_k: np.ndarray, law_acc: np.ndarray,
    law_delta: np.ndarray, target: np.ndarray, crashed: np.ndarray, dt: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``committed_sets.car_sets``' longitudinal sets: :func:`envelope` with the turning ``allowance``, capped by
    :func:`law_rise` where a law applies (``law_rows``; gains as :func:`acceleration_law` returns them), a crashed
    car a wall. Returns (x_lo, x_hi, v_lo, v_hi), each (cars, frames)."""
    n, m = x.shape[0], t.shape[0]
    x_lo, x_hi = np.empty((n, m)), np.empty((n, m))
    v_lo, v_hi = np.empty((n, m)), np.empty((n, m))
    # The law's bound (law_rise): highway-env's explicit Euler, the acceleration at most min(a, max(law, 0)). Each
    # car's recursion is sequential; the cars are stepped side by side, frame by frame, so that their powers (the
    # costly part) do not wait on one another. The bounds go in the output rows first.
    ruled = law_rows & ~crashed
    vk, xk = np.where(ruled, v, 0.0), np.zeros(n)
    safe_target, k = np.ones(n), np.empty(n)
    settled = np.zeros(n, dtype=np.bool_)  # the speed stopped changing: the law's input, and so its step, stays
    for i in range(n):
        if ruled[i] and np.isfinite(target[i]) and target[i] > 0.0:
            safe_target[i] = target[i]
        k[i] = _nan_to_num(law_k[i])
        v_hi[i, 0], x_hi[i, 0] = vk[i], 0.0
    for j in range(1, m):
        for i in range(n):
            if not ruled[i]:
                continue
            xk[i] = xk[i] + dt * nmax(vk[i], 0.0)
            if not settled[i]:
                if np.isfinite(law_k[i]):
                    law = k[i] * (target[i] - vk[i])
                else:
                    law = law_acc[i] * (1.0 - np.power(nmax(vk[i], 0.0) / safe_target[i], law_delta[i]))
                before = vk[i]
                vk[i] = vk[i] + dt * nmin(a[i], nmax(_nan_to_num(law), 0.0))
                settled[i] = vk[i] == before
            v_hi[i, j], x_hi[i, j] = vk[i], xk[i]
    for i in range(n):
        vi, ai, bi, lo, hi = v[i], a[i], b[i], v_min[i], v_max[i]
        if crashed[i]:  # a wall where it stands
            x_lo[i], x_hi[i], v_lo[i], v_hi[i] = x[i], x[i], 0.0, 0.0
            continue
        # The closed forms' switching times do not depend on the frame: computed once (the same operations).
        t_low = nmax(vi - lo, 0.0) / nmax(bi, 1e-9)
        start, top = nmax(vi, 0.0), nmax(hi, 0.0)
        t0 = nmax(-vi / nmax(ai, 1e-9), 0.0)
        t_top = nmax(top - start, 0.0) / nmax(ai, 1e-9)
        back_v, back_low = nmin(vi, 0.0), nmin(lo, 0.0)
        t0b = nmax(vi / nmax(bi, 1e-9), 0.0)
        t_back = nmax(back_v - back_low, 0.0) / nmax(bi, 1e-9)
        for j in range(m):  # the envelope, frame by frame independent
            tj = t[j]
            # envelope: the speeds' bang-bang bounds, the forward and backward parts of the positions.
            v_up = nmin(vi + ai * tj, hi)
            v_down = nmax(vi - bi * tj, lo)
            tt = nmin(tj, t_low)
            d_lo = vi * tt - 0.5 * bi * tt * tt + lo * nmax(tj - t_low, 0.0)
            t_up = nmax(tj - t0, 0.0)
            tt = nmin(t_up, t_top)
            d_hi = start * tt + 0.5 * ai * tt * tt + top * nmax(t_up - t_top, 0.0)
            t_down = nmax(tj - t0b, 0.0)
            tt = nmin(t_down, t_back)
            back = back_v * tt - 0.5 * bi * tt * tt + back_low * nmax(t_down - t_back, 0.0)
            d_lo = nmax(d_lo - allowance[i, j], back)
            xl, xh = x[i] + d_lo, x[i] + d_hi
            if ruled[i]:
                xh = nmin(xh, x[i] + x_hi[i, j])
                v_up = nmin(v_up, v_hi[i, j])
            x_lo[i, j], x_hi[i, j], v_lo[i, j], v_hi[i, j] = xl, xh, v_down, v_up
    return x_lo, x_hi, v_lo, v_hi


@njit(cache=True, error_model="numpy")
def ego_paths(
    ego_x: float, ego_speed: float, targets: np.ndarray, ts: np.ndarray, powers: np.ndarray, frames: int,
    horizon: int, frame_dt: float, ego_kp: float,
) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """``ego.ego_trajectories``: the ego's positions [m] and speeds [m/s], each (5, holds, frames + 1), for the
    action set-points ``targets`` (``ego.action_targets``); ``powers``: the P-controller's decay powers."""
    n_t = horizon * frames + 1
    xs = np.empty((N_ACTIONS, N_FALLBACKS, n_t))
    vs = np.empty((N_ACTIONS, N_FALLBACKS, n_t))
    for a in range(N_ACTIONS):
        for k in range(N_FALLBACKS):
            v, x, tg = ego_speed, ego_x, targets[a]
            for d in range(horizon):
                base = d * frames
                if d > k:  # the hold is over: SLOWER from the speed reached
                    tg = ts[max(speed_index(v, ts) - 1, 0)]
                dv = v - tg
                # The decision's frame 0 overwrites the last one's, as the reference's slices do.
                xs[a, k, base] = 0.0 * frame_dt + x
                vp = dv * powers[0] + tg
                vs[a, k, base] = vp
                cov = 0.0
                for j in range(1, frames + 1):
                    cov = vp if j == 1 else cov + vp  # np.cumsum: sequential
                    vp = dv * powers[j] + tg
                    xs[a, k, base + j] = cov * frame_dt + x
                    vs[a, k, base + j] = vp
                x, v = xs[a, k, base + frames], vp
            xs[a, k, n_t - 1] += nmax(v - 0.0, 0.0) / ego_kp  # the exponential tail beyond the horizon
    return xs, vs


@njit(cache=True, error_model="numpy")
def set_points_kernel(ego_v: np.ndarray, first: float, ts: np.ndarray, frames: int) -> np.ndarray:
    """``committed.plan_set_points`` of one action (``first``: its set-point [m/s]; ``ego_v``: (holds, frames + 1)
    its speeds)."""
    holds, n_t = ego_v.shape
    out = np.empty((holds, n_t))
    for hold in range(holds):
        point = first
        for d in range(-(-n_t // frames)):
            if d > hold:
                point = ts[max(speed_index(ego_v[hold, d * frames], ts) - 1, 0)]
            for j in range(d * frames, min((d + 1) * frames, n_t)):
                out[hold, j] = point
    return out


@njit(cache=True, inline="always")
def _follower_high(
    x: float, speed: float, a: float, b: float, v_min: float, v_max: float, react: float, tj: float
) -> float:  # fmt: skip
    """``committed.follower_bound`` at one time ``tj`` [s] for one plan's reaction time ``react`` [s]."""
    v0 = nmax(speed, 0.0)
    if tj <= react:
        return x + _rise_distance(v0, a, v_max, nmin(tj, react))
    d_r = _rise_distance(v0, a, v_max, react)
    v_r = nmin(v0 + a * react, v_max)
    return x + (d_r + _fall_distance(v_r, b, nmin(v_min, 0.0), nmax(tj - react, 0.0)))


@njit(cache=True, error_model="numpy")
def follower_kernel(
    x: float, speed: float, a: float, b: float, v_min: float, v_max: float, react: np.ndarray, t: np.ndarray
) -> np.ndarray:  # fmt: skip
    """``committed.follower_bound``: (holds, frames) [m] the highest position of a follower reacting at ``react``."""
    out = np.empty((react.shape[0], t.shape[0]))
    for h in range(react.shape[0]):
        for j in range(t.shape[0]):
            out[h, j] = _follower_high(x, speed, a, b, v_min, v_max, react[h], t[j])
    return out


@njit(cache=True, error_model="numpy")
def followers_kernel(
    x: np.ndarray, speed: np.ndarray, a: np.ndarray, b: np.ndarray, v_min: np.ndarray, v_max: np.ndarray,
    rows: np.ndarray, react: float, t: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`follower_kernel` of each car of ``rows`` (per car: position, speed along its path, acceleration and
    braking limits, follower speed bounds) for one reaction time ``react`` [s]: (rows, frames) [m]."""
    out = np.empty((rows.shape[0], t.shape[0]))
    for k in range(rows.shape[0]):
        i = rows[k]
        for j in range(t.shape[0]):
            out[k, j] = _follower_high(x[i], speed[i], a[i], b[i], v_min[i], v_max[i], react, t[j])
    return out


@njit(cache=True, error_model="numpy")
def car_gaps_kernel(
    x_lo: np.ndarray, x_hi: np.ndarray, entry: np.ndarray, now: np.ndarray, ego_x: np.ndarray, onset: np.ndarray,
    lane_ids: np.ndarray, lane_until: np.ndarray, held_a: int, held_b: int, last_frame: int,
    carried_lane: np.ndarray, carried_high: np.ndarray,
    x: np.ndarray, half: np.ndarray, ahead: np.ndarray, own_lane: np.ndarray, speed: np.ndarray,
    accel_max: np.ndarray, brake_max: np.ndarray, fv_min: np.ndarray, fv_max: np.ndarray,
    t: np.ndarray, follower_reaction: float, order: np.ndarray, least: bool, lo_min: np.ndarray, hi_max: np.ndarray,
    floor: float,
) -> np.ndarray:  # fmt: skip
    """``committed.car_gaps``: (cars, holds) each car's worst bumper-to-bumper gap [m] to the plans (the reference
    documents the arguments; lanes as ``lane_ids``/``lane_until``, the carried follower bounds as ``carried_lane`` (a
    bitmask of the lanes each applies in, 0: none) and ``carried_high``; per car: ``half`` the half-lengths' sum,
    ``own_lane`` its lane, ``speed`` along its path, ``fv_min``/``fv_max`` its follower speed bounds). Cars are visited
    in ``order``. With ``least`` only the least gap over the cars is wanted: a car is skipped (its row left inf) when a
    bound below its gap (from ``lo_min``/``hi_max`` (cars, chunks), its lowest and highest position in each chunk of
    :data:`CHUNK` frames) is already above the least gap so far for every plan — rounding is monotone, so the computed
    gap is at least the computed bound and the least gap is the same to the bit. With ``least`` and a ``floor`` above
    −inf the kernel returns as soon as every plan's least gap so far is below ``floor`` (a verdict below a margin needs
    no more: the rows are then only a witness)."""
    n, holds, m = x.shape[0], ego_x.shape[0], t.shape[0]
    worst = np.full((n, holds), np.inf)
    running = np.full(holds, np.inf)
    skip = np.zeros(holds, dtype=np.bool_)
    chunks = lo_min.shape[1] if least else 0
    ego_lo, ego_hi = np.full((holds, chunks), np.inf), np.full((holds, chunks), -np.inf)
    for h in range(holds):
        for j in range(m if least else 0):
            c = j // CHUNK
            ego_lo[h, c], ego_hi[h, c] = nmin(ego_lo[h, c], ego_x[h, j]), nmax(ego_hi[h, c], ego_x[h, j])
    t_last = t[min(max(last_frame, 0), m - 1)]
    react = np.empty(holds)
    for h in range(holds):
        react[h] = nmax(onset[h] + follower_reaction, 0.0)  # a past reaction: braking from now
    for li in range(lane_ids.shape[0]):
        lane, until = lane_ids[li], lane_until[li]
        held_lane = lane in (held_a, held_b)
        for oi in range(n):
            i = order[oi]
            if least:
                below = True  # the bound is above the least gap so far for every plan: this car cannot lower it
                for h in range(holds):
                    bound = np.inf
                    for c in range(chunks):
                        chunk = nmax(lo_min[i, c] - ego_hi[h, c] - half[i], ego_lo[h, c] - hi_max[i, c] - half[i])
                        bound = nmin(bound, chunk)
                    skip[h] = bound > running[h]
                    below = below and skip[h]
                if below:
                    continue
            entry_i = entry[i, lane]  # the same for every plan
            count = np.isfinite(entry_i)
            if held_lane:  # cut-ins, and cars behind in the ego's lane (held_a): theirs to avoid
                count = count and now[i, lane] and (ahead[i] or lane != held_a)
            if not count:
                continue
            following = held_lane and not ahead[i] and own_lane[i] == lane
            carried = (carried_lane[i] >> lane) & 1 == 1
            for h in range(holds):
                if least and skip[h]:  # this plan's least gap is already below the car's bound
                    continue
                low = np.inf
                for j in range(m):
                    if not (t[j] >= entry_i and t[j] <= t_last and t[j] <= until):
                        continue
                    high = x_hi[i, j]
                    if following:
                        high = nmin(high, _follower_high(x[i], speed[i], accel_max[i], brake_max[i], fv_min[i],
                                                         fv_max[i], react[h], t[j]))  # fmt: skip
                    if carried:
                        high = nmin(high, carried_high[i, j])
                    gap = nmax(x_lo[i, j] - ego_x[h, j] - half[i], ego_x[h, j] - high - half[i])
                    low = nmin(low, gap)
                worst[i, h] = nmin(worst[i, h], low)
                if least:
                    running[h] = nmin(running[h], low)
            if least and floor > -np.inf:
                settled = True
                for h in range(holds):
                    settled = settled and running[h] < floor
                if settled:
                    return worst
    return worst


@njit(cache=True, error_model="numpy")
def prepare_kernel(
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, can_change: np.ndarray, target: np.ndarray, k0: np.ndarray, k1: np.ndarray, k2: np.ndarray,
    idm_acc: np.ndarray, idm_delta: np.ndarray, ego_x: float, ego_length: float, t: np.ndarray,
    consts: np.ndarray, lanes_count: int,
) -> tuple:  # fmt: skip
    """Every per-car quantity of ``committed_sets`` and ``committed.car_gaps`` in one pass (the numpy functions'
    operations, elementwise): (speed along the path, the sets' speed bounds v_min / v_max, the turning shortfall
    (cars, frames), the law's rows and gains, the lanes occupied / now / entry times (cars, lanes), and for the
    gaps: half-lengths' sum, ahead, own lane, the follower speed bounds). ``consts``: dt, lane
    width, body width, the lateral-motion threshold, cut-in time, lane-crossing time, one change's shortfall,
    the changes begun, the top speed (:func:`prepare_consts`)."""
    dt, lane_width, body_width, lateral = consts[0], consts[1], consts[2], consts[3]
    cut_in, crossing, per_change, begun, top = consts[4], consts[5], consts[6], int(consts[7]), consts[8]
    n, m = x.shape[0], t.shape[0]
    speed, v_min, v_max = np.empty(n), np.empty(n), np.empty(n)
    fv_min, fv_max = np.empty(n), np.empty(n)
    allowance = np.empty((n, m))
    law_rows, law_k = np.empty(n, dtype=np.bool_), np.empty(n)
    occupied, now = np.empty((n, lanes_count), dtype=np.bool_), np.empty((n, lanes_count), dtype=np.bool_)
    entry = np.empty((n, lanes_count))
    half, ahead = np.empty(n), np.empty(n, dtype=np.bool_)
    own_lane = np.empty(n, dtype=np.int64)
    half_lane = 0.5 * lane_width
    for i in range(n):
        v = vx[i] * np.cos(heading[i]) + vy[i] * np.sin(heading[i])
        speed[i] = v
        linear_gain = np.isfinite(k0[i])
        bounded_linear = (linear_gain and np.isfinite(k1[i]) and np.isfinite(k2[i]) and k0[i] >= 0.0 and k1[i] >= 0.0
                          and k2[i] >= 0.0 and np.isfinite(target[i]))  # fmt: skip
        known = np.isfinite(target[i])
        # speed_bounds: the sets' (linear drivers without the set-point bound: MAX_SPEED), the followers' (every
        # linear driver: MAX_SPEED).
        capped = nmax(v, target[i] if known else 0.0)
        top_set = top if ((linear_gain and not bounded_linear) or not known) else capped
        v_min[i], v_max[i] = nmin(v, 0.0), nmax(top_set, v)
        top_follow = top if (linear_gain or not known) else capped
        fv_min[i], fv_max[i] = nmin(v, 0.0), nmax(top_follow, v)
        # acceleration_law
        idm = (not linear_gain) and known and target[i] > 0.0
        if bounded_linear:
            monotone = dt * _nan_to_num(k0[i]) <= 1.0
        else:
            monotone = dt * idm_acc[i] * idm_delta[i] <= (target[i] if idm else 0.0)
        law_rows[i] = (bounded_linear or idm) and monotone and not crashed[i]
        law_k[i] = k0[i] if bounded_linear else np.nan
        # shortfall: one allowance per lane change under way or begun
        turning = abs(heading[i]) > lateral or abs(vy[i]) > 0.3
        count = (1 if turning else 0) + (begun if can_change[i] else 0)
        for j in range(m):
            allowed = float(count) if t[j] > 0.0 else 0.0
            allowance[i, j] = 0.0 if crashed[i] else per_change * allowed
        # occupied_lanes, lanes_now, lane_entry_times
        reach = abs(0.5 * length[i] * np.sin(heading[i])) + abs(0.5 * body_width * np.cos(heading[i]))
        lo, hi = y[i] - reach, y[i] + reach
        own = int(nmin(nmax(np.rint(y[i] / lane_width), 0.0), lanes_count - 1.0))
        own_lane[i] = own
        for lane in range(lanes_count):
            centre = lane * lane_width
            occupied[i, lane] = hi > centre - half_lane and lo < centre + half_lane
            now[i, lane] = occupied[i, lane]
        if turning:
            toward = own + (1 if vy[i] > 0 else -1)
            now[i, min(max(toward, 0), lanes_count - 1)] = True
        for lane in range(lanes_count):
            dist = 10**6
            for other in range(lanes_count):
                if now[i, other]:
                    dist = min(dist, abs(lane - other))
            value = cut_in + (dist - 1) * crossing if dist > 0 else 0.0
            entry[i, lane] = value if (can_change[i] or dist == 0) else np.inf
        half[i] = 0.5 * (length[i] + ego_length)
        ahead[i] = x[i] >= ego_x
    return speed, v_min, v_max, allowance, law_rows, law_k, occupied, now, entry, half, ahead, own_lane, fv_min, fv_max


@njit(cache=True, error_model="numpy")
def chunk_bounds(x: np.ndarray, ego_x: float, x_lo: np.ndarray, x_hi: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(order, lo_min, hi_max): the cars (at ``x`` [m]) nearest the ego first, and each car's lowest and highest
    position [m] in each chunk of :data:`CHUNK` frames of its set (``car_gaps_kernel``'s ``least``)."""
    n = x.shape[0]
    order = np.argsort(np.abs(x - ego_x), kind="mergesort")
    chunks = -(-x_lo.shape[1] // CHUNK)
    lo_min, hi_max = np.full((n, chunks), np.inf), np.full((n, chunks), -np.inf)
    for i in range(n):
        for j in range(x_lo.shape[1]):
            c = j // CHUNK
            lo_min[i, c], hi_max[i, c] = nmin(lo_min[i, c], x_lo[i, j]), nmax(hi_max[i, c], x_hi[i, j])
    return order, lo_min, hi_max


@njit(cache=True, error_model="numpy")
def plans_kernel(
    available: np.ndarray, lane_ids: np.ndarray, lane_until: np.ndarray, lane_counts: np.ndarray, onsets: np.ndarray,
    targets: np.ndarray, ego_x0: float, ego_speed: float, ts: np.ndarray, powers: np.ndarray, frames: int,
    horizon: int, frame_dt: float, ego_kp: float,
    x_lo: np.ndarray, x_hi: np.ndarray, entry: np.ndarray, now: np.ndarray, held_a: int, held_b: int,
    verify: np.ndarray, x: np.ndarray, half: np.ndarray, ahead: np.ndarray, own_lane: np.ndarray, speed: np.ndarray,
    accel_max: np.ndarray, brake_max: np.ndarray, fv_min: np.ndarray, fv_max: np.ndarray, t: np.ndarray,
    follower_reaction: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``committed.verify_plans`` in one call: the ego's paths, each available action's set-points, and the worst
    gap of each action in ``verify`` (its lanes: ``lane_counts[a]`` rows of ``lane_ids``/``lane_until`` from
    ``a``'s offset). Returns (worst (5, holds), xs, vs, set-points (5, holds, frames + 1))."""
    xs, vs = ego_paths(ego_x0, ego_speed, targets, ts, powers, frames, horizon, frame_dt, ego_kp)
    set_points = np.full(vs.shape, np.nan)
    worst = np.full((N_ACTIONS, N_FALLBACKS), -np.inf)
    n = x.shape[0]
    no_carried = np.zeros(n, dtype=np.int64)  # no carried bound in any lane
    empty = np.empty((0, 0))
    # The nearest cars first, so that the far ones are skipped (car_gaps_kernel's ``least``).
    order, lo_min, hi_max = chunk_bounds(x, ego_x0, x_lo, x_hi)
    start = 0
    for a in range(N_ACTIONS):
        stop = start + lane_counts[a]
        first, start = start, stop
        if not available[a]:
            continue
        set_points[a] = set_points_kernel(vs[a], targets[a], ts, frames)
        if not verify[a]:
            continue
        gaps = car_gaps_kernel(x_lo, x_hi, entry, now, xs[a], onsets[a], lane_ids[first:stop],
                               lane_until[first:stop], held_a, held_b, t.shape[0] - 1, no_carried, empty, x, half,
                               ahead, own_lane, speed, accel_max, brake_max, fv_min, fv_max, t, follower_reaction,
                               order, True, lo_min, hi_max, -np.inf)  # fmt: skip
        for h in range(N_FALLBACKS):
            low = np.inf
            for i in range(gaps.shape[0]):
                low = gaps[i, h] if i == 0 else nmin(low, gaps[i, h])
            worst[a, h] = low
    return worst, xs, vs, set_points


@njit(cache=True, error_model="numpy")
def carry_kernel(
    x_lo: np.ndarray, x_hi: np.ndarray, v_lo: np.ndarray, v_hi: np.ndarray, entry: np.ndarray,
    old_x_lo: np.ndarray, old_x_hi: np.ndarray, old_v_lo: np.ndarray, old_v_hi: np.ndarray, old_entry: np.ndarray,
    rows: np.ndarray, frames: int, seconds: float, x: np.ndarray, speed: np.ndarray, occupied: np.ndarray,
    unbraked: np.ndarray, tol: float,
) -> tuple:  # fmt: skip
    """The carried sets' step of :meth:`~safelane.safety.committed.family.CommittedFamily.evaluate_state` in one
    pass, the numpy functions' operations element by element: the sets carried from the last decision
    (``old_*``) shifted ``frames`` frames (``seconds`` [s]) to now (``CarSets.shifted``), the cars outside them
    (``escaped_cars``, or'ed with ``unbraked``), the fresh sets (``x_lo``, …) intersected with them for the cars
    inside (``CarSets.intersect``) and the escaped cars that rolled back (``rolling_back``). ``rows``: each car's
    row among the carried sets (−1: none; ``rows_in``); ``speed``: along its path (``path_speed``); ``occupied``:
    (cars, lanes) the lanes its body overlaps (``occupied_lanes``). Returns (x_lo, x_hi, v_lo, v_hi, entry,
    escaped, rolled back, how many cars had a carried set)."""
    n, m = x_lo.shape
    lanes = entry.shape[1]
    out_x_lo, out_x_hi, out_v_lo, out_v_hi, out_entry = x_lo.copy(), x_hi.copy(), v_lo.copy(), v_hi.copy(), entry.copy()
    escaped, rolled = np.zeros(n, dtype=np.bool_), np.zeros(n, dtype=np.bool_)
    checked = 0
    for i in range(n):
        r = rows[i]
        if r < 0:
            escaped[i] = unbraked[i]
            rolled[i] = escaped[i] and speed[i] < 0.0
            continue
        checked += 1
        # The carried set at frame 0 of now: frame ``frames`` of the last decision's (the padding beyond it).
        lo0 = old_x_lo[r, frames] if frames < m else -np.inf
        hi0 = old_x_hi[r, frames] if frames < m else np.inf
        vlo0 = old_v_lo[r, frames] if frames < m else -np.inf
        vhi0 = old_v_hi[r, frames] if frames < m else np.inf
        inside = (lo0 - tol <= x[i]) and (x[i] <= hi0 + tol)
        inside = inside and (vlo0 - tol <= speed[i]) and (speed[i] <= vhi0 + tol)
        entered = False
        for lane in range(lanes):
            entered = entered or (nmax(old_entry[r, lane] - seconds, 0.0) > tol and occupied[i, lane])
        escaped[i] = (not (inside and not entered)) or unbraked[i]
        if escaped[i]:
            rolled[i] = speed[i] < 0.0 or (vlo0 < 0.0 and x[i] < lo0)
            continue
        for j in range(m):
            shifted = j + frames < m
            out_x_lo[i, j] = nmax(x_lo[i, j], old_x_lo[r, j + frames] if shifted else -np.inf)
            out_x_hi[i, j] = nmin(x_hi[i, j], old_x_hi[r, j + frames] if shifted else np.inf)
            out_v_lo[i, j] = nmax(v_lo[i, j], old_v_lo[r, j + frames] if shifted else -np.inf)
            out_v_hi[i, j] = nmin(v_hi[i, j], old_v_hi[r, j + frames] if shifted else np.inf)
        for lane in range(lanes):
            out_entry[i, lane] = nmax(entry[i, lane], nmax(old_entry[r, lane] - seconds, 0.0))
    return out_x_lo, out_x_hi, out_v_lo, out_v_hi, out_entry, escaped, rolled, checked


# --------------------------------------------------------------------------------------------
# The Python entries: the reference functions' signatures.
# --------------------------------------------------------------------------------------------


class Prepared(NamedTuple):
    """:func:`prepare_kernel`'s per-car quantities of one state."""

    speed: np.ndarray
    v_min: np.ndarray
    v_max: np.ndarray
    allowance: np.ndarray
    law_rows: np.ndarray
    law_k: np.ndarray
    occupied: np.ndarray
    now: np.ndarray
    entry: np.ndarray
    half: np.ndarray
    ahead: np.ndarray
    own_lane: np.ndarray
    fv_min: np.ndarray
    fv_max: np.ndarray


class DynamicsArrays(NamedTuple):
    """What the kernels read of a :class:`Dynamics`, as arrays (computed as the reference computes them)."""

    times: np.ndarray
    """(frames + 1,) [s] ``dyn.times``."""
    onsets: np.ndarray
    """(5, holds) [s] each action's :func:`onsets`."""
    powers: np.ndarray
    """(frames per decision + 1,) the ego's P-controller's decay powers."""
    target_speeds: np.ndarray
    """[m/s] ``dyn.target_speeds``."""
    prepare_consts: np.ndarray
    """:func:`prepare_kernel`'s ``consts``."""


_ARRAYS: dict[int, tuple[Dynamics, DynamicsArrays]] = {}
"""The arrays of each Dynamics object: a family evaluates one Dynamics for as long as the ego's leave time stays
(:meth:`~safelane.safety.committed.family.CommittedFamily.evaluate`)."""


def dynamics_arrays(dyn: Dynamics) -> DynamicsArrays:
    """``dyn``'s :class:`DynamicsArrays`, built once per Dynamics object (read them, never write them)."""
    hit = _ARRAYS.get(id(dyn))
    if hit is not None and hit[0] is dyn:  # the entry holds dyn, so its id is not reused meanwhile
        return hit[1]
    decay = 1.0 - dyn.ego_kp * dyn.frame_dt
    consts = np.array([dyn.frame_dt, dyn.lane_width, dyn.body_width, LATERAL_MOTION_THRESHOLD, dyn.cut_in_time,
                       lane_crossing_time(dyn), lane_change_allowance(dyn), LANE_CHANGES_BEGUN, MAX_SPEED])  # fmt: skip
    arrays = DynamicsArrays(dyn.times, np.stack([onsets(dyn, a) for a in range(N_ACTIONS)]),
                            decay ** np.arange(dyn.frames_per_decision + 1),
                            np.asarray(dyn.target_speeds, dtype=float), consts)  # fmt: skip
    if len(_ARRAYS) >= 64:
        _ARRAYS.clear()
    _ARRAYS[id(dyn)] = (dyn, arrays)
    return arrays


def prepare(state: RoadState, dyn: Dynamics) -> Prepared:
    """The per-car quantities of ``state`` (:func:`prepare_kernel`), computed once per state."""
    arrays = dynamics_arrays(dyn)
    return Prepared(*prepare_kernel(
        _f(state.x), _f(state.y), _f(state.vx), _f(state.vy), _f(state.heading), _f(state.length),
        np.asarray(state.crashed, dtype=np.bool_), np.asarray(state.can_change_lane, dtype=np.bool_),
        _f(state.target_speed), _f(state.linear_speed_gain), _f(state.linear_speed_difference_gain),
        _f(state.linear_distance_gain), _f(state.idm_comfort_acc), _f(state.idm_delta), float(state.ego_x),
        float(state.ego_length), arrays.times, arrays.prepare_consts, int(dyn.lanes_count),
    ))  # fmt: skip


def car_sets_compiled(state: RoadState, dyn: Dynamics, vehicle: np.ndarray, prep: Prepared | None = None) -> CarSets:
    """:func:`safelane.safety.committed.sets.car_sets`, compiled (the same bits); ``prep``: :func:`prepare` of
    ``state`` when already computed."""
    prep = prepare(state, dyn) if prep is None else prep
    x_lo, x_hi, v_lo, v_hi = sets_kernel(
        _f(state.x), prep.speed, _f(state.accel_max), _f(state.brake_max), prep.v_min, prep.v_max, prep.allowance,
        dynamics_arrays(dyn).times, prep.law_rows, prep.law_k, _f(state.idm_comfort_acc), _f(state.idm_delta),
        _f(state.target_speed),
        np.asarray(state.crashed, dtype=np.bool_), float(dyn.frame_dt),
    )  # fmt: skip
    return CarSets(np.asarray(vehicle), x_lo, x_hi, v_lo, v_hi, prep.entry, prep.now)


def ego_trajectories_compiled(state: RoadState, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """:func:`safelane.safety.ego.ego_trajectories`, compiled (the same bits)."""
    decay = 1.0 - dyn.ego_kp * dyn.frame_dt
    powers = decay ** np.arange(dyn.frames_per_decision + 1)
    return ego_paths(float(state.ego_x), float(state.ego_speed), action_targets(state, dyn),
                     np.asarray(dyn.target_speeds, dtype=float), powers, dyn.frames_per_decision,
                     dyn.horizon_decisions, float(dyn.frame_dt), float(dyn.ego_kp))  # fmt: skip


def plan_set_points_compiled(state: RoadState, dyn: Dynamics, ego_v: np.ndarray, action: int) -> np.ndarray:
    """:func:`safelane.safety.committed.plans.plan_set_points`, compiled (the same bits)."""
    return set_points_kernel(np.ascontiguousarray(ego_v), float(action_targets(state, dyn)[action]),
                             np.asarray(dyn.target_speeds, dtype=float), dyn.frames_per_decision)  # fmt: skip


class CarArrays(NamedTuple):
    """What :func:`car_gaps_compiled` reads of a state's cars, computed once per state."""

    x: np.ndarray
    half: np.ndarray
    ahead: np.ndarray
    own_lane: np.ndarray
    speed: np.ndarray
    accel_max: np.ndarray
    brake_max: np.ndarray
    fv_min: np.ndarray
    fv_max: np.ndarray


def car_arrays(state: RoadState, dyn: Dynamics, prep: Prepared | None = None) -> CarArrays:
    """The per-car inputs of :func:`car_gaps_compiled` (as :func:`safelane.safety.committed.plans.car_gaps` derives
    them); ``prep``: :func:`prepare` of ``state`` when already computed."""
    p = prepare(state, dyn) if prep is None else prep
    return CarArrays(
        _f(state.x), p.half, p.ahead, p.own_lane, p.speed, _f(state.accel_max), _f(state.brake_max), p.fv_min,
        p.fv_max,
    )  # fmt: skip


def verify_plans_compiled(
    state: RoadState, dyn: Dynamics, sets: CarSets, cars: CarArrays | None = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """:func:`safelane.safety.committed.plans.verify_plans` in one kernel call (the same bits); ``cars``: the
    state's :func:`car_arrays` when already computed."""
    available, verify = plan_actions(state, dyn)
    lanes = [action_lanes(state, dyn, a) if available[a] else [] for a in range(N_ACTIONS)]
    arrays = dynamics_arrays(dyn)
    cars = car_arrays(state, dyn) if cars is None else cars
    flat = [lane for per_action in lanes for lane in per_action]
    return plans_kernel(
        available, np.array([lane for lane, _ in flat], dtype=np.int64),
        np.array([until for _, until in flat], dtype=float), np.array([len(x) for x in lanes], dtype=np.int64),
        arrays.onsets, action_targets(state, dyn), float(state.ego_x), float(state.ego_speed), arrays.target_speeds,
        arrays.powers, dyn.frames_per_decision, dyn.horizon_decisions, float(dyn.frame_dt),
        float(dyn.ego_kp), sets.x_lo, sets.x_hi, sets.entry, np.asarray(sets.now, dtype=np.bool_),
        int(state.ego_lane), int(state.ego_target_lane), verify, *cars, arrays.times, float(dyn.follower_reaction),
    )  # fmt: skip


def car_gaps_compiled(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, onset: np.ndarray, lanes: Lanes,
    until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    held: tuple[int, ...] | None = None, cars: CarArrays | None = None,
) -> np.ndarray:  # fmt: skip
    """:func:`safelane.safety.committed.plans.car_gaps`, compiled (the same bits); ``cars``: :func:`car_arrays` of
    ``state`` when already computed."""
    cars = car_arrays(state, dyn) if cars is None else cars
    t = dynamics_arrays(dyn).times
    n = state.n
    carried_lane, carried_high = carried_arrays(carried_followers or {}, n, t.size)
    lane_ids = np.array([lane for lane, _ in lanes], dtype=np.int64)
    lane_until = np.array([until for _, until in lanes], dtype=float)
    return car_gaps_kernel(
        sets.x_lo, sets.x_hi, sets.entry, np.asarray(sets.now, dtype=np.bool_), np.ascontiguousarray(ego_x),
        _f(onset), lane_ids, lane_until, *_held_pair(state, held),
        t.size - 1 if until_frame is None else int(until_frame), carried_lane, carried_high, *cars, t,
        float(dyn.follower_reaction), np.arange(n, dtype=np.int64), False, np.empty((0, 0)), np.empty((0, 0)), -np.inf,
    )  # fmt: skip


def carried_arrays(carried_followers: dict[int, tuple[int, np.ndarray]], n: int, frames: int
                   ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
    """(lanes bitmask (n,), highest positions (n or 0, frames)) of the follower bounds ``carried_followers``
    ({row: (lanes bitmask, highest position [m] per frame)}) as :func:`car_gaps_kernel` reads them."""
    carried_lane = np.zeros(n, dtype=np.int64)
    carried_high = np.empty((n if carried_followers else 0, frames))
    for row, (lanes, high) in carried_followers.items():
        carried_lane[row], carried_high[row] = lanes, high
    return carried_lane, carried_high


def follower_bound_compiled(state: RoadState, i: int, react: np.ndarray, t: np.ndarray) -> np.ndarray:
    """:func:`safelane.safety.committed.plans.follower_bound`, compiled (the same bits)."""
    speed = path_speed(state)[i : i + 1]
    v_min, v_max = speed_bounds(speed, state.target_speed[i : i + 1], np.isfinite(state.linear_speed_gain[i : i + 1]))
    return follower_kernel(float(state.x[i]), float(speed[0]), float(state.accel_max[i]), float(state.brake_max[i]),
                           float(v_min[0]), float(v_max[0]), _f(react), t)  # fmt: skip


def follower_bounds_compiled(state: RoadState, rows: np.ndarray, react: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(rows, frames) [m] :func:`follower_bound_compiled` of each car of ``rows`` for one plan (``react``: (1,)) in
    one kernel call, the speeds and their bounds computed over every car at once (elementwise: the same bits)."""
    speed = path_speed(state)
    v_min, v_max = speed_bounds(speed, state.target_speed, np.isfinite(state.linear_speed_gain))
    return followers_kernel(_f(state.x), _f(speed), _f(state.accel_max), _f(state.brake_max), _f(v_min), _f(v_max),
                            np.asarray(rows, dtype=np.int64), float(react[0]), t)  # fmt: skip


def _held_pair(state: RoadState, held: tuple[int, ...] | None) -> tuple[int, int]:
    """The (at most two) lanes the ego holds, as the kernel takes them (:func:`held_lanes`)."""
    lanes = held_lanes(state, held)
    if len(lanes) > 2:
        raise ValueError(f"held: at most two lanes (the ego's lane and its target lane), got {lanes}")
    return lanes[0], lanes[-1]


def _f(a: np.ndarray | float) -> np.ndarray:
    """``a`` as a contiguous float64 array (the kernels' one signature)."""
    return np.ascontiguousarray(a, dtype=np.float64)


def carry_compiled(
    state: RoadState, dyn: Dynamics, sets: CarSets, carried: CarSets, vehicle: np.ndarray, unbraked: np.ndarray,
    occupied: np.ndarray,
) -> tuple[CarSets, np.ndarray, np.ndarray, int]:  # fmt: skip
    """The fresh ``sets`` against those ``carried`` from the last decision (not yet shifted), compiled (the same
    bits as the reference's ``carried.shifted``, ``escaped_cars(…) | unbraked``, ``sets.intersect(…, ~escaped)``,
    ``rolling_back`` and the count of cars with a carried set): (the sets intersected, escaped, rolled back,
    checked). ``occupied``: ``occupied_lanes`` of ``state``."""
    rows = rows_in(carried.vehicle, vehicle)
    x_lo, x_hi, v_lo, v_hi, entry, escaped, rolled, checked = carry_kernel(
        sets.x_lo, sets.x_hi, sets.v_lo, sets.v_hi, sets.entry, carried.x_lo, carried.x_hi, carried.v_lo,
        carried.v_hi, carried.entry, rows, int(dyn.frames_per_decision), float(dyn.decision_period), _f(state.x),
        _f(path_speed(state)), np.asarray(occupied, dtype=np.bool_), np.asarray(unbraked, dtype=np.bool_),
        float(ESCAPE_TOLERANCE),
    )  # fmt: skip
    return CarSets(sets.vehicle, x_lo, x_hi, v_lo, v_hi, entry, sets.now), escaped, rolled, int(checked)
