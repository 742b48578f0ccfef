"""A vectorised drop-in for highway-env's hottest function, validated to give identical episodes.

highway-env spends most of a step in ``Road.neighbour_vehicles``: every vehicle, every physics
frame, loops in Python over every other vehicle and converts its position to lane coordinates
(ANCHORS.md: 49–62 % of a step). Within one ``Road.act()`` phase no vehicle moves, so the positions
can be gathered once per phase into an array and every query answered with a few numpy operations.

The replacement reproduces the original exactly — same lane test (``on_lane`` with a 1 m margin),
same tie-breaking (the last of equal leaders, the first of equal followers) — and falls back to
highway-env's own code for anything it does not cover (connected lane segments, curved lanes,
calls outside ``Road.act``). It is opt-in per road: :func:`enable` marks a road; other roads in
the same process are untouched. ``tests/test_fastsim.py`` checks that whole episodes are identical,
bit for bit, with and without it.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road
from highway_env.vehicle.objects import Landmark

_original_neighbour_vehicles = Road.neighbour_vehicles
_original_act = Road.act


def _act(self: Road) -> None:
    if not getattr(self, "_safelane_vectorized", False):
        _original_act(self)
        return
    self._safelane_cache = None
    self._safelane_in_act = True
    try:
        _original_act(self)
    finally:
        self._safelane_in_act = False
        self._safelane_cache = None


def _entities(road: Road) -> tuple[list[Any], np.ndarray, dict[int, int]]:
    cache = road._safelane_cache
    if cache is None:
        entities = [v for v in road.vehicles + road.objects if not isinstance(v, Landmark)]
        positions = np.array([v.position for v in entities], dtype=float).reshape(len(entities), 2)
        index = {id(v): i for i, v in enumerate(entities)}
        cache = road._safelane_cache = (entities, positions, index)
    return cache


def _neighbour_vehicles(self: Road, vehicle: Any, lane_index: Any = None) -> tuple[Any, Any]:
    if not getattr(self, "_safelane_in_act", False) or self.neighbour_vehicles_connected_lanes:
        return _original_neighbour_vehicles(self, vehicle, lane_index)
    lane_index = lane_index or vehicle.lane_index
    if not lane_index:
        return None, None
    lane = self.network.get_lane(lane_index)
    if type(lane) is not StraightLane:
        return _original_neighbour_vehicles(self, vehicle, lane_index)
    entities, positions, index = _entities(self)
    if not entities:
        return None, None
    s = lane.local_coordinates(vehicle.position)[0]
    delta = positions - lane.start
    # Same arithmetic as StraightLane.local_coordinates (np.dot of two 2-vectors), row by row.
    s_v = delta[:, 0] * lane.direction[0] + delta[:, 1] * lane.direction[1]
    lat = delta[:, 0] * lane.direction_lateral[0] + delta[:, 1] * lane.direction_lateral[1]
    on = (np.abs(lat) <= lane.width / 2 + 1) & (s_v >= -lane.VEHICLE_LENGTH) & (s_v < lane.length + lane.VEHICLE_LENGTH)
    own = index.get(id(vehicle))
    if own is not None:
        on[own] = False
    front = rear = None
    ahead = on & (s_v >= s)
    if ahead.any():
        best = s_v[ahead].min()
        front = entities[int(np.flatnonzero(ahead & (s_v == best))[-1])]
    behind = on & (s_v < s)
    if behind.any():
        best = s_v[behind].max()
        rear = entities[int(np.flatnonzero(behind & (s_v == best))[0])]
    return front, rear


Road.neighbour_vehicles = _neighbour_vehicles  # type: ignore[method-assign]
Road.act = _act  # type: ignore[method-assign]


def enable(road: Road, on: bool = True) -> None:
    """Use the vectorised neighbour search on ``road`` (a highway-env ``Road``)."""
    road._safelane_vectorized = on  # type: ignore[attr-defined]
