"""Scripted adversaries for the stress suite: drivers that push (or break) the safety model's limits.

Each is a highway-env ``IDMVehicle`` subclass; :func:`add_adversary` places one relative to the ego
right after a reset (``traffic.adversary`` in the config), using the road's own RNG so that a seed
gives the same scene.

* ``brake`` — :class:`HardBraker`: the leader ahead of the ego, in its lane, brakes at full
  ``ACC_MAX`` (6 m/s²) at a random time and stays stopped: inside the model's worst case.
* ``cut_in`` — :class:`CutInVehicle`: a car in an adjacent lane that changes into the ego's lane as
  soon as it is just ahead of it, with a minimal gap, *ignoring* MOBIL's safety criterion: outside
  the model (a driver breaking its own rule).
* ``stopped`` — :class:`StoppedVehicle`: a broken-down car standing in the ego's lane ahead.
* ``cut_in_mobil`` — :class:`MobilCutInVehicle`: a car in an adjacent lane that changes into the ego's
  lane just ahead of it the moment MOBIL's *safety* criterion allows (the ego, its new follower, would
  brake no harder than ``LANE_CHANGE_MAX_BRAKING_IMPOSED`` by the car's own IDM), with no incentive
  criterion: the most aggressive cut-in inside the model.
"""

from __future__ import annotations

from typing import Any

from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.kinematics import Vehicle

ADVERSARIES = ("none", "brake", "cut_in", "stopped", "cut_in_mobil")


class HardBraker(IDMVehicle):
    """Drives as IDM until ``brake_at`` [s] after spawning, then brakes at ``ACC_MAX`` to a standstill."""

    brake_at: float = 5.0  # [s]
    timer_total: float = 0.0  # [s] since spawning

    def act(self, action: Any = None) -> None:
        if self.timer_total < self.brake_at:
            super().act(action)
            return
        self.enable_lane_change = False
        steering = self.steering_control(self.target_lane_index)
        Vehicle.act(self, {"steering": steering, "acceleration": -self.ACC_MAX if self.speed > 0 else 0.0})

    def step(self, dt: float) -> None:
        self.timer_total += dt
        super().step(dt)
        if self.timer_total >= self.brake_at and self.speed < 0:
            self.speed = 0.0  # brakes hold the car: no reversing


class CutInVehicle(IDMVehicle):
    """Changes into ``victim``'s lane as soon as it is ahead of it by less than ``trigger_gap`` [m]."""

    victim: Any = None
    trigger_gap: float = 8.0  # [m] bumper to bumper
    done_cut: bool = False

    def change_lane_policy(self) -> None:
        ego = self.victim
        if self.done_cut or ego is None:
            return
        if abs(ego.lane_index[2] - self.lane_index[2]) != 1:
            return
        gap = self.lane_distance_to(ego) * -1 - self.LENGTH
        if 0.0 < gap < self.trigger_gap:
            self.target_lane_index = ego.lane_index
            self.done_cut = True


class MobilCutInVehicle(IDMVehicle):
    """Changes into ``victim``'s lane, right in front of it, as soon as MOBIL's safety criterion holds:
    ``acceleration(ego_vehicle=victim, front_vehicle=self) >= -LANE_CHANGE_MAX_BRAKING_IMPOSED`` [m/s²],
    highway-env's ``new_following_pred_a`` test with the victim as the new follower. Once."""

    victim: Any = None
    done_cut: bool = False

    def change_lane_policy(self) -> None:
        ego = self.victim
        if self.done_cut or ego is None or abs(ego.lane_index[2] - self.lane_index[2]) != 1:
            return
        _, new_following = self.road.neighbour_vehicles(self, ego.lane_index)
        if new_following is not ego:  # only directly in front of the ego (ahead of it, nobody between)
            return
        if self.acceleration(ego_vehicle=ego, front_vehicle=self) < -self.LANE_CHANGE_MAX_BRAKING_IMPOSED:
            return
        self.target_lane_index = ego.lane_index
        self.done_cut = True


class StoppedVehicle(IDMVehicle):
    """A car standing still in its lane (never accelerates, never changes lane)."""

    def act(self, action: Any = None) -> None:
        Vehicle.act(self, {"steering": 0.0, "acceleration": 0.0})

    def step(self, dt: float) -> None:
        self.speed = 0.0
        super().step(dt)


def add_adversary(road: Any, ego: Any, kind: str) -> Vehicle | None:
    """Place one scripted adversary of ``kind`` (:data:`ADVERSARIES`) relative to ``ego``; returns it."""
    if kind == "none":
        return None
    if kind not in ADVERSARIES:
        raise ValueError(f"traffic.adversary: got {kind!r}; allowed: {', '.join(ADVERSARIES)}")
    rng = road.np_random
    lane_index = ego.lane_index
    lane = road.network.get_lane(lane_index)
    x = lane.local_coordinates(ego.position)[0]
    n_lanes = len(road.network.graph[lane_index[0]][lane_index[1]])
    if kind == "brake":
        dx, lane_id = float(rng.uniform(30.0, 50.0)), lane_index[2]
        vehicle: Vehicle = HardBraker(road, lane.position(x + dx, 0), 0.0, float(rng.uniform(22.0, 26.0)))
        vehicle.brake_at = float(rng.uniform(2.0, 20.0))
    elif kind == "stopped":
        dx, lane_id = float(rng.uniform(120.0, 250.0)), lane_index[2]
        vehicle = StoppedVehicle(road, lane.position(x + dx, 0), 0.0, 0.0)
        vehicle.enable_lane_change = False
    else:
        sides = [i for i in (lane_index[2] - 1, lane_index[2] + 1) if 0 <= i < n_lanes]
        lane_id = int(rng.choice(sides))
        side_lane = road.network.get_lane((*lane_index[:2], lane_id))
        dx = float(rng.uniform(40.0, 80.0))
        cls = CutInVehicle if kind == "cut_in" else MobilCutInVehicle
        vehicle = cls(road, side_lane.position(x + dx, 0), 0.0, float(rng.uniform(18.0, 22.0)))
        vehicle.victim = ego
    # Remove a vehicle already occupying that spot so the adversary does not spawn inside it.
    target_lane = road.network.get_lane((*lane_index[:2], lane_id))
    xa = target_lane.local_coordinates(vehicle.position)[0]
    for v in list(road.vehicles):
        if v is ego:
            continue
        s, lat = target_lane.local_coordinates(v.position)
        if abs(lat) < 2.0 and abs(s - xa) < 12.0:
            road.vehicles.remove(v)
    others = [v for v in road.vehicles if v is not ego]
    vehicle.check_collisions = others[0].check_collisions if others else True
    road.vehicles.append(vehicle)
    return vehicle
