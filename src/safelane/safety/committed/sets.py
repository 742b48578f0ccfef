"""The reachable sets of the committed shield (:mod:`safelane.safety.committed`): every other car's positions and
speeds per frame of the horizon, and the lanes it may occupy and when, drawn from the observable state only.

Pure maths (no simulator). The bounds are those of highway-env's driver models (IDM and the linear models, their
constants read from the state) and of its kinematics, which moves a car along ``heading + β`` (β: the slip angle)
at its *speed along the path* — the quantity whose rate the driver model bounds. Design and nesting argument:
``docs/research/committed-plans.md``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from safelane.safety.world import LATERAL_MOTION_THRESHOLD, Dynamics, RoadState

MAX_SPEED = 40.0
"""[m/s] highway-env's ``Vehicle.MAX_SPEED``: the speed bound of a car whose set-point is unknown."""
ESCAPE_TOLERANCE = 1e-6
"""[m, m/s, s] A car counts as outside its set only beyond this (rounding of the closed forms)."""
LANE_CHANGES_BEGUN = 1
"""Lane changes a car may begin within the horizon besides the one under way: the model's bound, as the robust
rule's ``turning_leaders`` counts them. highway-env lets a driver begin one per ``LANE_CHANGE_DELAY`` (1 s), a
zigzag no set of this size contains; counting them all (one allowance per second) left 19 % of the decisions of
four gate cells without a verified plan, against none (docs/research/committed-plans.md). A car beginning a
second change is outside the set drawn for it, and named."""
TURN_HEADING = math.pi / 8
"""[rad] Half the heading (π/4) highway-env's lateral controller holds a lane change to: the along-road shortfall
of one lane change is ``lane_width · tan(π/8)`` (:func:`lane_change_allowance`)."""

__all__ = [
    "ESCAPE_TOLERANCE", "LANE_CHANGES_BEGUN", "MAX_SPEED", "TURN_HEADING", "CarSets", "acceleration_law", "car_sets",
    "envelope", "escaped_cars", "fall", "lane_change_allowance", "lane_changes_allowed", "lane_crossing_time",
    "lane_entry_times", "lanes_now", "law_rise", "linear_set_point_bound", "occupied_lanes", "path_speed", "rise",
    "rolling_back", "rows_in", "shortfall", "speed_bounds",
]  # fmt: skip


def rise(v: np.ndarray, a: np.ndarray, v_max: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance [m], speed [m/s]) after ``t`` [s] accelerating at ``a`` [m/s²] from ``v`` up to ``v_max``."""
    t_top = np.maximum(v_max - v, 0.0) / np.maximum(a, 1e-9)
    tt = np.minimum(t, t_top)
    return v * tt + 0.5 * a * tt * tt + v_max * np.maximum(t - t_top, 0.0), np.minimum(v + a * t, v_max)


def fall(v: np.ndarray, b: np.ndarray, v_min: np.ndarray, t: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(distance [m], speed [m/s]) after ``t`` [s] braking at ``b`` [m/s²] from ``v`` down to ``v_min``."""
    t_low = np.maximum(v - v_min, 0.0) / np.maximum(b, 1e-9)
    tt = np.minimum(t, t_low)
    return v * tt - 0.5 * b * tt * tt + v_min * np.maximum(t - t_low, 0.0), np.maximum(v - b * t, v_min)


def _forward(v: np.ndarray, a: np.ndarray, v_max: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[m] ``∫₀ᵗ max(u(s), 0) ds`` for the speed ``u`` rising at ``a`` from ``v`` up to ``v_max``: the forward
    distance of a car whose speed along its path is at most ``u`` (its heading turns it, never backwards)."""
    t0 = np.clip(-v / np.maximum(a, 1e-9), 0.0, None)  # when the rising speed crosses 0 (0 if it starts ≥ 0)
    start = np.maximum(v, 0.0)
    d, _ = rise(start, a, np.maximum(v_max, 0.0), np.maximum(t - t0, 0.0))
    return d


def _backward(v: np.ndarray, b: np.ndarray, v_min: np.ndarray, t: np.ndarray) -> np.ndarray:
    """[m] ``∫₀ᵗ min(u(s), 0) ds`` (≤ 0) for the speed ``u`` falling at ``b`` from ``v`` down to ``v_min``."""
    t0 = np.clip(v / np.maximum(b, 1e-9), 0.0, None)  # when the falling speed crosses 0
    d, _ = fall(np.minimum(v, 0.0), b, np.minimum(v_min, 0.0), np.maximum(t - t0, 0.0))
    return d


def path_speed(state: RoadState) -> np.ndarray:
    """(cars,) [m/s] each car's signed speed along its path (highway-env's ``speed``; the state holds its
    projections ``vx = speed·cos h``, ``vy = speed·sin h``)."""
    return state.vx * np.cos(state.heading) + state.vy * np.sin(state.heading)


def speed_bounds(v: np.ndarray, target: np.ndarray, linear: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(v_min, v_max) [m/s] a car's speed along its path stays in under its driver model: ``min(v, 0)`` (the
    models are meant for v ≥ 0: a car rolling back faster than it does now is outside them, :func:`rolling_back`)
    and ``max(v, set-point)`` (IDM's free-road term is ≤ 0 above the set-point, its interaction term always ≤ 0;
    the linear law with gains ≥ 0 is at most ``k₀·(v* − v)``, :func:`linear_set_point_bound`); :data:`MAX_SPEED`
    for the cars ``linear`` (:func:`car_sets` passes the linear drivers with no such bound) and an unknown
    set-point."""
    known = np.isfinite(target)
    v_max = np.where(linear | ~known, MAX_SPEED, np.maximum(v, np.where(known, target, 0.0)))
    return np.minimum(v, 0.0), np.maximum(v_max, v)


def envelope(
    x: np.ndarray, v: np.ndarray, a: np.ndarray, b: np.ndarray, v_min: np.ndarray, v_max: np.ndarray, t: np.ndarray,
    allowance: np.ndarray | None = None,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """The longitudinal reachable set of cars at ``x`` [m] along the road with speed ``v`` [m/s] along their path,
    acceleration in ``[−b, a]`` [m/s²] and speed in ``[v_min, v_max]``: (x_lo, x_hi, v_lo, v_hi), each (cars,
    frames) at the times ``t`` [s]. Speeds: the bang-bang bounds (every admissible speed history stays between
    them). Positions: a car moves along the road at ``speed·cos(heading + β)``, so at most its forward speed
    (``x_hi``: the rising bound's forward part) and at least its speed less what turning costs; ``allowance``
    (cars, frames) [m] bounds that cost (:func:`shortfall`; default none: a car that never turns), and a car
    moving forward never loses ground (``x_lo`` ≥ its backward part)."""
    col = lambda z: np.asarray(z, dtype=float)[:, None]  # noqa: E731
    tt = t[None, :]
    _, v_hi = rise(col(v), col(a), col(v_max), tt)
    d_lo, v_lo = fall(col(v), col(b), col(v_min), tt)
    d_hi = _forward(col(v), col(a), col(v_max), tt)
    if allowance is not None:
        d_lo = np.maximum(d_lo - allowance, _backward(col(v), col(b), col(v_min), tt))
    return col(x) + d_lo, col(x) + d_hi, v_lo, v_hi


def linear_set_point_bound(state: RoadState) -> np.ndarray:
    """(cars,) bool: linear-model drivers whose speed stays at most ``max(v, set-point)``: their acceleration
    ``k₀·(v* − v) + k₁·min(Δv, 0) + k₂·min(d − d_safe, 0)`` (``LinearVehicle.acceleration``) with gains ≥ 0 is at
    most ``k₀·(v* − v)``; set-point known."""
    gains = np.stack([state.linear_speed_gain, state.linear_speed_difference_gain, state.linear_distance_gain])
    return np.isfinite(gains).all(axis=0) & (gains >= 0.0).all(axis=0) & np.isfinite(state.target_speed)


def acceleration_law(state: RoadState, dt: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Each car's acceleration law toward its set-point, for :func:`law_rise`: (rows it applies to, gain k [1/s]
    of the linear law ``k·(v* − v)``, IDM's comfort acceleration [m/s²] and exponent δ of ``acc·(1 − (v/v*)^δ)``;
    the other terms of both models are ≤ 0). A law applies where the set-point is known, the car not crashed,
    and one frame of it is monotone in the speed (``1 − dt·∂acc/∂v ≥ 0``: a slower car stays slower)."""
    target = state.target_speed
    linear = linear_set_point_bound(state)
    idm = ~np.isfinite(state.linear_speed_gain) & np.isfinite(target) & (target > 0.0)
    monotone = np.where(linear, dt * np.nan_to_num(state.linear_speed_gain) <= 1.0,
                        dt * state.idm_comfort_acc * state.idm_delta <= np.where(idm, target, 0.0))  # fmt: skip
    rows = (linear | idm) & monotone & ~np.asarray(state.crashed, dtype=bool)
    return rows, np.where(linear, state.linear_speed_gain, np.nan), state.idm_comfort_acc, state.idm_delta


def law_rise(state: RoadState, v: np.ndarray, frames: int, dt: float) -> tuple[np.ndarray, np.ndarray]:
    """(speed [m/s], forward distance [m]) bounds per frame (cars, frames + 1) of cars following their driver
    model's acceleration law (:func:`acceleration_law`; elsewhere inf): highway-env's explicit Euler frame by frame
    (the position moves by the speed before the frame's update), the acceleration at most ``min(a, max(law, 0))``.
    Each frame's map is monotone in the speed, so a slower start stays below: the bound nests in time."""
    rows, k, acc, delta = acceleration_law(state, dt)
    target, a = state.target_speed, state.accel_max
    speed = np.full((state.n, frames + 1), np.inf)
    dist = np.full((state.n, frames + 1), np.inf)
    vk = np.where(rows, v, 0.0)
    xk = np.zeros(state.n)
    speed[rows, 0], dist[rows, 0] = vk[rows], 0.0
    safe_target = np.where(rows & np.isfinite(target) & (target > 0.0), target, 1.0)
    for j in range(1, frames + 1):
        linear_law = np.nan_to_num(k) * (target - vk)
        idm_law = acc * (1.0 - np.power(np.maximum(vk, 0.0) / safe_target, delta))
        law = np.where(np.isfinite(k), linear_law, idm_law)
        xk = xk + dt * np.maximum(vk, 0.0)
        vk = vk + dt * np.minimum(a, np.maximum(np.nan_to_num(law), 0.0))
        speed[rows, j], dist[rows, j] = vk[rows], xk[rows]
    return speed, dist


def lane_change_allowance(dyn: Dynamics) -> float:
    """[m] What one lane change can cost a car along the road against its speed along the path:
    ``lane_width·tan(π/8)`` (1.66 m on 4 m lanes) — the robust rule's ``turning_leaders`` allowance, measured
    against highway-env's controller from every frame of a lane change at 1–30 m/s braking at up to ACC_MAX, 5–15
    Hz physics (worst 1.59 m; ``tests/test_safety.py::test_turning_allowance_covers_highway_env_s_lane_change``).
    A measured bound, not a closed form: the path turns by ``heading + β``."""
    return dyn.lane_width * math.tan(TURN_HEADING)


def lane_changes_allowed(state: RoadState, t: np.ndarray) -> np.ndarray:
    """(cars, frames) how many lane changes each car may have under way or begun by each time ``t`` [s] > 0: the
    one it is making now (turned or moving sideways) and :data:`LANE_CHANGES_BEGUN` more at any time (its timer is
    not observed); a car that never changes lane: only the one under way. 0 at ``t = 0``."""
    turning = (np.abs(state.heading) > LATERAL_MOTION_THRESHOLD) | (np.abs(state.vy) > 0.3)
    count = turning + np.where(state.can_change_lane, LANE_CHANGES_BEGUN, 0)
    return np.where(t[None, :] > 0.0, count[:, None].astype(float), 0.0)


def shortfall(state: RoadState, dyn: Dynamics, t: np.ndarray) -> np.ndarray:
    """(cars, frames) [m] how far turning may leave each car behind its speed along its path by each time ``t``
    [s]: :func:`lane_change_allowance` per lane change in :func:`lane_changes_allowed` (crashed cars: none)."""
    crashed = np.asarray(state.crashed, dtype=bool)[:, None]
    return np.where(crashed, 0.0, lane_change_allowance(dyn) * lane_changes_allowed(state, t))


def occupied_lanes(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """(cars, lanes) bool: the lane bands each car's body, rotated by its heading, overlaps now."""
    reach = np.abs(0.5 * state.length * np.sin(state.heading)) + np.abs(0.5 * dyn.body_width * np.cos(state.heading))
    centres = np.arange(dyn.lanes_count) * dyn.lane_width
    half = 0.5 * dyn.lane_width
    lo, hi = (state.y - reach)[:, None], (state.y + reach)[:, None]
    return (hi > centres[None, :] - half) & (lo < centres[None, :] + half)


def lane_crossing_time(dyn: Dynamics) -> float:
    """[s] The least time a car needs to carry its centre across a lane boundary, a lower bound: its body's first
    entry into the next lane (the cut-in time plus the frame it subtracts) comes before. highway-env lets a driver
    start its next lane change only once its centre is in the new lane."""
    return dyn.cut_in_time + dyn.frame_dt


def lanes_now(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """(cars, lanes) bool: the lanes each car's rotated body overlaps now, and the lane it moves to (heading or
    lateral speed)."""
    occupied = occupied_lanes(state, dyn)
    moving = (np.abs(state.heading) > LATERAL_MOTION_THRESHOLD) | (np.abs(state.vy) > 0.3)
    own = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    toward = np.clip(own + np.where(state.vy > 0, 1, -1), 0, dyn.lanes_count - 1)
    rows = np.flatnonzero(moving)
    occupied[rows, toward[rows]] = True
    return occupied


def lane_entry_times(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """(cars, lanes) the earliest time [s] each car may occupy each lane: 0 for the lanes its body overlaps and the
    lane it moves to (heading or lateral speed), ``d · cut_in_time`` for a lane ``d`` lanes from those (the fastest
    lateral motion of highway-env's controller), and :func:`lane_crossing_time` more for every further lane; inf for
    a car that never changes lane."""
    occupied = lanes_now(state, dyn)
    lanes = np.arange(dyn.lanes_count)
    dist = np.where(occupied[:, None, :], np.abs(lanes[:, None] - lanes[None, :])[None], 10**6).min(axis=2)
    entry = np.where(dist > 0, dyn.cut_in_time + (dist - 1) * lane_crossing_time(dyn), 0.0)
    return np.where(state.can_change_lane[:, None] | (dist == 0), entry, np.inf).astype(float)


@dataclass(frozen=True)
class CarSets:
    """The reachable sets of every other car (rows of a :class:`RoadState`), per frame of :attr:`Dynamics.times`:
    positions ``x_lo``/``x_hi`` [m] along the road and speeds ``v_lo``/``v_hi`` [m/s] along the car's path
    (:func:`path_speed`), ``entry`` (cars, lanes) the earliest time [s] a car may occupy a lane, ``now`` (cars,
    lanes) the lanes it was in (or moving into) when the sets were drawn. ``vehicle``: the snapshot index of each
    row."""

    vehicle: np.ndarray
    x_lo: np.ndarray
    x_hi: np.ndarray
    v_lo: np.ndarray
    v_hi: np.ndarray
    entry: np.ndarray
    now: np.ndarray

    def shifted(self, frames: int, seconds: float) -> CarSets:
        """These sets ``frames`` frames (``seconds`` [s]) later, padded with no bound at the horizon's end."""

        def shift(a: np.ndarray, pad: float) -> np.ndarray:
            out = np.full_like(a, pad)
            out[:, : a.shape[1] - frames] = a[:, frames:]
            return out

        return CarSets(self.vehicle, shift(self.x_lo, -np.inf), shift(self.x_hi, np.inf), shift(self.v_lo, -np.inf),
                       shift(self.v_hi, np.inf), np.maximum(self.entry - seconds, 0.0), self.now)  # fmt: skip

    def intersect(self, older: CarSets, keep: np.ndarray) -> CarSets:
        """These sets intersected, row by row, with ``older`` (already shifted to now) for the rows ``keep``
        (cars still inside their older sets, matched by snapshot index)."""
        rows = rows_in(older.vehicle, self.vehicle)
        mine = np.flatnonzero((rows >= 0) & np.asarray(keep, dtype=bool))
        theirs = rows[mine]
        out = {name: getattr(self, name).copy() for name in ("x_lo", "x_hi", "v_lo", "v_hi", "entry")}
        for name, pick in (("x_lo", np.maximum), ("x_hi", np.minimum), ("v_lo", np.maximum),
                           ("v_hi", np.minimum), ("entry", np.maximum)):  # fmt: skip
            out[name][mine] = pick(out[name][mine], getattr(older, name)[theirs])
        return CarSets(self.vehicle, **out, now=self.now)


def rows_in(vehicles: np.ndarray, wanted: np.ndarray) -> np.ndarray:
    """(len(wanted),) the row of each snapshot index of ``wanted`` among ``vehicles`` (−1: absent)."""
    vehicles, wanted = np.asarray(vehicles, dtype=np.int64), np.asarray(wanted, dtype=np.int64)
    if not vehicles.size or not wanted.size:
        return np.full(wanted.size, -1, dtype=np.int64)
    lookup = np.full(max(int(vehicles.max()), int(wanted.max())) + 1, -1, dtype=np.int64)
    lookup[vehicles] = np.arange(vehicles.size)
    return lookup[wanted]


def car_sets(state: RoadState, dyn: Dynamics, vehicle: np.ndarray) -> CarSets:
    """The reachable sets drawn from ``state`` alone (``vehicle``: the snapshot index of each row); a crashed car
    is a wall where it stands."""
    t = dyn.times
    unbounded = np.isfinite(state.linear_speed_gain) & ~linear_set_point_bound(state)
    v = path_speed(state)
    v_min, v_max = speed_bounds(v, state.target_speed, unbounded)
    x_lo, x_hi, v_lo, v_hi = envelope(state.x, v, state.accel_max, state.brake_max, v_min, v_max, t,
                                      shortfall(state, dyn, t))  # fmt: skip
    law_v, law_d = law_rise(state, v, t.size - 1, dyn.frame_dt)  # the driver's own law, where it bounds tighter
    x_hi, v_hi = np.minimum(x_hi, state.x[:, None] + law_d), np.minimum(v_hi, law_v)
    wall = np.asarray(state.crashed, dtype=bool)
    x_lo[wall], x_hi[wall] = state.x[wall, None], state.x[wall, None]
    v_lo[wall], v_hi[wall] = 0.0, 0.0
    return CarSets(np.asarray(vehicle), x_lo, x_hi, v_lo, v_hi, lane_entry_times(state, dyn), lanes_now(state, dyn))


def escaped_cars(state: RoadState, dyn: Dynamics, carried: CarSets, vehicle: np.ndarray) -> np.ndarray:
    """(cars,) bool: the cars of ``state`` outside the sets ``carried`` drew for them (already shifted to now):
    position along the road or speed along the path (:func:`path_speed`) outside the intervals at frame 0, or a
    lane its body overlaps entered earlier than allowed. A car without a carried set is inside."""
    rows = rows_in(carried.vehicle, vehicle)
    mine = np.flatnonzero(rows >= 0)
    r = rows[mine]
    occupied = occupied_lanes(state, dyn)[mine]
    speed = path_speed(state)[mine]
    x = state.x[mine]
    tol = ESCAPE_TOLERANCE
    inside = (carried.x_lo[r, 0] - tol <= x) & (x <= carried.x_hi[r, 0] + tol)
    inside &= (carried.v_lo[r, 0] - tol <= speed) & (speed <= carried.v_hi[r, 0] + tol)
    inside &= ~((carried.entry[r] > tol) & occupied).any(axis=1)
    out = np.zeros(state.n, dtype=bool)
    out[mine] = ~inside
    return out


def rolling_back(
    state: RoadState, escaped: np.ndarray, carried: CarSets | None = None, vehicle: np.ndarray | None = None
) -> np.ndarray:
    """(cars,) bool: the escaped cars that rolled back: moving backwards now (speed along the path < 0), or, with
    the ``carried`` sets (shifted to now; ``vehicle``: the snapshot index of each row), already moving backwards
    when they were drawn (their lowest speed now below 0) and below them now, as a car that rolled back and moves
    forward again is. A jammed highway-env car (IDM or linear model) whose gap is below its desired one keeps
    braking through 0 m/s and rolls back; both models are meant for v ≥ 0, so these escapes are named as outside
    the driver model, not bounded."""
    out = np.asarray(escaped, dtype=bool) & (path_speed(state) < 0.0)
    if carried is not None and vehicle is not None:
        rows = rows_in(carried.vehicle, vehicle)
        rest = np.flatnonzero(np.asarray(escaped, dtype=bool) & ~out & (rows >= 0))
        r = rows[rest]
        out[rest] = (carried.v_lo[r, 0] < 0.0) & (state.x[rest] < carried.x_lo[r, 0])
    return out
