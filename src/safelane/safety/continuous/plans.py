"""Committed plans for an ego under continuous controls, and their verification (the numpy reference).

A **plan** is a sequence of actions, one per decision, ending with the ego stopped inside one lane: the action
for one decision, then the fail-safe (:func:`~safelane.safety.continuous.controls.fail_safe_action`) — holding the
speed ``hold ∈ {0..3}`` decisions, then braking to a standstill — steering toward the centre of the **plan's lane**,
the lane nearest the ego after the first decision (a lateral move is finished or aborted there). Its trajectory is
the ego's exact one (:func:`~safelane.safety.continuous.controls.roll_out`).

A plan is **verified** against the other cars' reachable sets of the committed rule
(:mod:`safelane.safety.committed.sets`) as a meta-action plan is (:func:`safelane.safety.committed.plans.car_gaps`):

* the lanes it occupies are those its body, turned by its heading, overlaps at some frame of the horizon or one
  frame later at that frame's velocity (highway-env's collision test also moves both bodies one frame on at
  their velocity, along their heading: a hard turn's next frame is not where that puts the body), each until the
  frame after the last such frame, counted from now (as a lane change's target lane is);
* the lanes it holds are the ego's lane now (a car behind it there is that driver's to avoid) and the plan's lane
  (whose followers react to its braking, the follower law); every other lane it overlaps is one it enters;
* the ego's body turned by its heading reaches further along the road than half its length, and the collision
  test's one frame on at the velocity puts it elsewhere along the road than the next frame: both excesses are
  taken off each gap; the ego's centre stays on the road at every frame (highway-env's ``on_road``), and it stands still
  by the horizon's end.

Pure maths: no simulator, no highway-env, no torch.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from safelane.safety.committed.plans import car_gaps
from safelane.safety.committed.sets import CarSets
from safelane.safety.continuous.controls import (
    STOPPED_SPEED,
    ControlLimits,
    EgoState,
    fail_safe_action,
    physical,
    roll_out,
)
from safelane.safety.world import MAX_HOLD_DECISIONS, Dynamics, RoadState

EGO_WIDTH = 2.0
"""[m] The ego's body width (highway-env's ``Vehicle.WIDTH``), for the lanes it overlaps and its reach along the
road when turned."""


@dataclass(frozen=True)
class ControlPlan:
    """A committed plan under continuous controls: ``actions`` (decisions, 2) float32 in [−1, 1], one per decision
    from now until the ego stands; the ego's ``x`` [m] along the road per frame of the horizon (frames + 1, the
    first now); the ``lanes`` it occupies, each with the time [s] until which it does; its braking ``onset`` [s]
    from now; the lanes it ``held`` when verified (the ego's lane then, first, and the plan's lane); ``frames``: the
    frames of the horizon it was verified over; ``gap`` [m]: its worst gap (verified: ≥ the margin)."""

    actions: np.ndarray
    x: np.ndarray
    lanes: tuple[tuple[int, float], ...]
    onset: float
    held: tuple[int, int]
    frames: int
    gap: float

    def next_action(self) -> np.ndarray:
        """The action of the plan's next decision (after the one it was drawn with)."""
        return self.actions[min(1, len(self.actions) - 1)].copy()

    def tail_actions(self) -> np.ndarray:
        """The plan's actions from the next decision on."""
        return self.actions[1:] if len(self.actions) > 1 else self.actions[-1:]


@dataclass(frozen=True)
class Trajectory:
    """The ego under a sequence of actions: (frames + 1, 4) its (x, y, heading, speed) per frame, the first now,
    and the actions (decisions, 2) float32."""

    states: np.ndarray
    actions: np.ndarray


def ego_state(state: RoadState) -> EgoState:
    """The ego's :class:`EgoState` in ``state``."""
    return EgoState(float(state.ego_x), float(state.ego_y), float(state.ego_heading), float(state.ego_speed))


def plan_lane(y: float, dyn: Dynamics) -> int:
    """The lane whose centre is nearest the lateral position ``y`` [m] (a tie: the one to the left, higher
    index), on the road."""
    return int(min(max(math.floor(y / dyn.lane_width + 0.5), 0), dyn.lanes_count - 1))


def _drive(state: RoadState, dyn: Dynamics, limits: ControlLimits,
           action_at: Callable[[int, EgoState], np.ndarray]) -> Trajectory:  # fmt: skip
    """The ego's trajectory over the horizon from ``state``, decision ``d`` holding ``action_at(d, ego)`` (``ego``:
    its state at the decision's start)."""
    f, dt = dyn.frames_per_decision, dyn.frame_dt
    decisions = dyn.horizon_decisions
    states = np.empty((decisions * f + 1, 4))
    ego = ego_state(state)
    states[0] = (ego.x, ego.y, ego.heading, ego.speed)
    actions = np.empty((decisions, 2), dtype=np.float32)
    for d in range(decisions):
        actions[d] = action_at(d, ego)
        acceleration, steering = physical(actions[d], limits)
        frames = states[1 + d * f : 1 + (d + 1) * f]
        ego = roll_out(ego, acceleration, steering, f, dt, limits, state.ego_length, frames)
    return Trajectory(states, actions)


def plan_trajectory(state: RoadState, dyn: Dynamics, limits: ControlLimits, action: np.ndarray, hold: int
                    ) -> tuple[Trajectory, int]:  # fmt: skip
    """(trajectory, the plan's lane) of the plan that applies ``action`` (2,) for one decision, holds its speed
    ``hold`` decisions and then brakes to a standstill, steering for the plan's lane (module docstring)."""
    lane = -1

    def action_at(d: int, ego: EgoState) -> np.ndarray:
        nonlocal lane
        if d == 0:
            return np.asarray(action, dtype=np.float32)
        if lane < 0:  # the lane nearest the ego after the first decision
            lane = plan_lane(ego.y, dyn)
        return fail_safe_action(ego, lane * dyn.lane_width, d > hold, dyn, limits, state.ego_length)

    return _drive(state, dyn, limits, action_at), lane


def replay_trajectory(state: RoadState, dyn: Dynamics, limits: ControlLimits, actions: np.ndarray) -> Trajectory:
    """The ego's trajectory over the horizon under ``actions`` (decisions, 2) from now, the last one held for
    the decisions after them (a kept plan's tail: it ends stopped, and its last braking action keeps it there)."""
    return _drive(state, dyn, limits, lambda d, _: actions[min(d, len(actions) - 1)])


def _swept_across(y: float, heading: float, speed: float, dt: float, length: float) -> tuple[float, float]:
    """(low, high) [m] across the road of the ego's body at a frame, turned by ``heading``, and of the same body
    moved on by its velocity (``speed`` along the heading) for ``dt`` [s]: where highway-env's collision test looks
    for it (``are_polygons_intersecting`` with each body's displacement over the frame)."""
    reach = abs(0.5 * length * math.sin(heading)) + abs(0.5 * EGO_WIDTH * math.cos(heading))
    sweep = speed * math.sin(heading) * dt
    return y - reach + min(sweep, 0.0), y + reach + max(sweep, 0.0)


def occupied_lanes(trajectory: Trajectory, dyn: Dynamics, length: float) -> tuple[tuple[int, float], ...]:
    """The lanes the ego's body, turned by its heading and swept one frame on at its velocity
    (:func:`_swept_across`), overlaps at some frame of ``trajectory``, each with the time [s] of the frame after the
    last such frame (the swept body is checked against that frame's sets; at the horizon's end: inf). Frame by
    frame with libm's functions, as the compiled engine computes it."""
    t = dyn.times
    half = 0.5 * dyn.lane_width
    last = [-1] * dyn.lanes_count
    final = t.size - 1
    for j, (_, y, heading, speed) in enumerate(trajectory.states.tolist()):
        low, high = _swept_across(y, heading, speed, dyn.frame_dt, length)
        for lane in range(dyn.lanes_count):
            centre = lane * dyn.lane_width
            if high > centre - half and low < centre + half:
                last[lane] = min(j + 1, final)
    return tuple((lane, math.inf if j == final else float(t[j])) for lane, j in enumerate(last) if j >= 0)


def reach_excess(trajectory: Trajectory, dyn: Dynamics, length: float) -> float:
    """[m] How far the ego's body reaches along the road beyond where the gaps put it, at worst over
    ``trajectory``: turned by its heading, beyond half its length; and moved one frame on at its velocity (the
    collision test's look ahead, along its heading), away from the next frame's position (the gaps are checked
    at both frames; the relative motion between them is linear, so its worst is at one end)."""
    states = trajectory.states.tolist()
    dt = dyn.frame_dt
    along = 0.0
    drift = 0.0
    for j, (x, _, heading, speed) in enumerate(states):
        along = max(along, abs(0.5 * length * math.cos(heading)) + abs(0.5 * EGO_WIDTH * math.sin(heading)))
        if j + 1 < len(states):
            drift = max(drift, abs(x + speed * math.cos(heading) * dt - states[j + 1][0]))
    return max(along - 0.5 * length, 0.0) + drift


def on_road(trajectory: Trajectory, dyn: Dynamics) -> bool:
    """The ego's centre stays within the road's edges at every frame (highway-env's ``on_road`` on its closest
    lane)."""
    y = trajectory.states[:, 1]
    half = 0.5 * dyn.lane_width
    return bool(((y >= -half) & (y <= (dyn.lanes_count - 1) * dyn.lane_width + half)).all())


def braking_onset(trajectory: Trajectory, dyn: Dynamics, limits: ControlLimits, hold: int) -> float:
    """[s] When the plan first brakes: now when its first action decelerates, else after the hold."""
    acceleration, _ = physical(trajectory.actions[0], limits)
    return 0.0 if acceleration < 0.0 else (1 + hold) * dyn.decision_period


def trajectory_gap(
    state: RoadState, dyn: Dynamics, sets: CarSets, trajectory: Trajectory, onset: float, held: tuple[int, int],
    until_frame: int | None = None, carried_followers: dict[int, tuple[int, np.ndarray]] | None = None,
) -> tuple[np.ndarray, tuple[tuple[int, float], ...]]:  # fmt: skip
    """((cars,) each car's worst gap [m] to ``trajectory``, less the ego's excess reach when turned; the lanes it
    occupies). A trajectory that leaves the road, or still moves at the horizon's end, gets −inf for every car
    (and −inf alone when there is no car)."""
    lanes = occupied_lanes(trajectory, dyn, state.ego_length)
    ego_x = trajectory.states[None, :, 0]
    gaps = car_gaps(state, dyn, sets, ego_x, np.array([onset]), list(lanes), until_frame, carried_followers,
                    held)[:, 0] - reach_excess(trajectory, dyn, state.ego_length)  # fmt: skip
    moving = abs(trajectory.states[-1, 3]) > STOPPED_SPEED and until_frame is None
    if not on_road(trajectory, dyn) or moving:
        gaps = np.full(max(gaps.size, 1), -np.inf)
    return gaps, lanes


def verify_action(state: RoadState, dyn: Dynamics, limits: ControlLimits, sets: CarSets, action: np.ndarray
                  ) -> ControlPlan | None:  # fmt: skip
    """The first plan starting with ``action`` (2,) float32 that keeps the margin to every car (holds 0 to 3, in
    that order), or None: the action is verified when there is one."""
    best = None
    for hold in range(MAX_HOLD_DECISIONS + 1):
        trajectory, lane = plan_trajectory(state, dyn, limits, action, hold)
        held = (int(state.ego_lane), lane)
        onset = braking_onset(trajectory, dyn, limits, hold)
        gaps, lanes = trajectory_gap(state, dyn, sets, trajectory, onset, held)
        gap = float(gaps.min()) if gaps.size else math.inf
        if gap >= dyn.margin:
            best = ControlPlan(trajectory.actions, trajectory.states[:, 0].copy(), lanes, onset, held,
                               dyn.times.size - 1, gap)  # fmt: skip
            break
    return best
