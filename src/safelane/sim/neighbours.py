"""Vectorised drop-ins for highway-env's two hottest loops, validated to give identical episodes.

highway-env spends most of a step in ``Road.neighbour_vehicles``: every vehicle, every physics
frame, loops in Python over every other vehicle and converts its position to lane coordinates
(ANCHORS.md: 49–62 % of a step). Within one ``Road.act()`` phase no vehicle moves, so the positions
can be gathered once per phase into an array and every query answered with a few numpy operations.

The replacement reproduces the original exactly — same lane test (``on_lane`` with a 1 m margin),
same tie-breaking (the last of equal leaders, the first of equal followers) — and falls back to
highway-env's own code for anything it does not cover (connected lane segments, curved lanes,
calls outside ``Road.act``).

The second hot loop is ``Road.step``'s collision check over every pair of vehicles (``highway-v0``, the
``paper`` preset, checks all 1 225 pairs of 50 vehicles at 15 Hz: a third of its step). highway-env
first discards a pair by a spherical test (centres farther apart than half the diagonals plus the
first vehicle's travel in ``dt``); that test is evaluated here for all pairs at once, with a 1 µm
margin so that floating-point differences can only keep a pair, and highway-env's own
``handle_collisions`` runs, in its order, on every pair kept. A discarded pair has no effect in
highway-env either, so the outcome is the same. It is opt-in per road: :func:`enable` marks a road; other roads in
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
_original_step = Road.step
SPHERE_MARGIN = 1e-6  # [m] pairs this close to the spherical test's threshold are checked by highway-env


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


def _step(self: Road, dt: float) -> None:
    if not getattr(self, "_safelane_vectorized", False):
        _original_step(self, dt)
        return
    vehicles = self.vehicles
    for vehicle in vehicles:
        vehicle.step(dt)
    n = len(vehicles)
    if n > 1:
        positions = np.array([v.position for v in vehicles], dtype=float)
        diagonals = np.array([v.diagonal for v in vehicles], dtype=float)
        speeds = np.array([v.speed for v in vehicles], dtype=float)
        delta = positions[None, :, :] - positions[:, None, :]
        distance = np.sqrt(delta[..., 0] ** 2 + delta[..., 1] ** 2)
        # Row i is highway-env's ``self`` (the earlier vehicle): its travel widens the sphere.
        reach = (diagonals[:, None] + diagonals[None, :]) / 2 + speeds[:, None] * dt
        kept = np.triu(distance <= reach + SPHERE_MARGIN, k=1)
    for i, vehicle in enumerate(vehicles):
        if n > 1:
            for j in np.flatnonzero(kept[i]):
                vehicle.handle_collisions(vehicles[j], dt)
        for other in self.objects:
            vehicle.handle_collisions(other, dt)


Road.neighbour_vehicles = _neighbour_vehicles  # type: ignore[method-assign]
Road.act = _act  # type: ignore[method-assign]
Road.step = _step  # type: ignore[method-assign]


def enable(road: Road, on: bool = True) -> None:
    """Use the vectorised neighbour search and collision pre-check on ``road`` (a highway-env ``Road``)."""
    road._safelane_vectorized = on  # type: ignore[attr-defined]
