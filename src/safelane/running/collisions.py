"""Collisions classified from geometry at the moment of impact, and against the rule's promise.

:func:`classify_collision` names the face that was hit: ``ego_hit_front`` (the ego drove into a vehicle
ahead in its lane), ``rear_ended`` (a vehicle behind drove into the ego) or ``side`` (lateral contact, i.e.
during a lane change). highway-env marks both vehicles ``crashed`` but records nobody's fault, and after the
impact it pushes the two bodies apart and lets the ego slide on, so the geometry at the end of a decision step
is unreliable; the simulator records the positions of the physics frame around the impact in the road
snapshot instead. :data:`COLLISION_CONTEXTS` names where a shielded episode's collision stands against the
rule's promise (the evaluation's tally decides it, step by step).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from safelane.core.snapshot import RoadSnapshot

COLLISION_KINDS: tuple[str, ...] = ("ego_hit_front", "rear_ended", "side")
"""Every value :func:`classify_collision` returns for a crashed ego."""

COLLISION_CONTEXTS: tuple[str, ...] = (
    "started_unsafe", "after_break", "from_safe_state", "after_fallback",
    "uncertified_start", "others_at_fault", "outside_model",
)  # fmt: skip
"""A shielded episode's collision, against the rule's promise (after an allowed action in a state with a
safe action, the next state has one again, while the others stay inside the model): ``started_unsafe``
— no state of the episode before the crash had a safe action (outside the promise: the scene was
spawned inside a crash); ``after_break`` — an invariant break came first (the hole is that break);
``from_safe_state`` — the action executed was allowed in a state with a safe action (a hole of the
rule itself; an unsafe choice the override replaced counts here, since the action executed was the allowed
one); ``after_fallback`` — anything else (an unsafe action executed without
override, or a crash right after a fallback state that no break led to).

The ``committed`` shield mode (a plan kept between decisions) names three more, checked first, in this order:
``uncertified_start`` — no state before the crash had a verified plan (the episode started uncertified and
stayed so: the committed mode's ``started_unsafe``, which it does not use); ``others_at_fault`` — the ego was
rear-ended or hit by a car that entered a lane the ego holds (the gap
that car made was its own to keep); ``outside_model`` — a car had left the set drawn for it before the crash:
the crash partner (also one rolling back, ``info["rolled_back"]``, or a follower ahead of the bound the plan drew
for it, ``info["unbraked_followers"]``, by the crash's own decision), or a car a lapse's kept plan failed on
(``info["lapse_escaped_cars"]``); the record names them: ``outside_model_cars``, by snapshot index. ``after_break``
then also counts a crash after a lapse (the kept plan no longer verified), and ``from_safe_state`` one after an
action with a verified plan. The other modes never report these three (0)."""

COMMITTED_CONTEXTS: tuple[str, ...] = ("uncertified_start", "others_at_fault", "outside_model")
"""The contexts only the ``committed`` shield mode reports (:data:`COLLISION_CONTEXTS`)."""


def collision_contexts(committed: bool) -> tuple[str, ...]:
    """The collision contexts a summary lists: the committed mode's (its three first, then ``after_break``,
    ``from_safe_state``, ``after_fallback``; never ``started_unsafe``) or the other modes' four."""
    if committed:
        return (*COMMITTED_CONTEXTS, "after_break", "from_safe_state", "after_fallback")
    return tuple(c for c in COLLISION_CONTEXTS if c not in COMMITTED_CONTEXTS)


def collision_kind(
    before: tuple[float, float],
    after: tuple[float, float],
    half_length: float,
    half_width: float,
) -> str:
    """Classify a contact from the other vehicle's lane-local offset (δs, δr) [m] relative to the ego,
    one physics frame before (``before``) and at (``after``) the impact; ``half_length`` /
    ``half_width`` [m] are the sums of the two bodies' longitudinal / lateral half-extents.

    The face that was hit is the axis along which the bodies came to overlap last. Entry times into
    overlap are linear over the frame; an axis already overlapping before the frame (or not closing,
    which a rotated body allows) entered "before". Lateral overlap first (or together) means a
    front/rear contact: ``ego_hit_front`` if the other was ahead (δs > 0), else ``rear_ended``;
    otherwise ``side``.
    """

    def entry(d0: float, d1: float, half: float) -> float:
        closing = abs(d0) - abs(d1)
        if abs(d0) < half or closing <= 0:
            return -math.inf
        return (abs(d0) - half) / closing

    (s0, r0), (s1, r1) = before, after
    if entry(r0, r1, half_width) > entry(s0, s1, half_length):
        return "side"
    return "ego_hit_front" if s0 > 0 else "rear_ended"


def _extents(length: float, width: float, heading: float) -> tuple[float, float]:
    """(longitudinal, lateral) half-extents [m] of a ``length`` × ``width`` body at ``heading`` [rad]
    relative to the lane."""
    c, s = abs(math.cos(heading)), abs(math.sin(heading))
    return length / 2 * c + width / 2 * s, length / 2 * s + width / 2 * c


def _lane_coordinates(snap: RoadSnapshot, lane: int, position: np.ndarray) -> tuple[float, float]:
    """(along, across) [m] of ``position`` in ``lane``'s own frame (highway-env's ``local_coordinates``)."""
    start = snap.lane_origin + snap.lane_lateral * (lane * snap.lane_width)
    delta = position - start
    return float(np.dot(delta, snap.lane_direction)), float(np.dot(delta, snap.lane_lateral))


def collision_partner(snap: RoadSnapshot) -> int | None:
    """The index of the body the ego crashed into: the crashed body nearest to the ego at the impact (the
    impact frame the simulator recorded, else the current geometry); None if the ego has not crashed or no
    partner is found."""
    if not snap.ego_crashed:
        return None
    e = snap.ego
    after = snap.impact_after if snap.impact_before is not None and snap.impact_after is not None else snap.position
    candidates = [i for i in range(min(snap.n, after.shape[0])) if i != e and snap.crashed[i]]
    if not candidates:
        return None
    # The first of equally near partners, as Python's min() picks.
    return min(candidates, key=lambda i: float(np.hypot(*(after[i] - after[e]))))


def classify_collision(snap: RoadSnapshot) -> str | None:
    """The kind of the ego's crash (one of :data:`COLLISION_KINDS`), or None if it has not crashed.

    The partner is the crashed body nearest to the ego at the impact; offsets are taken in the ego
    lane's local coordinates (the road is straight along x). Uses the impact frame the simulator
    recorded in the snapshot when there is one, else the current geometry.
    """
    if not snap.ego_crashed:
        return None
    e = snap.ego
    if snap.impact_before is not None and snap.impact_after is not None:
        before, after = snap.impact_before, snap.impact_after
    else:
        before = after = snap.position
    other = collision_partner(snap)
    if other is None:
        return "side"  # no partner found (not produced by highway-env's straight roads)
    lane = int(snap.lane[e])

    def offset(positions: np.ndarray) -> tuple[float, float]:
        s_e, r_e = _lane_coordinates(snap, lane, positions[e])
        s_o, r_o = _lane_coordinates(snap, lane, positions[other])
        return s_o - s_e, r_o - r_e

    lane_heading = snap.lane_heading
    ego_long, ego_lat = _extents(snap.length[e], snap.width[e], float(snap.heading[e]) - lane_heading)
    other_long, other_lat = _extents(snap.length[other], snap.width[other], float(snap.heading[other]) - lane_heading)
    return collision_kind(offset(before), offset(after), ego_long + other_long, ego_lat + other_lat)


SCENE_RANGE = 80.0
"""[m] The vehicles a scene lists (:func:`scene_near_ego`): within this distance of the ego along the road."""
BREAK_CLASSES: tuple[str, ...] = ("second_lane_cut_in", "adjacent_lane_change", "ego_lane_change", "other")
"""Every value :func:`break_class_of` returns."""
NEAR_CHANGE = 60.0
"""[m] How close along the road a lane-changing vehicle must be to count in :func:`break_class_of`."""


def scene_near_ego(snap: RoadSnapshot) -> tuple[dict[str, float], list[dict[str, float]]]:
    """The ego (lane, x [m], speed [m/s]) and the vehicles within :data:`SCENE_RANGE` of it (vehicle index, lane,
    x offset [m], speed [m/s]), sorted by lane then offset: what a counterexample's replay logs per decision."""
    e = snap.ego
    x0 = float(snap.position[e, 0])
    ego = {"lane": int(snap.lane[e]), "x": x0, "speed": float(snap.speed[e])}
    nearby = []
    for i in range(snap.n):
        dx = float(snap.position[i, 0]) - x0
        if i != e and abs(dx) <= SCENE_RANGE:
            nearby.append(
                {"vehicle": i, "lane": int(snap.lane[i]), "dx": round(dx, 2), "speed": round(float(snap.speed[i]), 2)}
            )
    nearby.sort(key=lambda v: (v["lane"], v["dx"]))
    return ego, nearby


def break_class_of(ego_lane_before: int, before: list[dict[str, Any]], ego_lane_after: int,
                   after: list[dict[str, Any]]) -> str:  # fmt: skip
    """The class of an invariant break from the scenes (:func:`scene_near_ego`) before and after its decision: a
    vehicle within :data:`NEAR_CHANGE` that came from two lanes away into the lane next to the ego
    (``second_lane_cut_in``); else one that changed lanes next to the ego (``adjacent_lane_change``); else the ego's
    own lane change (``ego_lane_change``); else ``other``."""
    lanes_before = {v["vehicle"]: v["lane"] for v in before}
    for v in after:
        was = lanes_before.get(v["vehicle"])
        if was is None or abs(v["dx"]) > NEAR_CHANGE:
            continue
        if abs(v["lane"] - ego_lane_after) == 1 and abs(was - ego_lane_before) >= 2:
            return "second_lane_cut_in"
    for v in after:
        was = lanes_before.get(v["vehicle"])
        if was is not None and was != v["lane"] and abs(v["dx"]) <= NEAR_CHANGE and abs(was - ego_lane_before) <= 1:
            return "adjacent_lane_change"
    if ego_lane_after != ego_lane_before:
        return "ego_lane_change"
    return "other"


def break_class_of_snapshots(before: RoadSnapshot, after: RoadSnapshot) -> str:
    """:func:`break_class_of` of the snapshots before and after a break's decision."""
    ego_before, near_before = scene_near_ego(before)
    ego_after, near_after = scene_near_ego(after)
    return break_class_of(int(ego_before["lane"]), near_before, int(ego_after["lane"]), near_after)
