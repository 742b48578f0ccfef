"""The road snapshot in the lane coordinates the safety rules read (metres, m/s, radians from the road's heading).

One projection (:func:`lane_frame`) for every rule: the one-decision rule's :func:`road_state` (the bodies within
:data:`~safelane.safety.world.RELEVANCE_RANGE` of the ego) and the committed rule's :func:`whole_road_state` (every
body at a finite position); the compiled one-decision kernel projects inside itself, bit for bit as
:func:`road_state` does, on an axis-aligned road. Pure maths: no simulator.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from safelane.core.snapshot import DRIVER_FIELDS, RoadSnapshot
from safelane.safety.world import RELEVANCE_RANGE, RoadState


class LaneFrame(NamedTuple):
    """Bodies in lane coordinates: along the road ``x`` [m], across it ``y`` [m], their velocity ``vx``/``vy``
    [m/s] and ``heading`` [rad] from the road's, wrapped to [−π, π]."""

    x: np.ndarray
    y: np.ndarray
    vx: np.ndarray
    vy: np.ndarray
    heading: np.ndarray


def lane_frame(snap: RoadSnapshot, bodies: np.ndarray) -> LaneFrame:
    """The bodies ``bodies`` (snapshot indices) of ``snap`` in lane coordinates. The positions are projected over
    ``bodies`` as given (a matrix product rounds by the rows it is given: callers that keep the bits of an earlier
    projection pass the same rows and select from the result)."""
    pos = snap.position[bodies] - snap.lane_origin
    heading = snap.heading[bodies] - snap.lane_heading
    speed = snap.speed[bodies]
    return LaneFrame(
        x=pos @ snap.lane_direction,
        y=pos @ snap.lane_lateral,
        vx=speed * np.cos(heading),
        vy=speed * np.sin(heading),
        heading=np.arctan2(np.sin(heading), np.cos(heading)),
    )


def _relevant(x: np.ndarray, ego_x: float) -> np.ndarray:
    """Which bodies at ``x`` [m] along the road the one-decision rule considers: within RELEVANCE_RANGE of the ego."""
    return (np.abs(x - ego_x) < RELEVANCE_RANGE) & np.isfinite(x)


def _ego_x(snap: RoadSnapshot) -> float:
    """[m] The ego's position along the road."""
    return float((snap.position[snap.ego] - snap.lane_origin) @ snap.lane_direction)


def road_state_bodies(snap: RoadSnapshot) -> np.ndarray:
    """The snapshot indices of the bodies :func:`road_state` keeps, in its order (its arrays' rows)."""
    others = snap.others(vehicles_only=False)
    if not others.size:
        return others
    x = (snap.position[others] - snap.lane_origin) @ snap.lane_direction
    return others[_relevant(x, _ego_x(snap))]


def road_state(snap: RoadSnapshot, ego_speed_magnitude: bool = True) -> RoadState:
    """The scene around the ego in lane coordinates (metres, m/s) for the safety model.

    ``ego_speed_magnitude`` (the rule's option): the ego's speed is its speed controller's (highway-env's
    ``vehicle.speed``: what MDPVehicle's set-points and its P-controller act on, exact for the model's ego
    trajectories, and along its path an upper bound on its progress along the road); false: the component along
    the road, which the heading of a lane change lowers (the rule then predicted a shorter stop, by up to 6.7 m in
    the claim grid's lane changes, and picked a lower SLOWER set-point than highway-env's).

    Only bodies within :data:`~safelane.safety.world.RELEVANCE_RANGE` [m] of the ego along the road are included —
    the ones :func:`safelane.safety.one_decision.reference.evaluate` considers.
    """
    others = snap.others(vehicles_only=False)
    ego_x = float((snap.position[snap.ego] - snap.lane_origin) @ snap.lane_direction)
    if others.size:
        frame = lane_frame(snap, others)  # over every other body, then the relevant ones (the bits road_state had)
        near = np.flatnonzero(_relevant(frame.x, ego_x))
        frame = LaneFrame(*(a[near] for a in frame))
    else:
        near = np.zeros(0, dtype=int)
        frame = LaneFrame(*(np.zeros(0) for _ in LaneFrame._fields))
    return _state(snap, ego_speed_magnitude, frame, others[near])


def _state(snap: RoadSnapshot, ego_speed_magnitude: bool, frame: LaneFrame, nearby: np.ndarray) -> RoadState:
    """The :class:`RoadState` of ``snap``'s ego and of the bodies ``nearby`` (snapshot indices), ``frame`` their
    lane coordinates (:func:`road_state` documents ``ego_speed_magnitude``)."""
    e = snap.ego
    ego_rel = snap.position[e] - snap.lane_origin
    ego_x = float(ego_rel @ snap.lane_direction)
    x, y, vx, vy, heading = frame
    ego_heading = float(snap.heading[e]) - snap.lane_heading
    return RoadState(
        ego_x=ego_x,
        ego_y=float(ego_rel @ snap.lane_lateral),
        ego_speed=float(snap.speed[e]) if ego_speed_magnitude else float(snap.speed[e] * math.cos(ego_heading)),
        ego_lane=int(snap.lane[e]),
        ego_target_lane=int(snap.target_lane[e]),
        ego_target_speed=snap.ego_target_speed,
        ego_speed_index=snap.ego_speed_index,
        ego_length=float(snap.length[e]),
        ego_heading=ego_heading,
        x=x,
        y=y,
        vx=vx,
        vy=vy,
        heading=heading,
        length=snap.length[nearby],
        crashed=snap.crashed[nearby],
        target_speed=snap.target_speed[nearby],
        speed_limit=snap.speed_limit,
        **{name: getattr(snap, name)[nearby] for name in DRIVER_FIELDS},
    )


def whole_road_state(snap: RoadSnapshot, ego_speed_magnitude: bool = True) -> tuple[RoadState, np.ndarray]:
    """The road state with every other body at a finite position (no relevance range: that is the one-decision
    rule's, not a bound on a reachable set) and the snapshot index of each row (the committed rule's)."""
    others = snap.others(vehicles_only=False)
    bodies = others[np.isfinite(snap.longitudinal(snap.position[others]))]
    return _state(snap, ego_speed_magnitude, lane_frame(snap, bodies), bodies), bodies
