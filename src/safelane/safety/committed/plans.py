"""The committed rule's numpy reference: plans, and each plan's worst gap to every car's reachable set.

* A **plan** (:class:`Plan`) is a sequence of ego set-points [m/s] and target lanes, one per decision, ending
  with the ego at a standstill. The family: the action, hold the set-point ``k ∈ {0..3}`` decisions, then SLOWER
  at every decision (the ego's exact trajectory: :func:`safelane.safety.ego.ego_trajectories`; the onsets and the
  lanes held: :mod:`safelane.safety.committed.plan_family`).
* Every other car's **reachable set** (:class:`~safelane.safety.committed.sets.CarSets`) comes from
  :mod:`safelane.safety.committed.sets`.
* Laws apply under a plan where they nest with the plan kept: the drivers' acceleration laws toward their
  set-points (in the sets), MOBIL's safety criterion against the ego's known plan (IDM and linear-model drivers
  entering a lane the ego holds), and followers reacting ``ρ`` after the plan's braking onset — an assumption, not
  IDM's law: a follower that does not brake so is named (``unbraked_followers``) (:func:`car_gaps`).
* An action is **verified** when a plan starting with it keeps ``margin`` to every car's reachable occupancy at
  every frame of the horizon (:func:`verify_plans`). Whose gap a car is: a car behind the ego in the lane it is
  in, or one cutting into a lane it holds, is not the ego's to avoid (that driver makes the gap); a car in a lane
  the ego is entering is, ahead or behind.

The compiled engine (:mod:`safelane.safety.committed.compiled`) gives the same bits; the family
(:mod:`safelane.safety.committed.family`) picks one. Pure maths: no simulator, no highway-env, no torch.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from safelane.core.spaces import IDLE, N_ACTIONS, SLOWER
from safelane.safety.committed.plan_family import Lanes, held_lanes, onsets, plan_actions
from safelane.safety.committed.sets import CarSets, fall, linear_set_point_bound, path_speed, rise, speed_bounds
from safelane.safety.ego import action_lanes, action_targets, ego_trajectories, speed_to_index
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState

__all__ = ["Lanes", "Plan", "car_gaps", "follower_bound", "onsets", "plan_gaps", "plan_of", "plan_set_points",
           "verify_plans"]  # fmt: skip


# --------------------------------------------------------------------------------------------
# Plans and their verification.
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Plan:
    """A committed plan: the ego's set-point [m/s] and target lane per decision from now until it stands
    (``set_points``, ``lanes``: the representation open to other families), the lanes it occupies and until when
    (``occupied``: (lane, time [s] from now)), its braking onset [s] from now, and how many frames of the horizon it
    was verified over (``frames``). ``action``/``hold``: the family's parameters that generated it (the action,
    hold ``hold`` decisions, then SLOWER)."""

    action: int
    hold: int
    set_points: tuple[float, ...]
    lanes: tuple[int, ...]
    occupied: tuple[tuple[int, float], ...]
    onset: float
    frames: int
    held: tuple[int, ...] = ()
    """The lanes the ego held (its lane and target lane) when the plan was verified: the line between the cars
    that count and those that do not stays where it was drawn while the plan is kept (:func:`car_gaps`' ``held``)."""

    def next_step(self) -> int:
        """The meta-action that realises the plan's next decision: IDLE while the set-point holds, SLOWER once it
        falls."""
        return IDLE if self.hold >= 1 else SLOWER

    def tail(self) -> tuple[int, int]:
        """(action, hold) whose trajectory from the next state is this plan's tail (a member of that state's
        family; its lanes and onset are this plan's, shifted: :meth:`shifted`)."""
        return (IDLE, self.hold - 1) if self.hold >= 1 else (SLOWER, 0)

    def shifted(self, dyn: Dynamics) -> Plan:
        """This plan one decision later."""
        a, k = self.tail()
        period = dyn.decision_period
        return Plan(a, k, self.set_points[1:] or self.set_points[-1:], self.lanes[1:] or self.lanes[-1:],
                    tuple((lane, until - period) for lane, until in self.occupied), self.onset - period,
                    self.frames - dyn.frames_per_decision, self.held)  # fmt: skip


def plan_of(state: RoadState, dyn: Dynamics, set_points: np.ndarray, action: int, hold: int) -> Plan:
    """The :class:`Plan` of (``action``, ``hold``) in ``state``: its set-points decision by decision, read from
    ``set_points`` [m/s], the plan's set-point per frame (a row of :func:`plan_set_points`), up to the first 0 m/s
    after the hold."""
    f = dyn.frames_per_decision
    points = [float(set_points[0])]
    for d in range(1, dyn.horizon_decisions):
        points.append(float(set_points[d * f]))
        if points[-1] == 0.0 and d > hold:
            break
    occupied = tuple(action_lanes(state, dyn, action))
    lane = occupied[-1][0]
    onset = float(onsets(dyn, action)[hold])
    return Plan(action, hold, tuple(points), (lane,) * len(points), occupied, onset, int(dyn.times.size - 1),
                (int(state.ego_lane), int(state.ego_target_lane)))  # fmt: skip


def plan_set_points(state: RoadState, dyn: Dynamics, ego_v: np.ndarray, action: int) -> np.ndarray:
    """(holds, frames) [m/s] the ego's set-point at each frame of each plan of ``action`` (``ego_v``: its speeds,
    (holds, frames)): the action's, held ``hold`` decisions, then one step below the speed at each decision (SLOWER,
    as :func:`plan_of` lists them)."""
    ts = dyn.target_speeds
    f = dyn.frames_per_decision
    out = np.empty_like(ego_v)
    for hold in range(ego_v.shape[0]):
        point = float(action_targets(state, dyn)[action])
        for d in range(0, math.ceil(ego_v.shape[1] / f)):
            if d > hold:
                point = float(ts[max(int(speed_to_index(ego_v[hold, d * f], ts)) - 1, 0)])
            out[hold, d * f : (d + 1) * f] = point
    return out


def _linear_criterion(
    state: RoadState, sets: CarSets, rows: np.ndarray, gap: np.ndarray, ev: np.ndarray, ego_set: np.ndarray | None,
    dyn: Dynamics,
) -> np.ndarray:  # fmt: skip
    """(rows, holds, frames) whether MOBIL's safety criterion of linear-model drivers could hold: the ego's
    acceleration behind the car by the car's own linear law (:func:`~safelane.safety.others.
    linear_acceleration_behind`), at its largest over the car's set (fastest, farthest: the law is monotone in both)
    and the ego's set-point (the plan's; without it the highest), at least ``−max_braking_imposed``."""
    k0, k1, k2 = (getattr(state, name)[rows][:, None, None] for name in
                  ("linear_speed_gain", "linear_speed_difference_gain", "linear_distance_gain"))  # fmt: skip
    target = (ego_set if ego_set is not None else np.full_like(ev[0], max(dyn.target_speeds)))[None]
    d_safe = state.idm_distance_wanted[rows][:, None, None] + ev * state.idm_time_wanted[rows][:, None, None]
    own = sets.v_hi[rows][:, None, :]  # highway-env reads the car's speed along its path
    pred = k0 * (target - ev) + k1 * np.minimum(own - ev, 0.0) + k2 * np.minimum(gap - d_safe, 0.0)
    return pred >= -state.max_braking_imposed[rows][:, None, None]


def _permit_entry(
    state: RoadState, dyn: Dynamics, sets: CarSets, rows: np.ndarray, ego_x: np.ndarray, ego_v: np.ndarray,
    ego_set: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(rows, holds) [s] the first time MOBIL's safety criterion could let each car (IDM and linear-model drivers,
    ahead) move in front of the ego on each plan (its loosest state in reach: the largest gap, the speed that makes
    the criterion loosest, the ego's set-point at the lane's limit for IDM, the plan's ``ego_set`` (holds, frames)
    for the linear models) or could be behind the ego, plus the cut-in time; inf: never in the horizon."""
    t = dyn.times
    acc = state.idm_comfort_acc[rows][:, None, None]
    ab = (-state.idm_comfort_acc * state.idm_comfort_dec)[rows][:, None, None]
    gap = sets.x_hi[rows][:, None, :] - ego_x[None]  # (rows, holds, frames) centre distance
    ev = np.maximum(ego_v[None], 0.0)
    target = max(state.speed_limit, 1e-2)
    free = acc * (1 - np.power(ev / target, state.idm_delta[rows][:, None, None]))
    base = state.idm_distance_wanted[rows][:, None, None] + ev * state.idm_time_wanted[rows][:, None, None]
    d_fast = base + ev * (ev - np.maximum(sets.v_hi[rows], 0.0)[:, None, :]) / (2 * np.sqrt(ab))
    # IDM's desired gap projects the car's velocity on the ego's heading: at most its speed along its path, at
    # least min(its lowest, 0) (both may be turned).
    d_slow = base + ev * (ev - np.minimum(sets.v_lo[rows], 0.0)[:, None, :]) / (2 * np.sqrt(ab))
    lo, hi = np.minimum(d_fast, d_slow), np.maximum(d_fast, d_slow)
    least = np.where(lo > 0.0, lo, np.where(hi < 0.0, -hi, 0.0))
    d = np.maximum(gap, 1e-2)
    ok = free - acc * (least / d) ** 2 >= -state.max_braking_imposed[rows][:, None, None]
    linear = np.isfinite(state.linear_speed_gain[rows])
    if linear.any():
        ok[linear] = _linear_criterion(state, sets, rows[linear], gap[linear], ev, ego_set, dyn)
    ok &= gap > 0.0
    # Once it may be behind the ego, MOBIL protects its new follower, not the ego: it may turn in behind it.
    ok |= sets.x_lo[rows][:, None, :] < ego_x[None]
    first = np.where(ok.any(axis=2), t[np.argmax(ok, axis=2)], np.inf)
    return first + dyn.cut_in_time


def verify_plans(
    state: RoadState, dyn: Dynamics, sets: CarSets
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """(5, holds) each plan's worst bumper-to-bumper gap [m] to every car's reachable occupancy over the horizon
    (−inf: action unavailable, inf: no car in reach), and the ego's positions [m], speeds [m/s] and set-points
    [m/s] (:func:`plan_set_points`; NaN for an unavailable action), each (5, holds, frames + 1) (:func:`plan_gaps`
    for one action). The compiled engine's :func:`~safelane.safety.committed.compiled.verify_plans_compiled`
    gives the same bits."""
    available, verify = plan_actions(state, dyn)
    ego_x, ego_v = ego_trajectories(state, dyn)
    set_points = np.full_like(ego_v, np.nan)
    for a in np.flatnonzero(available):
        set_points[a] = plan_set_points(state, dyn, ego_v[a], int(a))
    worst = np.full((N_ACTIONS, MAX_HOLD_DECISIONS + 1), -np.inf)
    for a in np.flatnonzero(verify):
        gaps = car_gaps(state, dyn, sets, ego_x[a], ego_v[a], onsets(dyn, int(a)), action_lanes(state, dyn, int(a)),
                        ego_set=set_points[a])  # fmt: skip
        worst[a] = gaps.min(axis=0) if gaps.shape[0] else np.inf
    return worst, ego_x, ego_v, set_points


def plan_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, ego_v: np.ndarray, onset: np.ndarray,
    lanes: Lanes, until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    ego_set: np.ndarray | None = None,
) -> np.ndarray:  # fmt: skip
    """(holds,) the worst bumper-to-bumper gap [m] of plans whose ego moves as ``ego_x``/``ego_v`` (holds, frames)
    over every car (inf: no car in reach): the least of :func:`car_gaps`, which documents the arguments."""
    gaps = car_gaps(state, dyn, sets, ego_x, ego_v, onset, lanes, until_frame, carried_followers, ego_set)
    return gaps.min(axis=0) if gaps.shape[0] else np.full(ego_x.shape[0], np.inf)


def car_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, ego_v: np.ndarray, onset: np.ndarray,
    lanes: Lanes, until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    ego_set: np.ndarray | None = None, held: tuple[int, ...] | None = None,
) -> np.ndarray:  # fmt: skip
    """(cars, holds) each car's worst bumper-to-bumper gap [m] to plans whose ego moves as ``ego_x``/``ego_v``
    (holds, frames) and brakes first at ``onset`` [s] (holds,), occupying ``lanes``, at every frame up to
    ``until_frame`` (default: the horizon's end); inf where the car never reaches the plan. The cars below the
    margin are the ones a plan fails on (a lapse names them).

    In each lane, from each car's entry time on, the car's interval ``[x_lo, x_hi]`` must stay clear of the ego by
    ``margin`` on one side or the other at every frame (a car that may be on either side conflicts). Laws: an IDM driver
    ahead, entering a lane the ego holds from the start, enters only after MOBIL's criterion against the plan could
    allow it (:func:`_permit_entry`); a car in such a lane behind the ego now follows it: accelerates at most until
    ``follower_reaction`` after the plan's braking onset, then brakes (:func:`follower_bound`). In a lane the ego holds,
    only the cars in that lane now (or moving into it) count, and of those in the lane the ego is in (``held``'s first)
    only the ones ahead: a car behind the ego in its lane, or one that cuts in later, is responsible for the gap it
    makes; a car in a lane the ego is entering is the ego's to keep clear of, ahead or behind. ``carried_followers``:
    {row: (lane, highest position [m] per frame)}, the follower bounds a kept plan drew, kept in that lane; ``ego_set``
    (holds, frames): the plans' set-points [m/s] (:func:`plan_set_points`; the linear drivers' MOBIL criterion reads
    it); ``held``: the lanes the ego holds (default: its lane and target lane now; a kept plan's tail passes those it
    held when verified, :attr:`Plan.held`)."""
    t = dyn.times
    half = 0.5 * (state.length + state.ego_length)
    ahead = state.x >= state.ego_x
    # Drivers that change lane by MOBIL with a formula the criterion can be bounded for: IDM, or the linear model
    # with gains ≥ 0 (linear_set_point_bound).
    mobil = (~np.isfinite(state.linear_speed_gain) | linear_set_point_bound(state)) & state.can_change_lane
    mobil &= ~state.crashed & np.isfinite(state.max_braking_imposed)
    holding = held_lanes(state, held)
    in_lane, held = holding[0], set(holding)  # the lane the ego is in, not one it is entering
    n_fb = ego_x.shape[0]
    frames = t <= (t[-1] if until_frame is None else t[min(max(until_frame, 0), t.size - 1)])
    worst = np.full((state.n, n_fb), np.inf)
    for lane, until in lanes:
        held_lane = lane in held
        entry = np.repeat(sets.entry[:, lane][:, None], n_fb, axis=1)  # (cars, holds)
        law = np.flatnonzero(held_lane & ahead & mobil & ~sets.now[:, lane])
        if law.size:
            entry[law] = np.maximum(entry[law], _permit_entry(state, dyn, sets, law, ego_x, ego_v, ego_set))
        count = np.isfinite(entry).any(axis=1)
        if held_lane:  # cut-ins, and cars behind in the ego's lane: theirs to avoid
            count &= sets.now[:, lane] & (ahead | (lane != in_lane))
        # A follower: its own lane is this one (highway-env's IDM sees the ego as its leader only then).
        following = held_lane & ~ahead & (state.lane_of(state.y, dyn.lanes_count, dyn.lane_width) == lane)
        in_time = frames & (t <= until)
        for i in np.flatnonzero(count):
            window = (t[None, :] >= entry[i][:, None]) & in_time[None, :]  # (holds, frames)
            if not window.any():
                continue
            high = sets.x_hi[i][None, :]
            if following[i]:
                react = np.maximum(onset + dyn.follower_reaction, 0.0)  # a past reaction: braking from now
                high = np.minimum(high, follower_bound(state, i, react, t))
            carried = (carried_followers or {}).get(int(i))
            if carried is not None and carried[0] == lane:
                high = np.minimum(high, carried[1][None, :])
            gap = np.maximum(sets.x_lo[i][None, :] - ego_x - half[i], ego_x - high - half[i])
            worst[i] = np.minimum(worst[i], np.where(window, gap, np.inf).min(axis=1))
    return worst


def follower_bound(state: RoadState, i: int, react: np.ndarray, t: np.ndarray) -> np.ndarray:
    """(holds, frames) [m] the highest position of car ``i`` reacting at ``react`` [s] (per plan): its envelope's
    top until then, then braking at its limit from the speed it may have reached."""
    speed = path_speed(state)[i : i + 1]  # along its path: at least its speed along the road
    v0 = np.maximum(speed, 0.0)
    a, b = np.array([state.accel_max[i]]), np.array([state.brake_max[i]])
    v_min, v_max = speed_bounds(speed, state.target_speed[i : i + 1], np.isfinite(state.linear_speed_gain[i : i + 1]))
    r = react[:, None]
    d1, _ = rise(v0, a, v_max, np.minimum(t[None, :], r))
    d_r, v_r = rise(v0, a, v_max, r)
    d2, _ = fall(v_r, b, np.minimum(v_min, 0.0), np.maximum(t[None, :] - r, 0.0))
    return state.x[i] + np.where(t[None, :] <= r, d1, d_r + d2)
