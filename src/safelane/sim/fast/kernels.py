"""Numba kernels: one whole decision (``frames`` physics frames) of highway-env's straight highway.

Every function mirrors one highway-env method, operation by operation and in the same order, so that
the IEEE-754 arithmetic (no fastmath) gives the same bits as highway-env's numpy scalars:

* ``Road.act``   -> :func:`_act_ego` / :func:`act_idm` for every vehicle, in ``road.vehicles`` order
  (vehicle ``k`` sees the target lanes the vehicles before it chose in the same pass);
* ``Road.step``  -> :func:`step_vehicle` for every vehicle, then the pairwise collision checks
  (:func:`_handle_collisions`, ``i < j``, skipped when neither vehicle checks collisions).

The road is ``RoadNetwork.straight_road_network``: lane ``i`` runs from ``(0, i·w)`` to ``(L, i·w)``
with direction exactly ``(1, 0)``, so highway-env's ``local_coordinates`` are exactly
``(x, y - i·w)`` and every lane's heading is ``0.0``.

Every per-vehicle helper is inlined at numba's IR level (``inline="always"``) into the two per-frame loops
:func:`act_traffic` and :func:`step_traffic`: numba compiles each ``@njit`` function on its own and LLVM does not
inline across them, so without it every vehicle paid a dozen calls per frame (measured: the whole decision 0.65x
the time, identical outputs; the price is a one-off compilation of about 45 s, cached on disk). The two loops
themselves are called, not inlined, once per frame, so that the discrete and the continuous decision kernels
share their compiled code (the continuous kernel compiles in 14 s instead of 50 s, no measurable cost per
decision). ``error_model="numpy"``: a division
by zero gives IEEE's inf / nan, as highway-env's numpy scalars do, instead of raising.

The state arrays' layout is :mod:`safelane.sim.fast.layout`, the scalar numerics (trigonometry exact at
``±0``, the random draws) :mod:`safelane.sim.fast.numerics`, the lanes and the neighbour search
:mod:`safelane.sim.fast.lanes`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.sim.fast import lanes, layout, numerics
from safelane.sim.fast.lanes import build_lane_index, closest_lane, is_reachable, neighbours
from safelane.sim.fast.layout import (
    ACC,
    AP0,
    AP1,
    AP2,
    CHECK,
    CMAX,
    CMIN,
    COSH,
    CRASHED,
    D_AR,
    D_CMAX,
    D_CMIN,
    D_DELAY,
    D_DHI,
    D_DLO,
    D_DW,
    D_GAIN,
    D_LIN,
    D_MBI,
    D_POL,
    D_SR,
    D_TW,
    DELTA,
    DTYPE,
    DW,
    ELC,
    FASTER,
    GAIN,
    HASIMP,
    IDM,
    IMPX,
    IMPY,
    LANE,
    LANE_LEFT,
    LANE_RIGHT,
    LIN,
    MBI,
    P_ACC_MAX,
    P_DIAGONAL,
    P_KP_A,
    P_KP_HEADING,
    P_KP_LATERAL,
    P_LANE_CHANGE_DELAY,
    P_LANE_WIDTH,
    P_LENGTH,
    P_MAX_SPEED,
    P_MAX_STEERING,
    P_MIN_SPEED,
    P_SPEED_LIMIT,
    P_SQUARE,
    P_WIDTH,
    POL,
    SINH,
    SLOWER,
    SP0,
    SP1,
    STEER,
    TIMER,
    TLANE,
    TSPD,
    TW,
    H,
    V,
    X,
    Y,
)
from safelane.sim.fast.numerics import asin, atan, clip, cos, integers, not_zero, sin, tan, uniform, wrap_to_pi

# These kernels compile in the lanes' and the numerics' and read the layout as frozen globals: numba's cache
# watches this file only.
drop_stale_kernel_cache(__file__, (layout.__file__, numerics.__file__, lanes.__file__))


@njit(cache=True, error_model="numpy", inline="always")
def _desired_gap(F, c, j, k, P):
    """``c.desired_gap(ego_vehicle=j, front_vehicle=k)``, projected (c's DISTANCE_WANTED, TIME_WANTED, comfort
    accelerations)."""
    d0 = F[c, DW]
    tau = F[c, TW]
    ab = -F[c, CMAX] * F[c, CMIN]
    cj = F[j, COSH]
    sj = F[j, SINH]
    ck = F[k, COSH]
    sk = F[k, SINH]
    vjx = F[j, V] * cj
    vjy = F[j, V] * sj
    vkx = F[k, V] * ck
    vky = F[k, V] * sk
    dv = (vjx - vkx) * cj + (vjy - vky) * sj
    return d0 + F[j, V] * tau + F[j, V] * dv / (2 * math.sqrt(ab))


@njit(cache=True, error_model="numpy", inline="always")
def _free_road(F, j, delta, acc, P):
    """IDM's free-road term ``acc * (1 - (v / v0)**delta)`` of vehicle j with exponent delta and comfort
    acceleration ``acc`` [m/s²] (the caller's COMFORT_ACC_MAX)."""
    tgt = clip(F[j, TSPD], 0.0, P[P_SPEED_LIMIT])
    sp = F[j, V]
    if not (sp > 0.0):
        sp = 0.0
    return acc * (1 - math.pow(sp / abs(not_zero(tgt)), delta))


@njit(cache=True, error_model="numpy", inline="always")
def _linear_acceleration(F, c, j, k, P):
    """``LinearVehicle.acceleration`` of caller c for ego_vehicle j (>= 0), front k: params · features."""
    vt = F[j, TSPD] - F[j, V]
    sp = F[j, V]
    m = sp if sp >= 0.0 else 0.0
    d_safe = F[c, DW] + m * F[c, TW]
    dv = 0.0
    dp = 0.0
    if k >= 0:
        d = F[k, X] - F[j, X]
        a = F[k, V] - F[j, V]
        dv = 0.0 if a > 0 else a  # min(a, 0)
        b = d - d_safe
        dp = 0.0 if b > 0 else b
    return (F[c, AP0] * vt + F[c, AP1] * dv) + F[c, AP2] * dp


@njit(cache=True, error_model="numpy", inline="always")
def _acceleration(F, G, c, j, k, P):
    """``c.acceleration(ego_vehicle=j, front_vehicle=k)``: c's model and parameters; j < 0: 0."""
    if j < 0:
        return 0.0
    if G[c, LIN]:
        return _linear_acceleration(F, c, j, k, P)
    return _acceleration_free(F, c, j, k, _free_road(F, j, F[c, DELTA], F[c, CMAX], P), P)


@njit(cache=True, error_model="numpy", inline="always")
def _acceleration_free(F, c, j, k, free, P):
    """IDM acceleration of caller c for j given j's free-road term with c's DELTA and COMFORT_ACC_MAX."""
    acc = free
    if k >= 0:
        d = F[k, X] - F[j, X]
        acc -= F[c, CMAX] * math.pow(_desired_gap(F, c, j, k, P) / not_zero(d), 2.0)
    return acc


@njit(cache=True, error_model="numpy", inline="always")
def _own_acceleration(F, G, j, k, free_j, P):
    """``j.acceleration(ego_vehicle=j, front_vehicle=k)`` (free_j: j's IDM free-road term, unused if linear)."""
    if G[j, LIN]:
        return _linear_acceleration(F, j, j, k, P)
    return _acceleration_free(F, j, j, k, free_j, P)


@njit(cache=True, error_model="numpy", inline="always")
def _steering_control(F, j, target_lane, P):
    """ControlledVehicle.steering_control on a straight lane (heading 0)."""
    lat = F[j, Y] - target_lane * P[P_LANE_WIDTH]
    sp = F[j, V]
    lane_future_heading = 0.0
    lateral_speed_command = -P[P_KP_LATERAL] * lat
    heading_command = asin(clip(lateral_speed_command / not_zero(sp), -1.0, 1.0))
    heading_ref = lane_future_heading + clip(heading_command, -np.pi / 4, np.pi / 4)
    heading_rate_command = P[P_KP_HEADING] * wrap_to_pi(heading_ref - F[j, H])
    slip_angle = asin(clip(P[P_LENGTH] / 2 / not_zero(sp) * heading_rate_command, -1.0, 1.0))
    steering_angle = atan(2 * tan(slip_angle))
    return clip(steering_angle, -P[P_MAX_STEERING], P[P_MAX_STEERING])


@njit(cache=True, error_model="numpy", inline="always")
def _linear_steering(F, j, target_lane, P):
    """LinearVehicle.steering_control: STEERING_PARAMETERS · steering_features (not clipped here).

    ``not_zero(speed) ** 2`` is libm's ``pow(speed, 2.0)``, which is not always ``speed * speed`` (glibc's pow
    is within 0.52 ulp, not correctly rounded: about 1 speed in 1 200 differs by an ulp). With a literal
    2.0, LLVM rewrites ``pow(x, 2.0)`` as ``x * x``; the exponent ``P[P_SQUARE]`` is only known at run time.
    """
    lat = F[j, Y] - target_lane * P[P_LANE_WIDTH]
    nz = not_zero(F[j, V])
    f0 = wrap_to_pi(0.0 - F[j, H]) * P[P_LENGTH] / nz
    f1 = -lat * P[P_LENGTH] / math.pow(nz, P[P_SQUARE])
    return F[j, SP0] * f0 + F[j, SP1] * f1


@njit(cache=True, error_model="numpy", inline="always")
def speed_to_index(speed, ts):
    """``MDPVehicle.speed_to_index``: the index of the target speed in ``ts`` [m/s] nearest ``speed`` [m/s]."""
    m = ts.size
    x = (speed - ts[0]) / (ts[m - 1] - ts[0])
    r = np.rint(x * (m - 1))
    return int(clip(r, 0.0, float(m - 1)))


@njit(cache=True, error_model="numpy", inline="always")
def _act_ego(F, G, E, ts, action, n_lanes, P):
    """MDPVehicle.act(action) (action < 0: act(None)), then ControlledVehicle's controllers."""
    if action in (FASTER, SLOWER):
        si = speed_to_index(F[0, V], ts) + (1 if action == FASTER else -1)
        if si < 0:
            si = 0
        if si > ts.size - 1:
            si = ts.size - 1
        E[0] = si
        F[0, TSPD] = ts[si]
    elif action in (LANE_RIGHT, LANE_LEFT):
        cand = G[0, TLANE] + (1 if action == LANE_RIGHT else -1)
        if cand < 0:
            cand = 0
        if cand > n_lanes - 1:
            cand = n_lanes - 1
        if is_reachable(F[0, X], F[0, Y], cand, P):
            G[0, TLANE] = cand
    steer = _steering_control(F, 0, G[0, TLANE], P)
    F[0, STEER] = clip(steer, -P[P_MAX_STEERING], P[P_MAX_STEERING])
    F[0, ACC] = P[P_KP_A] * (F[0, TSPD] - F[0, V])


@njit(cache=True, error_model="numpy", inline="always")
def _free_c(F, G, c, j, P):
    """j's IDM free-road term with caller c's DELTA and COMFORT_ACC_MAX (0.0 when unused: no j, or c is linear)."""
    if j < 0 or G[c, LIN]:
        return 0.0
    return _free_road(F, j, F[c, DELTA], F[c, CMAX], P)


@njit(cache=True, error_model="numpy", inline="always")
def _acc_c(F, G, c, j, k, free, P):
    """``c.acceleration(ego_vehicle=j, front_vehicle=k)`` given ``free = _free_c(F, G, c, j, P)``."""
    if j < 0:
        return 0.0
    if G[c, LIN]:
        return _linear_acceleration(F, c, j, k, P)
    return _acceleration_free(F, c, j, k, free, P)


@njit(cache=True, error_model="numpy", inline="always")
def _change_lane_policy(F, G, n, j, n_lanes, P, members, mx, cnt, free_j):
    """IDMVehicle.change_lane_policy, with ``mobil(lane)`` inlined.

    The accelerations are pure functions of the (fixed during act) positions and speeds, so the
    old-lane terms, the same for both candidate lanes, are computed once (when first needed), and each
    follower's free-road term once for its two accelerations: the same values highway-env computes.
    """
    if G[j, LANE] != G[j, TLANE]:
        tl = G[j, TLANE]
        for k in range(n):
            if k != j and G[k, LANE] != tl and G[k, TLANE] == tl:
                d = F[k, X] - F[j, X]
                d_star = _desired_gap(F, j, j, k, P)
                if 0 < d < d_star:
                    G[j, TLANE] = G[j, LANE]
                    break
        return
    if not (P[P_LANE_CHANGE_DELAY] < F[j, TIMER]):
        return
    F[j, TIMER] = 0.0
    lane = G[j, LANE]
    old_done = False
    old_preceding = -1
    self_a = 0.0
    old_following_a = 0.0
    old_following_pred_a = 0.0
    for side in range(2):
        cand = lane - 1 if side == 0 else lane + 1
        if cand < 0 or cand > n_lanes - 1:
            continue
        if not is_reachable(F[j, X], F[j, Y], cand, P):
            continue
        if abs(F[j, V]) < 1:
            continue
        # --- mobil(cand)
        new_preceding, new_following = neighbours(F, j, cand, members, mx, cnt)
        free_nf = _free_c(F, G, j, new_following, P)
        new_following_a = _acc_c(F, G, j, new_following, new_preceding, free_nf, P)
        new_following_pred_a = _acc_c(F, G, j, new_following, j, free_nf, P)
        if new_following_pred_a < -F[j, MBI]:
            continue
        if not old_done:
            old_preceding, old_following = neighbours(F, j, lane, members, mx, cnt)
            self_a = _own_acceleration(F, G, j, old_preceding, free_j, P)
            free_of = _free_c(F, G, j, old_following, P)
            old_following_a = _acc_c(F, G, j, old_following, j, free_of, P)
            old_following_pred_a = _acc_c(F, G, j, old_following, old_preceding, free_of, P)
            old_done = True
        self_pred_a = _own_acceleration(F, G, j, new_preceding, free_j, P)
        jerk = (
            self_pred_a
            - self_a
            + F[j, POL] * (new_following_pred_a - new_following_a + old_following_pred_a - old_following_a)
        )
        if not jerk < F[j, GAIN]:
            G[j, TLANE] = cand


@njit(cache=True, error_model="numpy", inline="always")
def act_idm(F, G, n, j, n_lanes, P, members, mx, cnt):
    """IDMVehicle.act() (LinearVehicle's: the same with its acceleration and steering models)."""
    if G[j, CRASHED]:
        return
    # j's IDM free-road term: speed and target speed do not change during act
    free_j = 0.0 if G[j, LIN] else _free_road(F, j, F[j, DELTA], F[j, CMAX], P)
    if G[j, ELC]:
        _change_lane_policy(F, G, n, j, n_lanes, P, members, mx, cnt, free_j)
    lin = G[j, LIN]
    steer = _linear_steering(F, j, G[j, TLANE], P) if lin else _steering_control(F, j, G[j, TLANE], P)
    F[j, STEER] = clip(steer, -P[P_MAX_STEERING], P[P_MAX_STEERING])
    front, _rear = neighbours(F, j, G[j, LANE], members, mx, cnt)
    acc = _own_acceleration(F, G, j, front, free_j, P)
    if G[j, LANE] != G[j, TLANE]:
        front2, _rear2 = neighbours(F, j, G[j, TLANE], members, mx, cnt)
        acc2 = _own_acceleration(F, G, j, front2, free_j, P)
        if acc2 < acc:
            acc = acc2
    F[j, ACC] = clip(acc, -P[P_ACC_MAX], P[P_ACC_MAX])


@njit(cache=True, error_model="numpy", inline="always")
def step_vehicle(F, G, j, dt, n_lanes, P):
    """(IDMVehicle timer +) Vehicle.step(dt): clip_actions, bicycle model, impact, lane update."""
    if G[j, IDM]:
        F[j, TIMER] += dt
    # clip_actions
    if G[j, CRASHED]:
        F[j, STEER] = 0.0
        F[j, ACC] = -1.0 * F[j, V]
    sp = F[j, V]
    if sp > P[P_MAX_SPEED]:
        lim = 1.0 * (P[P_MAX_SPEED] - sp)
        if lim < F[j, ACC]:
            F[j, ACC] = lim
    elif sp < P[P_MIN_SPEED]:
        lim = 1.0 * (P[P_MIN_SPEED] - sp)
        if lim > F[j, ACC]:
            F[j, ACC] = lim
    delta_f = F[j, STEER]
    beta = atan(1 / 2 * tan(delta_f))
    hb = F[j, H] + beta
    vx = sp * cos(hb)
    vy = sp * sin(hb)
    F[j, X] += vx * dt
    F[j, Y] += vy * dt
    if G[j, HASIMP]:
        F[j, X] += F[j, IMPX]
        F[j, Y] += F[j, IMPY]
        G[j, CRASHED] = 1
        G[j, HASIMP] = 0
    F[j, H] += sp * sin(beta) / (P[P_LENGTH] / 2) * dt
    F[j, V] += F[j, ACC] * dt
    G[j, LANE] = closest_lane(F[j, X], F[j, Y], F[j, H], n_lanes, P)


@njit(cache=True, error_model="numpy", inline="always")
def _polygon(F, j, P, out):
    """RoadObject.polygon(): 4 corners + the first again, rotated then translated."""
    hl = P[P_LENGTH] / 2
    hw = P[P_WIDTH] / 2
    c = cos(F[j, H])
    s = sin(F[j, H])
    px0 = -hl
    py0 = -hw
    px1 = -hl
    py1 = +hw
    px2 = +hl
    py2 = +hw
    px3 = +hl
    py3 = -hw
    out[0, 0] = c * px0 + (-s) * py0 + F[j, X]
    out[0, 1] = s * px0 + c * py0 + F[j, Y]
    out[1, 0] = c * px1 + (-s) * py1 + F[j, X]
    out[1, 1] = s * px1 + c * py1 + F[j, Y]
    out[2, 0] = c * px2 + (-s) * py2 + F[j, X]
    out[2, 1] = s * px2 + c * py2 + F[j, Y]
    out[3, 0] = c * px3 + (-s) * py3 + F[j, X]
    out[3, 1] = s * px3 + c * py3 + F[j, Y]
    out[4, 0] = out[0, 0]
    out[4, 1] = out[0, 1]


@njit(cache=True, error_model="numpy", inline="always")
def _interval_distance(min_a, max_a, min_b, max_b):
    return min_b - max_a if min_a < min_b else min_a - max_b


@njit(cache=True, error_model="numpy", inline="always")
def _project(poly, nx, ny):
    mn = poly[0, 0] * nx + poly[0, 1] * ny
    mx = mn
    for p in range(1, 5):
        v = poly[p, 0] * nx + poly[p, 1] * ny
        if v < mn:
            mn = v
        if v > mx:
            mx = v
    return mn, mx


@njit(cache=True, error_model="numpy", inline="always")
def _polygons_intersecting(a, b, dax, day, dbx, dby, res):
    """utils.are_polygons_intersecting; res = (translation_x, translation_y). Returns (intersecting, will)."""
    intersecting = True
    will_intersect = True
    min_distance = np.inf
    tax = 0.0
    tay = 0.0
    done = False
    for which in range(2):
        poly = a if which == 0 else b
        for e in range(4):
            nx = -poly[e + 1, 1] + poly[e, 1]
            ny = poly[e + 1, 0] - poly[e, 0]
            nrm = math.sqrt(nx * nx + ny * ny)
            nx /= nrm
            ny /= nrm
            min_a, max_a = _project(a, nx, ny)
            min_b, max_b = _project(b, nx, ny)
            if _interval_distance(min_a, max_a, min_b, max_b) > 0:
                intersecting = False
            velocity_projection = nx * (dax - dbx) + ny * (day - dby)
            if velocity_projection < 0:
                min_a += velocity_projection
            else:
                max_a += velocity_projection
            distance = _interval_distance(min_a, max_a, min_b, max_b)
            if distance > 0:
                will_intersect = False
            if not intersecting and not will_intersect:
                done = True
                break
            if abs(distance) < min_distance:
                min_distance = abs(distance)
                # center difference: mean of the 4 corners (numpy adds rows in order), then / 4
                cax = ((a[0, 0] + a[1, 0]) + a[2, 0]) + a[3, 0]
                cay = ((a[0, 1] + a[1, 1]) + a[2, 1]) + a[3, 1]
                cbx = ((b[0, 0] + b[1, 0]) + b[2, 0]) + b[3, 0]
                cby = ((b[0, 1] + b[1, 1]) + b[2, 1]) + b[3, 1]
                dx = cax / 4 - cbx / 4
                dy = cay / 4 - cby / 4
                if dx * nx + dy * ny > 0:
                    tax = nx
                    tay = ny
                else:
                    tax = -nx
                    tay = -ny
        if done:
            break
    if will_intersect:
        res[0] = min_distance * tax
        res[1] = min_distance * tay
    return intersecting, will_intersect


@njit(cache=True, error_model="numpy", inline="always")
def _handle_collisions(F, G, i, j, dt, P, pa, pb, res):
    """RoadObject.handle_collisions(self=i, other=j, dt) between two solid vehicles."""
    if not (G[i, CHECK] or G[j, CHECK]):
        return
    dx = F[j, X] - F[i, X]
    dy = F[j, Y] - F[i, Y]
    if math.sqrt(dx * dx + dy * dy) > (P[P_DIAGONAL] + P[P_DIAGONAL]) / 2 + F[i, V] * dt:
        return
    _polygon(F, i, P, pa)
    _polygon(F, j, P, pb)
    dax = F[i, V] * cos(F[i, H]) * dt
    day = F[i, V] * sin(F[i, H]) * dt
    dbx = F[j, V] * cos(F[j, H]) * dt
    dby = F[j, V] * sin(F[j, H]) * dt
    intersecting, will = _polygons_intersecting(pa, pb, dax, day, dbx, dby, res)
    if will:
        F[i, IMPX] = res[0] / 2
        F[i, IMPY] = res[1] / 2
        G[i, HASIMP] = 1
        F[j, IMPX] = -res[0] / 2
        F[j, IMPY] = -res[1] / 2
        G[j, HASIMP] = 1
    if intersecting:
        G[i, CRASHED] = 1
        G[j, CRASHED] = 1


@njit(cache=True, error_model="numpy", inline="always")
def collisions(F, G, dt, P, pa, pb, res, reach, cand, order):
    """Road.step's pairwise checks: ``vehicles[i].handle_collisions(vehicles[j])`` for i < j, in that order.

    Pairs whose |dx| exceeds ``reach`` (the pre-check's radius + (MAX_SPEED + 1)·dt + 1 m) cannot pass
    highway-env's distance pre-check, so only the pairs near in x (found from the x order) are examined,
    still for i ascending and, for each i, j ascending; a vehicle faster than MAX_SPEED + 1 checks all.
    """
    n = F.shape[0]
    order[:] = np.argsort(F[:, X], kind="mergesort")
    rank = np.empty(n, dtype=np.int64)
    last_checker = -1
    for r in range(n):
        rank[order[r]] = r
        if G[r, CHECK]:
            last_checker = r
    for i in range(n):
        ci = G[i, CHECK]
        if not ci and i >= last_checker:
            continue  # no vehicle j > i checks collisions, and i does not either
        xi = F[i, X]
        if abs(F[i, V]) > P[P_MAX_SPEED] + 1.0:
            for j in range(i + 1, n):
                _handle_collisions(F, G, i, j, dt, P, pa, pb, res)
            continue
        m = 0
        r = rank[i] - 1
        while r >= 0 and xi - F[order[r], X] <= reach:
            j = order[r]
            if j > i and (ci or G[j, CHECK]):
                cand[m] = j
                m += 1
            r -= 1
        r = rank[i] + 1
        while r < n and F[order[r], X] - xi <= reach:
            j = order[r]
            if j > i and (ci or G[j, CHECK]):
                cand[m] = j
                m += 1
            r += 1
        # ascending j (insertion sort: a handful of candidates)
        for a in range(1, m):
            v = cand[a]
            b = a - 1
            while b >= 0 and cand[b] > v:
                cand[b + 1] = cand[b]
                b -= 1
            cand[b + 1] = v
        for a in range(m):
            _handle_collisions(F, G, i, cand[a], dt, P, pa, pb, res)


@njit(cache=True, error_model="numpy")
def act_traffic(F, G, first, n_lanes, P, members, mx, cnt):
    """``Road.act`` of the IDM / linear drivers in rows ``first``.. in row order (each sees the target lanes the
    rows before it chose).

    Not inlined into the simulate kernels: it holds every inlined copy of MOBIL's accelerations, and one compiled
    loop that both the discrete and the continuous kernel call compiles (and caches) once; a call per frame costs
    nothing measurable beside the vehicles' work.
    """
    n = F.shape[0]
    for k in range(first, n):
        act_idm(F, G, n, k, n_lanes, P, members, mx, cnt)


@njit(cache=True, error_model="numpy")
def step_traffic(F, G, first, dt, n_lanes, P, pa, pb, res, reach, cand, order):
    """``Road.step`` of rows ``first``..: each vehicle's ``step(dt)``, then every pair's collision check (all
    rows); not inlined, for the reason :func:`act_traffic` gives. Both kernels pass ``first`` = 1 (the ego's
    step inlined before it): numba types a literal argument as its value, and a second value would compile
    this loop a second time."""
    n = F.shape[0]
    for k in range(first, n):
        step_vehicle(F, G, k, dt, n_lanes, P)
    collisions(F, G, dt, P, pa, pb, res, reach, cand, order)


@njit(cache=True, error_model="numpy")
def simulate(F, G, E, ts, P, action, frames, dt, n_lanes, before, after, rec):
    """AbstractEnv._simulate(action): ``frames`` x (act [+ the meta-action at frame 0], step, collisions).

    ``rec[0]`` is set to 1 (and ``before``/``after`` filled with the positions at the start and end of
    that frame) in the frame in which the ego first becomes crashed, if ``rec[0]`` was 0.
    """
    n = F.shape[0]
    pa = np.empty((5, 2))
    pb = np.empty((5, 2))
    res = np.zeros(2)
    members = np.empty((n_lanes, n), dtype=np.int64)
    mx = np.empty((n_lanes, n))
    cnt = np.zeros(n_lanes, dtype=np.int64)
    reach = (P[P_DIAGONAL] + P[P_DIAGONAL]) / 2 + (P[P_MAX_SPEED] + 1.0) * dt + 1.0
    cand = np.empty(n, dtype=np.int64)
    order = np.empty(n, dtype=np.int64)
    for frame in range(frames):
        was_crashed = G[0, CRASHED]
        if rec[0] == 0 and not was_crashed:
            for k in range(n):
                before[k, 0] = F[k, X]
                before[k, 1] = F[k, Y]
        # Road.act (the ego's meta-action first, at the decision's first frame)
        if frame == 0:
            order[:] = np.argsort(F[:, X], kind="mergesort")
        build_lane_index(F, n_lanes, P, members, mx, cnt, order)
        _act_ego(F, G, E, ts, action if frame == 0 else -1, n_lanes, P)  # row 0, the ego, acts first
        act_traffic(F, G, 1, n_lanes, P, members, mx, cnt)
        step_vehicle(F, G, 0, dt, n_lanes, P)
        step_traffic(F, G, 1, dt, n_lanes, P, pa, pb, res, reach, cand, order)
        if rec[0] == 0 and not was_crashed and G[0, CRASHED]:
            rec[0] = 1
            for k in range(n):
                after[k, 0] = F[k, X]
                after[k, 1] = F[k, Y]


@njit(cache=True, error_model="numpy", inline="always")
def _driver_type(raws, st, cdf):
    """The next car's driver type: ``choice(cdf.size, p)`` (numpy's: one double, then the number of entries of the
    normalised cumulative ``cdf`` at or below it, ``searchsorted(side="right")``); -1 when ``cdf`` is empty (no
    mixture, no draw)."""
    if cdf.size == 0:
        return -1
    u = uniform(raws, st, 0.0, 1.0)  # Generator.random(): 0 + 1 * next_double, exactly next_double
    t = 0
    while t < cdf.size and cdf[t] <= u:
        t += 1
    return t


@njit(cache=True, error_model="numpy", inline="always")
def _place_vehicle(raws, st, k, x, y, speed, drivers, t, check_others, n_lanes, P, F, G):
    """Row ``k``: a driver of type ``t`` (row ``max(t, 0)`` of the driver table ``drivers``, see
    scene.driver_constants) created at (x, y) [m] going ``speed`` [m/s] — its constructor's fields (target speed =
    speed, the lane-change timer from its position, its class's constants) — then ``randomize_behavior()``'s draws
    (a linear driver's gains first, then DELTA in its DELTA_RANGE). Shared by :func:`spawn` and
    :func:`spawn_behind`."""
    drv = drivers[max(t, 0)]
    F[k, :] = 0.0
    G[k, :] = 0
    F[k, X] = x
    F[k, Y] = y
    F[k, V] = speed
    F[k, TSPD] = speed
    F[k, TIMER] = ((x + y) * np.pi) % drv[D_DELAY]
    F[k, TW] = drv[D_TW]
    F[k, GAIN] = drv[D_GAIN]
    F[k, CMAX] = drv[D_CMAX]
    F[k, CMIN] = drv[D_CMIN]
    F[k, DW] = drv[D_DW]
    F[k, POL] = drv[D_POL]
    F[k, MBI] = drv[D_MBI]
    if drv[D_LIN] != 0.0:
        u0 = uniform(raws, st, 0.0, 1.0)
        u1 = uniform(raws, st, 0.0, 1.0)
        u2 = uniform(raws, st, 0.0, 1.0)
        F[k, AP0] = drv[D_AR] + u0 * (drv[D_AR + 3] - drv[D_AR])
        F[k, AP1] = drv[D_AR + 1] + u1 * (drv[D_AR + 4] - drv[D_AR + 1])
        F[k, AP2] = drv[D_AR + 2] + u2 * (drv[D_AR + 5] - drv[D_AR + 2])
        v0 = uniform(raws, st, 0.0, 1.0)
        v1 = uniform(raws, st, 0.0, 1.0)
        F[k, SP0] = drv[D_SR] + v0 * (drv[D_SR + 2] - drv[D_SR])
        F[k, SP1] = drv[D_SR + 1] + v1 * (drv[D_SR + 3] - drv[D_SR + 1])
        G[k, LIN] = 1
    F[k, DELTA] = uniform(raws, st, drv[D_DLO], drv[D_DHI])
    lane = closest_lane(x, y, 0.0, n_lanes, P)
    G[k, LANE] = lane
    G[k, TLANE] = lane
    G[k, CHECK] = check_others
    G[k, ELC] = 1
    G[k, IDM] = 1
    G[k, DTYPE] = t


@njit(cache=True, error_model="numpy")
def spawn(raws, st, ego_lane, ego_spacing, spacing, lanes_factor, lo, hi, ego_delta, ego_time_wanted,
          drivers, cdf, check_others, ts, n_lanes, P, F, G, E):  # fmt: skip
    """The scene of HighwayEnv._create_vehicles (see scene.build_scene_python, its line-by-line twin).

    ``drivers``: the driver table (one row per type, scene.driver_constants); ``cdf``: the mixture's normalised
    cumulative probabilities (empty: no mixture, every car of type row 0). Each other car: its type (with a
    mixture), lane, speed, gap, then ``randomize_behavior()`` (a LinearVehicle's draws uniform(size=3),
    uniform(size=2) before DELTA). ``ego_time_wanted`` [s]: the ego row's TIME_WANTED (IDM's).

    Returns False when ``raws`` ran out (``st[0] == -1``)."""
    n = F.shape[0]
    width = P[P_LANE_WIDTH]
    lane_id = ego_lane if ego_lane >= 0 else integers(raws, st, n_lanes)
    speed = 25.0
    default_spacing = 12 + 1.0 * speed
    offset = ego_spacing * default_spacing * lanes_factor
    x0 = 3 * offset
    x0 += offset * uniform(raws, st, 0.9, 1.1)
    x = x0
    y = lane_id * width
    F[0, :] = 0.0
    G[0, :] = 0
    F[0, X] = x
    F[0, Y] = y
    F[0, V] = speed
    lane = closest_lane(x, y, 0.0, n_lanes, P)
    G[0, LANE] = lane
    G[0, TLANE] = lane
    G[0, CHECK] = 1
    G[0, DTYPE] = -1
    si = speed_to_index(speed, ts)
    E[0] = si
    F[0, TSPD] = ts[si]
    F[0, DELTA] = ego_delta
    F[0, TW] = ego_time_wanted
    x_max = x
    for k in range(1, n):
        t = _driver_type(raws, st, cdf)
        lane_id = integers(raws, st, n_lanes)
        speed = uniform(raws, st, lo, hi)
        default_spacing = 12 + 1.0 * speed
        offset = spacing * default_spacing * lanes_factor
        x0 = x_max
        x0 += offset * uniform(raws, st, 0.9, 1.1)
        x = x0
        y = lane_id * width
        _place_vehicle(raws, st, k, x, y, speed, drivers, t, check_others, n_lanes, P, F, G)
        if x > x_max:
            x_max = x
    return st[0] >= 0


@njit(cache=True, error_model="numpy")
def spawn_behind(raws, st, first, count, x, lo, hi, lanes_factor, density, drivers, cdf, check_others,
                 n_lanes, P, F, G):  # fmt: skip
    """safelane's ``TrafficLayout._spawn_behind``: ``count`` vehicles behind the ego at x [m], in rows
    ``first`` .. ``first + count - 1`` (see scene.spawn_behind_python, its line-by-line twin).

    Each: its type (with a mixture: ``drivers`` and ``cdf`` as in :func:`spawn`), lane ``integers(n_lanes)``,
    speed ``uniform(lo, hi)`` [m/s], gap ``(12 + speed) * lanes_factor / density * uniform(0.9, 1.1)`` [m] back
    from the previous one, then ``randomize_behavior()``. Returns False when ``raws`` ran out (``st[0] == -1``)."""
    width = P[P_LANE_WIDTH]
    for k in range(first, first + count):
        t = _driver_type(raws, st, cdf)
        lane_id = integers(raws, st, n_lanes)
        speed = uniform(raws, st, lo, hi)
        offset = (12 + speed) * lanes_factor / density
        x -= offset * uniform(raws, st, 0.9, 1.1)
        y = lane_id * width
        _place_vehicle(raws, st, k, x, y, speed, drivers, t, check_others, n_lanes, P, F, G)
    return st[0] >= 0
