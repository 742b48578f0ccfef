"""The robust rule's cut-ins: which lanes each vehicle may occupy (its heading, body and nose), which vehicles
may change into a lane the ego uses and from when (MOBIL's safety criterion and incentive, with each driver's own
model), and a car passing the ego that cuts in ahead of it. Metres, m/s, seconds."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from safelane.safety.one_decision.forecast import accelerated, current_accelerations
from safelane.safety.others import (
    idm_acceleration_behind,
    idm_acceleration_behind_gap,
    least_desired_gap,
    linear_acceleration_behind,
    set_points,
)
from safelane.safety.world import IDM_LANE_MARGIN, LATERAL_MOTION_THRESHOLD, Dynamics, Mode, RoadState


@dataclass
class Occupancy:
    """For each other vehicle, the lanes it may occupy and from when [s] (robust adds cut-ins)."""

    vehicle: list[int] = field(default_factory=list)
    lane: list[int] = field(default_factory=list)
    start: list[float] = field(default_factory=list)
    nominal: list[bool] = field(default_factory=list)  # also a conflict of the nominal model

    def add(self, vehicle: int, lane: int, start: float, nominal: bool) -> None:
        self.vehicle.append(vehicle)
        self.lane.append(lane)
        self.start.append(start)
        self.nominal.append(nominal)


def occupancy(state: RoadState, dyn: Dynamics, mode: Mode, near: np.ndarray) -> Occupancy:
    occ = Occupancy()
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    for i in near:
        own = int(lanes[i])
        occ.add(int(i), own, 0.0, True)
        if mode != "robust":
            continue
        # Heading angle (Section IV.4b): a vehicle already moving sideways is in the next lane too.
        nxt = -10
        if abs(state.heading[i]) > LATERAL_MOTION_THRESHOLD or abs(state.vy[i]) > 0.3:
            direction = 1 if state.vy[i] > 0 else -1
            nxt = own + direction
            if dyn.rule.finishing_changes and finishing_change(state, dyn, int(i), own, direction):
                nxt = -10  # it may still cut in from its lane: a cut-in candidate there, MOBIL-filtered
            elif 0 <= nxt < dyn.lanes_count:
                occ.add(int(i), nxt, 0.0, False)
        if dyn.rule.reversing_noses and state.vx[i] < 0.0 and abs(state.heading[i]) > LATERAL_MOTION_THRESHOLD:
            # Rolling backwards it moves away from the lane its nose points to, and drives there as soon as
            # it moves forward again (a jammed IDM car rolling back, found by the trained agents).
            nose = own + (1 if state.heading[i] > 0 else -1)
            if nose != nxt and 0 <= nose < dyn.lanes_count:
                occ.add(int(i), nose, 0.0, False)
        if dyn.rule.body_extent:
            # Its body, rotated by its heading, reaches this far either side of its centre [m]; it is
            # in every lane whose band that overlaps (a slow car turning hard sticks its rear corner
            # into the lane it is leaving).
            reach = abs(0.5 * state.length[i] * math.sin(state.heading[i])) + abs(
                0.5 * dyn.body_width * math.cos(state.heading[i])
            )
            for side in (own - 1, own + 1):
                if side == nxt or not 0 <= side < dyn.lanes_count:
                    continue
                centre, half_lane = side * dyn.lane_width, 0.5 * dyn.lane_width
                if state.y[i] + reach > centre - half_lane and state.y[i] - reach < centre + half_lane:
                    occ.add(int(i), side, 0.0, False)
    return occ


def permit_times(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray, ego_target: float
) -> np.ndarray:
    """The first frame time [s] of the decision at which MOBIL's safety criterion lets each vehicle of ``near``
    change into the ego's lane ahead of it, the ego its new follower (the rule's ``cut_in_when_permitted``): the
    criterion of :func:`cut_in_candidates` at every frame of the decision instead of now and at its end, the
    ego on the action's path (``ego_xs`` [m], ``ego_vs`` [m/s]: frames 0 … frames) and the car at its fastest
    (accelerating at its limit from now, which only makes the criterion allow more and earlier); inf: at none.
    0 for a car moving backwards with ``reversing_cut_ins`` (any lane change). With the option a permitted
    cut-in starts at this time plus the cut-in time rather than at the cut-in time from now: the car decides
    its lane change only when MOBIL lets it (a car passing a stopped ego in the next
    lane, 3 m ahead, is not allowed to cut in now — the ego would have to brake at 28 m/s² — but is at the end
    of the decision, 24 m ahead; it was assumed in the ego's lane from now)."""
    out = np.full(near.size, np.inf)
    if near.size == 0:
        return out
    t = dyn.times[: ego_xs.shape[0]]
    target = np.clip(ego_target, 0.0, state.speed_limit)
    linear = np.isfinite(state.linear_speed_gain[near])
    accel = np.maximum(state.accel_max[near], 0.0)
    brake = np.maximum(state.brake_max[near], 1e-6)
    limit = -state.max_braking_imposed[near]
    for f in range(t.size):
        tau = t[f]
        x_f = state.x[near] + state.vx[near] * tau + 0.5 * accel * tau * tau
        v_f = state.vx[near] + accel * tau
        d = x_f - ego_xs[f]
        ego_v = np.full(near.size, ego_vs[f])
        if dyn.rule.permit_any_speed:
            # IDM's desired gap d* falls with the car's speed and can go negative (a car much faster than the
            # ego); highway-env squares d*/d, so the criterion is loosest at the car's speed with the least
            # |d*| in [braking from now, accelerating from now], not at its fastest.
            v_lo = np.maximum(state.vx[near] - brake * tau, 0.0)
            q = least_desired_gap(state, near, ego_vs[f], v_lo, v_f)
            a = idm_acceleration_behind_gap(state, near, d, ego_v, np.full(near.size, target), q)
            a = np.where(d > 0.0, a, -np.inf)  # MOBIL sees the ego as the new follower only behind the car
        else:
            a = idm_acceleration_behind(state, near, d, ego_v, np.full(near.size, target), v_f)
        if linear.any() and dyn.rule.linear_mobil:
            own = np.hypot(state.vx[near], state.vy[near]) + accel * tau
            a_lin = linear_acceleration_behind(state, near, d, ego_v, np.full(near.size, float(ego_target)), own)
            a = np.where(linear, a_lin, a)
        elif linear.any():
            a = np.where(linear, np.inf, a)
        newly = (a >= limit) & ~np.isfinite(out)
        out[newly] = tau
    if dyn.rule.reversing_cut_ins:
        out[state.vx[near] < 0.0] = 0.0
    return out


def required_gap(state: RoadState, i: int, ego_speed: float, ego_target: float, tau: float) -> float:
    """The smallest centre distance [m] ahead of the ego at which MOBIL's safety criterion lets vehicle ``i``
    cut in front of it at time ``tau`` [s] (the ego at ``ego_speed`` [m/s], set-point ``ego_target``), whatever
    speed the car has then within its reach since now: the criterion of :func:`permit_times` solved for the
    distance; inf where it allows it at none. IDM drivers:
    ``a = free − acc·(d*/d)² ≥ −b_safe`` gives ``d ≥ |d*| / √((free + b_safe)/acc)``, with the least ``|d*|``
    over the car's speeds in reach (:func:`least_desired_gap`, as ``permit_any_speed`` takes it); linear-model
    drivers (with ``linear_mobil``): ``d ≥ d_safe − (C + b_safe)/k₂`` with ``C`` the formula's other terms at
    the car's fastest (the formula grows with its speed). Never below 0:
    MOBIL sees the ego as the new follower only while the car's centre is ahead of the ego's."""
    limit = -float(state.max_braking_imposed[i])
    accel = max(float(state.accel_max[i]), 0.0)
    dw, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    if math.isfinite(float(state.linear_speed_gain[i])):
        own = math.hypot(float(state.vx[i]), float(state.vy[i])) + accel * tau
        k0, k1 = float(state.linear_speed_gain[i]), float(state.linear_speed_difference_gain[i])
        k2 = float(state.linear_distance_gain[i])
        other = k0 * (ego_target - ego_speed) + k1 * min(own - ego_speed, 0.0)
        if not (other >= limit and k2 > 0.0):
            return math.inf
        d_safe = dw + max(ego_speed, 0.0) * tw
        return max(d_safe - (other - limit) / k2, 0.0)
    acc, delta = float(state.idm_comfort_acc[i]), float(state.idm_delta[i])
    target = min(max(ego_target, 0.0), float(state.speed_limit))
    target = 1e-2 if abs(target) < 1e-2 else target
    free = acc * (1 - math.pow(max(ego_speed, 0.0) / abs(target), delta))
    room = (free - limit) / acc
    if not room > 0.0:
        return math.inf
    b = max(float(state.brake_max[i]), 1e-6)
    v_lo, v_hi = max(float(state.vx[i]) - b * tau, 0.0), float(state.vx[i]) + accel * tau
    who = np.array([i])
    q = float(least_desired_gap(state, who, ego_speed, np.array([v_lo]), np.array([v_hi]))[0])
    return q / math.sqrt(room)


def passing_positions(
    state: RoadState, dyn: Dynamics, i: int, ego_xs: np.ndarray, ego_vs: np.ndarray, ego_target: float,
    first: float, allowance: float,
) -> np.ndarray:  # fmt: skip
    """A lower bound on the position [m] along the road, at every frame of the horizon, of vehicle ``i`` — now
    behind the ego in a next lane — once it has cut into the ego's lane *ahead* of it (``passing_cut_ins``):
    MOBIL's safety criterion is judged with the ego as the new follower, so the car decides only while it is
    at least :func:`required_gap` ahead, at a frame of the decision from ``first`` [s] (:func:`permit_times`)
    on; its body is in the lane from that frame plus the cut-in time, and it brakes at its limit from its
    lowest speed then (braking from now). The minimum over those decision frames, less ``allowance`` [m]
    (:func:`turning_allowance`); inf before the earliest entry. ``ego_xs`` [m], ``ego_vs`` [m/s]: the ego on
    the action's path at the decision's frames (0 … frames). Why: a car passing a
    slow or stopped ego in the next lane, behind it now, was bounded as a follower entering the ego's lane —
    driving on through the ego — though MOBIL lets it in only ahead."""
    t = dyn.times
    out = np.full(t.size, np.inf)
    b = max(float(state.brake_max[i]), 1e-6)
    for f in range(ego_xs.shape[0]):
        tau = float(t[f])
        if not tau >= first:
            continue
        d_req = required_gap(state, i, float(ego_vs[f]), ego_target, tau)
        if not math.isfinite(d_req):
            continue
        v = max(float(state.vx[i]) - b * tau, 0.0)
        lo = int(np.searchsorted(t, tau + dyn.cut_in_time, side="left"))
        s = t[lo:] - tau
        tt = np.minimum(s, v / b)
        x = ((float(ego_xs[f]) + d_req) + (v * tt - 0.5 * b * (tt * tt))) - allowance
        out[lo:] = np.minimum(out[lo:], x)
    return out


def band_lanes(state: RoadState, dyn: Dynamics, near: np.ndarray) -> np.ndarray:
    """For each vehicle of ``near``, the lane next to its own whose IDM band — half a lane + ``IDM_LANE_MARGIN`` (1 m)
    of the lane's centre, where highway-env's IDM (``Road.neighbour_vehicles``, ``Lane.on_lane(margin=1)``) sees a
    leader — also holds its centre; −10: none, or without ``incentive_leaders_band``. MOBIL's incentive reads a
    driver's leader by that band: a car changing into the driver's lane, its centre still nearer the lane it leaves,
    is already the driver's leader (a timid car turned in behind the ego to escape one, found by the claim grid
    with hidden types)."""
    out = np.full(near.size, -10, dtype=np.int64)
    if not dyn.rule.incentive_leaders_band:
        return out
    y = state.y[near]
    lanes = state.lane_of(y, dyn.lanes_count, dyn.lane_width)
    for side in (-1, 1):
        other = lanes + side
        inside = np.abs(y - other * dyn.lane_width) <= 0.5 * dyn.lane_width + IDM_LANE_MARGIN
        out = np.where(inside & (other >= 0) & (other < dyn.lanes_count), other, out)
    return out


def finishing_change(state: RoadState, dyn: Dynamics, i: int, own: int, direction: int) -> bool:
    """Whether vehicle ``i``, in lane ``own`` and moving sideways in ``direction`` (±1 lane), is finishing a
    lane change *into* that lane (the rule's ``finishing_changes``): moving forward, its centre short of the
    lane's centre [m] and moving toward it.

    highway-env steers a car to its target lane's centre and changes the target only by a new MOBIL decision,
    taken while its lane is its target (``IDMVehicle.change_lane_policy``). A car that has crossed into a lane
    and is moving toward its centre is either settling there or has just decided to go on; the heading
    projection put it in the lane beyond from now — the lane next to it, the ego's — whatever MOBIL says
    (283 of 295 sampled 'second_lane_cut_in' breaks, a car from two lanes over settling in the lane
    next to the ego). With the option it is a cut-in candidate from its own lane like any car there: into the
    ego's lane only if MOBIL's safety criterion allows it, from the cut-in time. A car rolling backwards
    steers the wrong way and keeps the projection."""
    if not state.vx[i] >= 0.0:
        return False
    return (own * dyn.lane_width - float(state.y[i])) * direction > 0.0


def cut_in_candidates(
    state: RoadState,
    dyn: Dynamics,
    near: np.ndarray,
    ego_x_end: float,
    ego_v_end: float,
    ego_target: float,
    ego_path: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicles that may change into a lane the ego uses: (ahead, into a lane the ego is in; ahead, into a
    lane the ego is entering; level with or behind the ego, into a lane the ego is in; level with or behind
    the ego, into a lane it is entering — the last two for ``level_cut_ins``; level with or behind the ego,
    unfiltered by MOBIL's incentive — the cars ``level_incentive_frames`` times frame by frame).

    Into a lane the ego already occupies, a vehicle changes lane only if its own rule allows it:
    MOBIL's safety criterion (highway-env) requires the acceleration its own model predicts for its new
    follower — the ego — to stay ≥ −LANE_CHANGE_MAX_BRAKING_IMPOSED: IDM's formula
    (:func:`idm_acceleration_behind`), or the linear model's for Linear, Aggressive and Defensive drivers
    (:func:`linear_acceleration_behind`). The ego is taken as that follower
    (conservative and independent of the other vehicles, which keeps the model monotone); the
    criterion is checked now and at the end of the decision period (others at constant speed, the ego
    on the action's trajectory). Into a lane the ego is only *entering*, the other driver cannot see the
    ego there when it decides, so any moving vehicle ahead may cut in.

    A vehicle whose centre is behind the ego's, now or at the end of the period (the ego overtaking it), sees the ego as
    its new *leader*: MOBIL's safety criterion then protects its new follower, not the ego, so any of them may turn in
    (a car just overtaken turned into the ego's rear flank). With ``level_cut_ins`` the rule counts them as followers
    entering the ego's lanes; with ``level_incentive`` only those MOBIL's incentive lets move behind the ego
    (:func:`turn_in_incentive`). That incentive is judged with the ego in the lane, so into a lane the ego is only
    *entering* it does not hold either (found twice by the trained agents: a car two lanes over, level with the ego,
    changed into the lane the ego was changing into — it saw no ego there when it decided): with ``level_entering``
    every level car counts there. A car moving backwards steers the wrong way (highway-env's steering assumes forward
    motion: a lane change away from the ego swings its nose into the ego's lane, found by the trained agents): with
    ``reversing_cut_ins`` it may enter the ego's lanes whatever MOBIL says, ahead or level. ``ego_path``: the ego's
    positions [m] and speeds [m/s] at the decision's frames (0 … frames), for ``linear_incentive_braking``.
    """
    if near.size == 0:
        return (np.zeros(0, dtype=bool),) * 5
    can = state.can_change_lane[near] & (np.abs(state.vx[near]) >= 1.0)
    target = np.clip(ego_target, 0.0, state.speed_limit)
    d_now = state.x[near] - state.ego_x
    d_end = state.x[near] + state.vx[near] * dyn.decision_period - ego_x_end
    v_now, v_end = np.full(near.size, state.ego_speed), np.full(near.size, ego_v_end)
    a_now = idm_acceleration_behind(state, near, d_now, v_now, np.full(near.size, target))
    a_end = idm_acceleration_behind(state, near, d_end, v_end, np.full(near.size, target))
    linear = np.isfinite(state.linear_speed_gain[near])
    if linear.any() and dyn.rule.linear_mobil:  # Linear / Aggressive / Defensive drivers: their own formula
        who, set_point = near[linear], np.full(int(linear.sum()), float(ego_target))
        a_now[linear] = linear_acceleration_behind(state, who, d_now[linear], v_now[linear], set_point)
        a_end[linear] = linear_acceleration_behind(state, who, d_end[linear], v_end[linear], set_point)
    elif linear.any():  # without linear_mobil their criterion is not modelled: any cut-in is allowed
        a_now[linear] = np.inf
    limit = -state.max_braking_imposed[near]
    ahead = (d_now > 0) | (d_end > 0)
    level_any = (d_now <= 0) | (d_end <= 0)
    if dyn.rule.level_cut_ins and dyn.rule.level_incentive:
        incentive = turn_in_incentive(state, dyn, near, d_now, d_end, ego_v_end)
        if dyn.rule.linear_incentive:  # linear-model drivers' incentive with their own formula
            linear_gain = linear_turn_in_incentive(state, dyn, near, d_now, d_end, ego_v_end)
            if dyn.rule.linear_incentive_braking:
                linear_gain = linear_gain | linear_turn_in_incentive_braking(state, dyn, near, *ego_path)
            level = np.where(linear, linear_gain, incentive)
        else:  # without linear_incentive their incentive is not modelled: any turn-in is assumed
            level = np.where(linear, level_any, incentive)
    else:
        level = level_any
    permitted = (a_now >= limit) | (a_end >= limit)
    if dyn.rule.reversing_cut_ins:  # steering assumes forward motion: reversing, a lane change away swings its nose in
        reversing = state.vx[near] < 0.0
        permitted, level = permitted | reversing, level | (reversing & level_any)
    level_entering = level_any if dyn.rule.level_entering else level
    return can & ahead & permitted, can & ahead, can & level, can & level_entering, can & level_any


def _gap_ratio(state: RoadState, who: np.ndarray, front_speed: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """IDM's ``d*/d`` for vehicles ``who`` following a vehicle at ``front_speed`` [m/s], ``gap`` [m] centre to
    centre (``IDMVehicle.desired_gap`` over ``not_zero(lane_distance_to)``), with their own parameters."""
    v = state.vx[who]
    ab = -state.idm_comfort_acc[who] * state.idm_comfort_dec[who]
    d_star = state.idm_distance_wanted[who] + v * state.idm_time_wanted[who] + v * (v - front_speed) / (2 * np.sqrt(ab))
    d = np.where(np.abs(gap) < 1e-2, 1e-2, gap)
    return d_star / d


def turn_in_incentive(
    state: RoadState, dyn: Dynamics, near: np.ndarray, d_now: np.ndarray, d_end: np.ndarray, ego_v_end: float
) -> np.ndarray:
    """Whether each vehicle of ``near``, with its centre behind the ego's (``d_now`` / ``d_end`` [m]: its offset
    ahead of the ego now / at the end of the decision, others at constant speed), may gain by moving behind the ego:
    MOBIL's incentive with politeness 0 (highway-env's ``IDMVehicle``), ``a(behind the ego) − a(behind its leader)
    ≥`` ``dyn.mobil_min_gain`` (0.2 m/s², highway-env's, unless a driver mixture's types go lower). The free-road
    terms cancel, leaving ``acc·(d*/d)²_leader − acc·(d*/d)²_ego``. Its leader's term is taken as the largest over
    every vehicle ahead of it in its lane (IDM sees the nearest; the largest can only overstate the gain, and it
    keeps the rule monotone: adding a vehicle never removes a conflict); none: 0. Checked now and at the end of the
    decision, as the cut-in criterion is (an approximation within the decision, not a bound): a car in free flow
    loses by tucking in behind the ego at a short gap; one stuck in a slow queue gains (the car just overtaken that
    turned into the ego's rear flank)."""
    x, v, t = state.x[near], state.vx[near], dyn.decision_period
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    acc = state.idm_comfort_acc[near]
    lead_now = np.zeros(near.size)
    lead_end = np.zeros(near.size)
    for j in range(near.size):
        rows = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))  # its leaders: IDM's band
        if rows.size:
            who = np.full(rows.size, near[j])
            q_now = _gap_ratio(state, who, v[rows], x[rows] - x[j])
            q_end = _gap_ratio(state, who, v[rows], (x[rows] + v[rows] * t) - (x[j] + v[j] * t))
            lead_now[j] = (q_now * q_now).max()
            lead_end[j] = (q_end * q_end).max()
    q_ego_now = _gap_ratio(state, near, np.full(near.size, state.ego_speed), -d_now)
    q_ego_end = _gap_ratio(state, near, np.full(near.size, ego_v_end), -d_end)
    gain_now = acc * lead_now - acc * (q_ego_now * q_ego_now)
    gain_end = acc * lead_end - acc * (q_ego_end * q_ego_end)
    return ((d_now <= 0) & (gain_now >= dyn.mobil_min_gain)) | ((d_end <= 0) & (gain_end >= dyn.mobil_min_gain))


def linear_turn_in_incentive(
    state: RoadState, dyn: Dynamics, near: np.ndarray, d_now: np.ndarray, d_end: np.ndarray, ego_v_end: float
) -> np.ndarray:
    """:func:`turn_in_incentive` for drivers with the linear acceleration model (Linear, Aggressive,
    Defensive; NaN gains elsewhere give False), with their own formula, as highway-env's ``IDMVehicle.mobil``
    applies it through ``LinearVehicle.acceleration``: politeness 0, so the gain is
    ``a(behind the ego) − a(behind its leader)``, and the target-speed term ``k₀·(v* − v)`` cancels, leaving
    ``k₁·min(v_front − v, 0) + k₂·min(d − d_safe, 0)`` per front vehicle, ``d_safe = DISTANCE_WANTED +
    max(v, 0)·TIME_WANTED`` [m], ``d`` [m] centre to centre. No leader: its term is 0, so a car on a free lane
    never gains by moving behind the ego. The leader's term is the most negative over every vehicle ahead of
    it in its lane (monotone, as for IDM). The threshold is ``dyn.mobil_min_gain`` (0.2 m/s², Linear's);
    Aggressive and Defensive drivers need 1.0, so the rule assumes more turn-ins than they make."""
    x, v, t = state.x[near], state.vx[near], dyn.decision_period
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_now = np.zeros(near.size)
    lead_end = np.zeros(near.size)
    for j in range(near.size):
        if not np.isfinite(state.linear_speed_gain[near[j]]):
            continue
        rows = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))  # its leaders: IDM's band
        if rows.size:
            closing = k1[j] * np.minimum(v[rows] - v[j], 0.0)
            gap_end = (x[rows] + v[rows] * t) - (x[j] + v[j] * t)
            lead_now[j] = (closing + k2[j] * np.minimum((x[rows] - x[j]) - d_safe[j], 0.0)).min()
            lead_end[j] = (closing + k2[j] * np.minimum(gap_end - d_safe[j], 0.0)).min()
    ego_now = k1 * np.minimum(state.ego_speed - v, 0.0) + k2 * np.minimum(-d_now - d_safe, 0.0)
    ego_end = k1 * np.minimum(ego_v_end - v, 0.0) + k2 * np.minimum(-d_end - d_safe, 0.0)
    gain_now = ego_now - lead_now
    gain_end = ego_end - lead_end
    return ((d_now <= 0) & (gain_now >= dyn.mobil_min_gain)) | ((d_end <= 0) & (gain_end >= dyn.mobil_min_gain))


def linear_turn_in_incentive_braking(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """:func:`linear_turn_in_incentive` at every physics frame of the decision (``ego_xs`` [m], ``ego_vs``
    [m/s]: the ego's positions and speeds at its frames 0 … frames) with every vehicle ahead of the driver in
    its lane braking at its maximum from now (a crashed one stopped), the driver itself at constant speed:
    ``shield.linear_incentive_braking``. Its leader braking only makes the driver's own lane worse, so this
    can only find more turn-ins than the check now and at the end at constant speeds (which it is OR-ed
    with). Why: a Linear car closing on a slow car 9 m ahead at 7.5
    m/s gained −5.4 m/s² now and −1 at the end by moving behind the ego, and turned in within the decision
    as its leader braked."""
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    lead_b = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    out = np.zeros(near.size, dtype=bool)
    for j in range(near.size):
        if not np.isfinite(state.linear_speed_gain[near[j]]):
            continue
        rows = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))
        for f in range(times.size):
            tau = times[f]
            own_x = x[j] + v[j] * tau
            d = own_x - ego_xs[f]
            if not d <= 0:
                continue
            # np.minimum, not min: NaN propagates as in the compiled kernel.
            ego_term = k1[j] * np.minimum(ego_vs[f] - v[j], 0.0) + k2[j] * np.minimum(-d - d_safe[j], 0.0)
            lead_term = 0.0
            for q, r in enumerate(rows):
                tt = np.minimum(tau, lead_v0[r] / lead_b[r])
                lx = x[r] + lead_v0[r] * tt - 0.5 * lead_b[r] * (tt * tt)
                lv = lead_v0[r] - lead_b[r] * tt
                term = k1[j] * np.minimum(lv - v[j], 0.0) + k2[j] * np.minimum((lx - own_x) - d_safe[j], 0.0)
                lead_term = term if q == 0 else np.minimum(lead_term, term)
            if ego_term - lead_term >= dyn.mobil_min_gain:
                out[j] = True
                break
    return out


def _desired_gap_range(
    dw: float, tw: float, root_ab: float, v_lo: float, v_hi: float, front_lo: float, front_hi: float
) -> tuple[float, float]:
    """The least and largest of IDM's desired gap ``d* = d₀ + v·T + v·(v − v_front)/(2√(ab))`` [m] over a
    driver's speeds ``v`` in ``[v_lo, v_hi]`` and its front vehicle's in ``[front_lo, front_hi]`` [m/s]
    (``v ≥ 0``): falling in ``v_front``; convex in ``v``, so the largest at an end of the range and the least
    at the vertex ``(v_front − T·2√(ab))/2`` clipped to it."""
    c = 2 * root_ab
    top = max(dw + v * tw + v * (v - front_lo) / c for v in (v_lo, v_hi))
    vertex = min(max(0.5 * (front_hi - tw * c), v_lo), v_hi)
    bottom = dw + vertex * tw + vertex * (vertex - front_hi) / c
    return bottom, top


def incentive_times_any_speed(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """:func:`incentive_times` as a bound (the rule's ``incentive_any_speed``): the first frame time [s] of the
    decision at which MOBIL's incentive *could* let each vehicle of ``near`` turn in behind the ego, whatever
    it and the vehicles ahead of it in its lane do within their limits — each between braking at its limit
    from now (a crashed one stopped) and accelerating at its limit from now, the ego on the action's path.
    The gain ``a(behind the ego) − a(behind its leader)`` is bounded above by the least its term behind the
    ego can be (the car slowest, farthest back) and the largest its leader's can be (the car fastest, the
    leader slowest and nearest; a gap that can close: unbounded), the leader's term the largest over every
    vehicle ahead of it, as :func:`turn_in_incentive` takes it. Its centre must be able to be behind the
    ego's. inf: at none. Why: :func:`incentive_times` (others at constant speed) was decided one physics
    frame late by 5 of 45 highway-env turn-ins (``examples/turn_in_timing.py``)."""
    out = np.full(near.size, np.inf)
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    brake = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    accel = np.where(state.crashed[near], 0.0, np.maximum(state.accel_max[near], 0.0))
    speed = np.where(state.crashed[near], 0.0, np.hypot(v, state.vy[near]))
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    for f in range(times.size):
        tau = times[f]
        stop = np.minimum(tau, v0 / brake)
        x_lo = x + v0 * stop - 0.5 * brake * (stop * stop)  # braking at its limit from now
        v_lo = v0 - brake * stop
        x_hi = x + v0 * tau + 0.5 * accel * (tau * tau)  # accelerating at its limit from now
        v_hi = speed + accel * tau  # IDM and MOBIL read the whole speed, not only along the road
        for j in range(near.size):
            if np.isfinite(out[j]) or not x_lo[j] - ego_xs[f] <= 0:
                continue
            i = near[j]
            linear = bool(np.isfinite(state.linear_speed_gain[i]))
            rows = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))  # its leaders: IDM's band
            gap_ego = ego_xs[f] - x_lo[j]  # [m] centre to centre, the car farthest back
            if linear and dyn.rule.linear_incentive:
                k1, k2 = state.linear_speed_difference_gain[i], state.linear_distance_gain[i]
                dw, tw = state.idm_distance_wanted[i], state.idm_time_wanted[i]
                ego_term = k1 * min(ego_vs[f] - v_lo[j], 0.0) + k2 * min(gap_ego - (dw + v_lo[j] * tw), 0.0)
                lead = 0.0  # no vehicle ahead: its term is 0
                if rows.size:
                    closing = k1 * np.minimum(v_lo[rows] - v_hi[j], 0.0)  # leaders slowest, the car fastest
                    gap = x_lo[rows] - x_hi[j]
                    lead = float((closing + k2 * np.minimum(gap - (dw + v_hi[j] * tw), 0.0)).min())
                if ego_term - lead >= dyn.mobil_min_gain:
                    out[j] = tau
            elif not linear:
                acc, dw, tw = state.idm_comfort_acc[i], state.idm_distance_wanted[i], state.idm_time_wanted[i]
                root_ab = float(np.sqrt(-acc * state.idm_comfort_dec[i]))
                lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo[j], v_hi[j], ego_vs[f], ego_vs[f])
                least = lo if lo > 0.0 else (-hi if hi < 0.0 else 0.0)
                q_ego = least / max(gap_ego, 1e-2)
                ego_term = q_ego * q_ego
                lead = 0.0
                for r in rows:
                    gap = x_lo[r] - x_hi[j]
                    if not gap >= 1e-2:
                        lead = np.inf  # the gap may close: IDM's term has no bound
                        break
                    lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo[j], v_hi[j], v_lo[r], v_hi[r])
                    q = max(hi, -lo) / gap
                    lead = max(lead, q * q)
                if acc * lead - acc * ego_term >= dyn.mobil_min_gain:
                    out[j] = tau
    return out


def incentive_times(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """The first frame time [s] of the decision at which MOBIL's incentive lets each vehicle of ``near`` turn
    in behind the ego (the rule's ``level_when_incentive`` with ``incentive_any_speed`` false — a timing,
    not a bound; :func:`incentive_times_any_speed` is): :func:`turn_in_incentive` (IDM) or
    :func:`linear_turn_in_incentive` (linear-model drivers) at every frame instead of now and at the end, the
    others at constant speed and the ego on the action's path; for linear-model drivers also
    :func:`linear_turn_in_incentive_braking`'s frames. Its centre must be behind the ego's at that frame. inf:
    at none (then only the now-and-end verdict, from the cut-in time)."""
    out = np.full(near.size, np.inf)
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    acc = state.idm_comfort_acc[near]
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    lead_b = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    now_acc = current_accelerations_of(state, dyn) if dyn.rule.incentive_accelerations else None
    for j in range(near.size):
        linear = bool(np.isfinite(state.linear_speed_gain[near[j]]))
        rows = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))
        who = np.full(rows.size, near[j])
        for f in range(times.size):
            tau = times[f]
            own_x = x[j] + v[j] * tau
            d = own_x - ego_xs[f]
            if not d <= 0:
                continue
            if linear and dyn.rule.linear_incentive:
                ego_term = k1[j] * np.minimum(ego_vs[f] - v[j], 0.0) + k2[j] * np.minimum(-d - d_safe[j], 0.0)
                lead = braking = 0.0  # no vehicle ahead: its term is 0
                if rows.size:
                    gap = (x[rows] + v[rows] * tau) - own_x
                    lead = (k1[j] * np.minimum(v[rows] - v[j], 0.0) + k2[j] * np.minimum(gap - d_safe[j], 0.0)).min()
                    tt = np.minimum(tau, lead_v0[rows] / lead_b[rows])
                    lx = x[rows] + lead_v0[rows] * tt - 0.5 * lead_b[rows] * (tt * tt)
                    lv = lead_v0[rows] - lead_b[rows] * tt
                    braking = (
                        k1[j] * np.minimum(lv - v[j], 0.0) + k2[j] * np.minimum((lx - own_x) - d_safe[j], 0.0)
                    ).min()
                gains = ego_term - lead >= dyn.mobil_min_gain
                if dyn.rule.linear_incentive_braking:
                    gains = gains or ego_term - braking >= dyn.mobil_min_gain
                if gains:
                    out[j] = tau
                    break
            elif not linear:
                lead = 0.0
                if rows.size:
                    q = _gap_ratio(state, who, v[rows], (x[rows] + v[rows] * tau) - own_x)
                    lead = float((q * q).max())
                q_ego = float(_gap_ratio(state, near[j : j + 1], np.array([ego_vs[f]]), np.array([-d]))[0])
                if acc[j] * lead - acc[j] * (q_ego * q_ego) >= dyn.mobil_min_gain:
                    out[j] = tau
                    break
                if now_acc is not None and _gains_accelerating(state, dyn, near, j, rows, now_acc, tau, ego_xs[f],
                                                               ego_vs[f]):  # fmt: skip
                    out[j] = tau
                    break
    return out


def current_accelerations_of(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """[m/s²] Each vehicle's acceleration now (:func:`~safelane.safety.one_decision.forecast.current_accelerations`,
    the kernel the compiled engine calls too)."""
    return current_accelerations(
        state.ego_x, dyn.lanes_count, dyn.lane_width, state.speed_limit, state.x, state.y, state.vx, state.vy,
        state.length, state.crashed, state.brake_max, state.accel_max, state.idm_delta, state.idm_comfort_acc,
        state.idm_comfort_dec, state.idm_distance_wanted, state.idm_time_wanted, state.linear_speed_gain,
        state.linear_speed_difference_gain, state.linear_distance_gain, set_points(state),
    )  # fmt: skip


def _gains_accelerating(
    state: RoadState, dyn: Dynamics, near: np.ndarray, j: int, rows: np.ndarray, now_acc: np.ndarray, tau: float,
    ego_x: float, ego_v: float,
) -> bool:
    """Whether MOBIL's incentive lets IDM driver ``near[j]`` turn in behind the ego (at ``ego_x`` [m], ``ego_v``
    [m/s]) ``tau`` [s] from now, it and its leaders ``rows`` (rows of ``near``) each keeping its acceleration now
    (``now_acc`` [m/s²], per state row; the rule's ``incentive_accelerations``): its centre behind the ego's and
    its gain ``acc·(d*/d)²_leader − acc·(d*/d)²_ego`` at least ``dyn.mobil_min_gain``."""
    i = int(near[j])
    own_x, own_v = accelerated(float(state.x[i]), float(state.vx[i]), float(now_acc[i]), tau)
    if not own_x - ego_x <= 0:
        return False
    dw, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    acc, dec = float(state.idm_comfort_acc[i]), float(state.idm_comfort_dec[i])
    lead = 0.0
    for k, r in enumerate(rows):
        lx, lv = accelerated(float(state.x[near[r]]), float(state.vx[near[r]]), float(now_acc[near[r]]), tau)
        q = _idm_ratio(dw, tw, acc, dec, own_v, lv, lx - own_x)
        lead = q * q if k == 0 else float(np.maximum(lead, q * q))
    q_ego = _idm_ratio(dw, tw, acc, dec, own_v, ego_v, ego_x - own_x)
    return acc * lead - acc * (q_ego * q_ego) >= dyn.mobil_min_gain


def politeness_of(state: RoadState) -> np.ndarray:
    """Each vehicle's MOBIL politeness (``state.politeness``; an empty array: 0 for every vehicle)."""
    if state.politeness.shape[0] == state.n:
        return state.politeness
    return np.zeros(state.n)


def _neighbours(pos: np.ndarray, own_x: float) -> tuple[int, int]:
    """The nearest of the bodies at ``pos`` [m] (in that order) ahead of ``own_x`` (``pos ≥ own_x``, the last on a
    tie) and behind it (``pos < own_x``, the first on a tie), as highway-env's ``Road.neighbour_vehicles`` picks
    them; −1: none."""
    front = rear = -1
    for k in range(pos.shape[0]):
        if own_x <= pos[k] and (front < 0 or pos[k] <= pos[front]):
            front = k
        if pos[k] < own_x and (rear < 0 or pos[k] > pos[rear]):
            rear = k
    return front, rear


def polite_turn_ins(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray, lane: int
) -> np.ndarray:
    """Whether each vehicle of ``near`` in a lane next to ``lane`` may turn in behind the ego into ``lane`` for its
    followers' sake (the rule's ``incentive_politeness``): at some frame of the decision (``ego_xs`` [m], ``ego_vs``
    [m/s]: the ego's path, frames 0 … frames; the others at constant speed), its centre behind the ego's, MOBIL's
    politeness term ``p · (Δ new follower + Δ old follower)`` is positive and lifts the incentive of
    :func:`incentive_times` to ``dyn.mobil_min_gain``. The followers and leaders are the nearest in each lane's IDM
    band (:func:`band_lanes`), the ego one of ``lane``'s; their accelerations use the driver's own IDM constants, as
    ``IDMVehicle.mobil`` computes them (the free-road terms cancel in each difference). A timing with the others at
    constant speed, not a bound: the rule lets such a car turn in from the decision's start. IDM-formula drivers
    with politeness > 0 only (highway-env's linear-model drivers have none)."""
    out = np.zeros(near.size, dtype=bool)
    pol = politeness_of(state)[near]
    if not dyn.rule.incentive_politeness or not (pol > 0.0).any():
        return out
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    band = band_lanes(state, dyn, near)
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    for j in range(near.size):
        i = int(near[j])
        if not pol[j] > 0.0 or np.isfinite(state.linear_speed_gain[i]) or abs(int(lanes[j]) - lane) != 1:
            continue
        dw, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
        acc, dec = float(state.idm_comfort_acc[i]), float(state.idm_comfort_dec[i])
        idm = (dw, tw, acc, dec)
        others = np.arange(near.size) != j
        old_rows = np.flatnonzero(others & ((lanes == lanes[j]) | (band == lanes[j])))
        new_rows = np.flatnonzero(others & ((lanes == lane) | (band == lane)))
        leaders = np.flatnonzero(((lanes == lanes[j]) | (band == lanes[j])) & (x > x[j]))  # as incentive_times
        for f in range(times.size):
            tau = times[f]
            own_x = x[j] + v[j] * tau
            d = own_x - ego_xs[f]
            if not d <= 0:
                continue
            lead = 0.0
            if leaders.size:
                who = np.full(leaders.size, i)
                q = _gap_ratio(state, who, v[leaders], (x[leaders] + v[leaders] * tau) - own_x)
                lead = float((q * q).max())
            q_ego = float(_gap_ratio(state, near[j : j + 1], np.array([ego_vs[f]]), np.array([-d]))[0])
            own_gain = acc * lead - acc * (q_ego * q_ego)

            # The new lane: the ego first, then the others in order (highway-env lists the ego first).
            pos_new = np.concatenate(([ego_xs[f]], x[new_rows] + v[new_rows] * tau))
            v_new = np.concatenate(([ego_vs[f]], v[new_rows]))
            front, rear = _neighbours(pos_new, own_x)
            new_change = 0.0  # Δ new follower: behind the car instead of behind its leader
            if rear >= 0:
                before = 0.0
                if front >= 0:
                    before = _idm_term(*idm, v_new[rear], v_new[front], pos_new[front] - pos_new[rear])
                new_change = before - _idm_term(*idm, v_new[rear], v[j], own_x - pos_new[rear])
            pos_old = x[old_rows] + v[old_rows] * tau
            v_old = v[old_rows]
            front, rear = _neighbours(pos_old, own_x)
            old_change = 0.0  # Δ old follower: behind the car's leader instead of behind the car
            if rear >= 0:
                after = 0.0
                if front >= 0:
                    after = _idm_term(*idm, v_old[rear], v_old[front], pos_old[front] - pos_old[rear])
                old_change = _idm_term(*idm, v_old[rear], v[j], own_x - pos_old[rear]) - after
            polite = pol[j] * (new_change + old_change)
            if polite > 0.0 and own_gain + polite >= dyn.mobil_min_gain:
                out[j] = True
                break
    return out


def _idm_ratio(dw: float, tw: float, acc: float, dec: float, v: float, front_speed: float, gap: float) -> float:
    """IDM's ``d*/d`` of a driver with constants ``dw`` [m], ``tw`` [s], ``acc``, ``dec`` [m/s²] at ``v`` [m/s] behind a
    vehicle at ``front_speed`` [m/s], ``gap`` [m] centre to centre (:func:`_gap_ratio` for one pair)."""
    ab = -acc * dec
    d_star = dw + v * tw + v * (v - front_speed) / (2 * np.sqrt(ab))
    d = 1e-2 if abs(gap) < 1e-2 else gap
    return float(d_star / d)


def _idm_term(dw: float, tw: float, acc: float, dec: float, v: float, front_speed: float, gap: float) -> float:
    """[m/s²] IDM's interaction term ``acc·(d*/d)²`` of a driver with constants ``dw`` [m], ``tw`` [s], ``acc``,
    ``dec`` [m/s²] applied to a vehicle at ``v`` [m/s] behind one at ``front_speed`` [m/s], ``gap`` [m] centre to
    centre (:func:`_gap_ratio` for one pair)."""
    q = _idm_ratio(dw, tw, acc, dec, v, front_speed, gap)
    return acc * (q * q)
