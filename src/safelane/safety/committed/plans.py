"""The committed rule's numpy reference: plans, and each plan's worst gap to every car's reachable set.

* A **plan** (:class:`Plan`) is a sequence of ego set-points [m/s] and target lanes, one per decision, ending
  with the ego at a standstill. The family: the action, hold the set-point ``k ∈ {0..3}`` decisions, then SLOWER
  at every decision (the ego's exact trajectory: :func:`safelane.safety.ego.ego_trajectories`; the onsets and the
  lanes held: :mod:`safelane.safety.committed.plan_family`).
* Every other car's **reachable set** (:class:`~safelane.safety.committed.sets.CarSets`) comes from
  :mod:`safelane.safety.committed.sets`.
* Laws apply under a plan where they nest with the plan kept: the drivers' acceleration laws toward their
  set-points (in the sets) and followers reacting ``ρ`` after the plan's braking onset — an assumption, not IDM's
  law: a follower that does not brake so is named (``unbraked_followers``) (:func:`car_gaps`). A car cutting into
  a lane the ego holds does not count at all (below), so no lane-change law is needed for it.
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
from safelane.safety.committed.sets import CarSets, fall, path_speed, rise, speed_bounds
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
    f, horizon = dyn.frames_per_decision, dyn.horizon_decisions
    decisions = set_points[: horizon * f : f].tolist()  # the set-point at each decision's first frame
    stop = next((d for d in range(hold + 1, len(decisions)) if decisions[d] == 0.0), len(decisions) - 1)
    points = decisions[: stop + 1]
    occupied = tuple(action_lanes(state, dyn, action))
    lane = occupied[-1][0]
    onset = float(onsets(dyn, action)[hold])
    return Plan(action, hold, tuple(points), (lane,) * len(points), occupied, onset, horizon * f,
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
        gaps = car_gaps(state, dyn, sets, ego_x[a], onsets(dyn, int(a)), action_lanes(state, dyn, int(a)))
        worst[a] = gaps.min(axis=0) if gaps.shape[0] else np.inf
    return worst, ego_x, ego_v, set_points


def plan_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, onset: np.ndarray, lanes: Lanes,
    until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
) -> np.ndarray:  # fmt: skip
    """(holds,) the worst bumper-to-bumper gap [m] of plans whose ego moves as ``ego_x`` (holds, frames) over every
    car (inf: no car in reach): the least of :func:`car_gaps`, which documents the arguments."""
    gaps = car_gaps(state, dyn, sets, ego_x, onset, lanes, until_frame, carried_followers)
    return gaps.min(axis=0) if gaps.shape[0] else np.full(ego_x.shape[0], np.inf)


def car_gaps(
    state: RoadState, dyn: Dynamics, sets: CarSets, ego_x: np.ndarray, onset: np.ndarray, lanes: Lanes,
    until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
    held: tuple[int, ...] | None = None,
) -> np.ndarray:  # fmt: skip
    """(cars, holds) each car's worst bumper-to-bumper gap [m] to plans whose ego moves as ``ego_x`` (holds,
    frames) and brakes first at ``onset`` [s] (holds,), occupying ``lanes``, at every frame up to ``until_frame``
    (default: the horizon's end); inf where the car never reaches the plan. The cars below the margin are the ones a
    plan fails on (a lapse names them).

    In each lane, from each car's entry time on, the car's interval ``[x_lo, x_hi]`` must stay clear of the ego by
    ``margin`` on one side or the other at every frame (a car that may be on either side conflicts). In a lane the
    ego holds, only the cars in that lane now (or moving into it) count, and of those in the lane the ego is in
    (``held``'s first) only the ones ahead: a car behind the ego in its lane, or one that cuts in later, is
    responsible for the gap it makes; a car in a lane the ego is entering is the ego's to keep clear of, ahead or
    behind. Law: a car in a lane the ego holds behind the ego now follows it: accelerates at most until
    ``follower_reaction`` after the plan's braking onset, then brakes (:func:`follower_bound`).
    ``carried_followers``: {row: (lanes, highest position [m] per frame)}, the follower bounds a kept plan drew,
    applied in the lanes of the bitmask ``lanes`` (:func:`lane_bit`: those the car followed the ego in); ``held``:
    the lanes the ego holds (default: its lane and target lane now; a kept plan's tail passes those it held when
    verified, :attr:`Plan.held`)."""
    t = dyn.times
    half = 0.5 * (state.length + state.ego_length)
    ahead = state.x >= state.ego_x
    holding = held_lanes(state, held)
    in_lane, held = holding[0], set(holding)  # the lane the ego is in, not one it is entering
    n_fb = ego_x.shape[0]
    frames = t <= (t[-1] if until_frame is None else t[min(max(until_frame, 0), t.size - 1)])
    worst = np.full((state.n, n_fb), np.inf)
    for lane, until in lanes:
        held_lane = lane in held
        entry = sets.entry[:, lane]  # (cars,)
        count = np.isfinite(entry)
        if held_lane:  # cut-ins, and cars behind in the ego's lane: theirs to avoid
            count &= sets.now[:, lane] & (ahead | (lane != in_lane))
        # A follower: its own lane is this one (highway-env's IDM sees the ego as its leader only then).
        following = held_lane & ~ahead & (state.lane_of(state.y, dyn.lanes_count, dyn.lane_width) == lane)
        in_time = frames & (t <= until)
        for i in np.flatnonzero(count):
            window = (t >= entry[i]) & in_time  # (frames,), the same for every plan
            if not window.any():
                continue
            high = sets.x_hi[i][None, :]
            if following[i]:
                react = np.maximum(onset + dyn.follower_reaction, 0.0)  # a past reaction: braking from now
                high = np.minimum(high, follower_bound(state, i, react, t))
            carried = (carried_followers or {}).get(int(i))
            if carried is not None and carried[0] >> lane & 1:
                high = np.minimum(high, carried[1][None, :])
            gap = np.maximum(sets.x_lo[i][None, :] - ego_x - half[i], ego_x - high - half[i])
            worst[i] = np.minimum(worst[i], np.where(window, gap, np.inf).min(axis=1))
    return worst


def lane_bit(lane: int) -> int:
    """The bitmask of one lane, as the carried follower bounds name the lanes they apply in."""
    return 1 << int(lane)


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
