"""safelane's traffic options, applied to highway-env's scene as it is built.

:class:`TrafficLayout` draws each other car's driver type from a mixture (``traffic.driver_mix``,
:mod:`safelane.sim.drivers`), spawns some vehicles behind the ego (``traffic.vehicles_behind``), places a
scripted adversary (``traffic.adversary``, :mod:`safelane.sim.adversaries`) and switches the road to
the numpy neighbour search (:mod:`safelane.sim.neighbours`, config ``neighbour_search``).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym

from safelane.core.drivers import DriverMix
from safelane.sim import neighbours
from safelane.sim.adversaries import add_adversary
from safelane.sim.drivers import DriverDraw, install_driver_mix


class TrafficLayout(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """safelane traffic options applied right after highway-env builds its scene.

    Also switches the road to :mod:`safelane.sim.neighbours`'s vectorised neighbour search when
    ``vectorized`` (config ``neighbour_search: numpy``), which gives identical episodes, faster.

    ``vehicles_behind = N`` removes the N vehicles farthest ahead and spawns N vehicles *behind* the
    ego with highway-env's own rules mirrored backwards: random lane and spacing from
    ``road.np_random`` (same spacing law as ``Vehicle.create_random``), speeds uniform in
    [0.7, 1.0]·speed limit so that some are faster than the ego. highway-env alone spawns the ego
    behind every other vehicle, so followers and cut-ins from behind never happen in the stock scene.

    ``driver_mix``: each other car's class is drawn from the mixture at spawn, highway-env's scene and the
    vehicles behind alike (:func:`safelane.sim.drivers.install_driver_mix`; behind the ego the type is drawn
    first, then lane, speed and gap, as ``create_random`` does it).
    """

    def __init__(
        self,
        env: gym.Env,
        vehicles_behind: int = 0,
        vectorized: bool = True,
        adversary: str = "none",
        driver_mix: DriverMix | None = None,
    ) -> None:
        gym.utils.RecordConstructorArgs.__init__(
            self, vehicles_behind=vehicles_behind, vectorized=vectorized, adversary=adversary, driver_mix=driver_mix
        )
        super().__init__(env)
        self.vehicles_behind = vehicles_behind
        self.vectorized = vectorized
        self.adversary = adversary
        self.drivers: DriverDraw | None = None
        if driver_mix is not None:
            self.drivers = install_driver_mix(self.env.unwrapped, driver_mix)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        neighbours.enable(self.env.unwrapped.road, self.vectorized)
        if self.vehicles_behind > 0:
            self._spawn_behind()
        if self.adversary != "none":
            base = self.env.unwrapped
            add_adversary(base.road, base.vehicle, self.adversary)
        return obs, info

    def _spawn_behind(self) -> None:
        base = self.env.unwrapped
        road, ego = base.road, base.vehicle
        others = [v for v in road.vehicles if v is not ego]
        n = min(self.vehicles_behind, len(others))
        if n == 0:
            return
        others.sort(key=lambda v: v.position[0])
        vehicle_cls = type(others[0])
        check_collisions = others[0].check_collisions
        for v in others[-n:]:
            road.vehicles.remove(v)
        lanes = road.network.graph
        _from = next(iter(lanes))
        _to = next(iter(lanes[_from]))
        n_lanes = len(lanes[_from][_to])
        x = ego.lane.local_coordinates(ego.position)[0]
        for _ in range(n):
            driver_type = -1
            if self.drivers is not None:
                driver_type = self.drivers.draw(road.np_random)
                vehicle_cls = self.drivers.classes[driver_type]
            lane_id = int(road.np_random.integers(n_lanes))
            lane = road.network.get_lane((_from, _to, lane_id))
            limit = lane.speed_limit or 30.0
            speed = float(road.np_random.uniform(0.7 * limit, 1.0 * limit))
            offset = (12 + speed) * math.exp(-5 / 40 * n_lanes) / base.config["vehicles_density"]
            x -= offset * road.np_random.uniform(0.9, 1.1)
            v = vehicle_cls(road, lane.position(x, 0), lane.heading_at(x), speed)
            if hasattr(v, "randomize_behavior"):
                v.randomize_behavior()
            v.check_collisions = check_collisions
            if driver_type >= 0:
                v.driver_type = driver_type
            road.vehicles.append(v)
