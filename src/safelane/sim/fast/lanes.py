"""The straight road's lanes on arrays: ``RoadNetwork.get_closest_lane_index``, ``on_lane``,
``is_reachable_from`` and ``Road.neighbour_vehicles`` (a per-lane index searched by bisection, and the
literal scan it reproduces).

The road is ``RoadNetwork.straight_road_network``: lane ``i`` runs from ``(0, i·w)`` to ``(L, i·w)``
with direction exactly ``(1, 0)``, so highway-env's ``local_coordinates`` are exactly ``(x, y - i·w)``
and every lane's heading is ``0.0``. The arrays' layout is :mod:`safelane.sim.fast.layout`.
"""

from __future__ import annotations

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.sim.fast import layout, numerics
from safelane.sim.fast.layout import COSH, P_LANE_LENGTH, P_LANE_WIDTH, P_VEHICLE_LENGTH_LANE, SINH, H, X, Y
from safelane.sim.fast.numerics import cos, sin, wrap_to_pi

# These kernels compile in the numerics and read the layout as frozen globals: numba's cache watches this file only.
drop_stale_kernel_cache(__file__, (layout.__file__, numerics.__file__))


@njit(cache=True, error_model="numpy", inline="always")
def closest_lane(x, y, heading, n_lanes, P):
    """RoadNetwork.get_closest_lane_index: argmin of StraightLane.distance_with_heading (first minimum)."""
    length = P[P_LANE_LENGTH]
    w = P[P_LANE_WIDTH]
    best = 0
    best_d = 0.0
    angle = abs(wrap_to_pi(heading - 0.0))
    for i in range(n_lanes):
        s = x
        r = y - i * w
        a = s - length
        if not (a > 0.0):
            a = 0.0
        b = 0.0 - s
        if not (b > 0.0):
            b = 0.0
        d = abs(r) + a + b + 1.0 * angle
        if i == 0 or d < best_d:
            best_d = d
            best = i
    return best


@njit(cache=True, error_model="numpy", inline="always")
def on_lane(x, y, lane, margin, P):
    """``StraightLane.on_lane`` of lane ``lane`` at (x, y) [m] with a lateral ``margin`` [m]."""
    lat = y - lane * P[P_LANE_WIDTH]
    return (abs(lat) <= P[P_LANE_WIDTH] / 2 + margin) and (
        -P[P_VEHICLE_LENGTH_LANE] <= x < P[P_LANE_LENGTH] + P[P_VEHICLE_LENGTH_LANE]
    )


@njit(cache=True, error_model="numpy", inline="always")
def is_reachable(x, y, lane, P):
    """``StraightLane.is_reachable_from`` (x, y) [m]: within two lane widths of lane ``lane``, on its length."""
    lat = y - lane * P[P_LANE_WIDTH]
    return (abs(lat) <= 2 * P[P_LANE_WIDTH]) and (0 <= x < P[P_LANE_LENGTH] + P[P_VEHICLE_LENGTH_LANE])


@njit(cache=True, error_model="numpy")
def neighbours_scan(F, n, j, lane, P):
    """Road.neighbour_vehicles(vehicle j, lane), literally: (front, rear) indices, -1 for none.

    Ties: the last of equal leaders (``s_v <= s_front``), the first of equal followers (``s_v > s_rear``).
    (Reference implementation; the kernels use the equivalent :func:`neighbours` on the lane index.)
    """
    s = F[j, X]
    front = -1
    rear = -1
    s_front = 0.0
    s_rear = 0.0
    for k in range(n):
        if k == j:
            continue
        s_v = F[k, X]
        if not on_lane(s_v, F[k, Y], lane, 1.0, P):
            continue
        if s <= s_v and (front < 0 or s_v <= s_front):
            s_front = s_v
            front = k
        if s_v < s and (rear < 0 or s_v > s_rear):
            s_rear = s_v
            rear = k
    return front, rear


@njit(cache=True, error_model="numpy")
def build_lane_index(F, n_lanes, P, members, mx, cnt, order=None):
    """Per lane, the vehicles ``on_lane(margin=1)`` sorted by (x, index): ``members[L, :cnt[L]]``, x in ``mx``.

    Also refreshes the COSH / SINH columns. Built once per ``Road.act`` phase (no vehicle moves during it), it answers
    ``Road.neighbour_vehicles`` by binary search with the same result and tie rules as the scan.
    """
    n = F.shape[0]
    if order is None:  # else: the stable x order of the current positions, from the last collisions()
        order = np.argsort(F[:, X], kind="mergesort")  # stable: equal x stay in index order
    for L in range(n_lanes):
        cnt[L] = 0
    for r in range(n):
        k = order[r]
        x = F[k, X]
        y = F[k, Y]
        F[k, COSH] = cos(F[k, H])
        F[k, SINH] = sin(F[k, H])
        for L in range(n_lanes):
            if on_lane(x, y, L, 1.0, P):
                c = cnt[L]
                members[L, c] = k
                mx[L, c] = x
                cnt[L] = c + 1


@njit(cache=True, error_model="numpy", inline="always")
def neighbours(F, j, lane, members, mx, cnt):
    """Road.neighbour_vehicles(vehicle j, lane) from the lane index: (front, rear), -1 for none.

    front: the smallest x >= x_j among the lane's vehicles other than j, the last (highest index) of
    equal ones; rear: the largest x < x_j, the first (lowest index) of equal ones.
    """
    s = F[j, X]
    c = cnt[lane]
    lo = 0
    hi = c
    while lo < hi:  # first position with mx >= s
        mid = (lo + hi) // 2
        if mx[lane, mid] < s:
            lo = mid + 1
        else:
            hi = mid
    p = lo
    front = -1
    q = p
    while q < c and members[lane, q] == j:
        q += 1
    if q < c:
        xm = mx[lane, q]
        while q < c and mx[lane, q] == xm:
            if members[lane, q] != j:
                front = members[lane, q]
            q += 1
    rear = -1
    if p > 0:
        q = p - 1
        xr = mx[lane, q]
        while q >= 0 and mx[lane, q] == xr:
            rear = members[lane, q]
            q -= 1
    return front, rear
