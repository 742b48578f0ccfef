"""The highway-env adapter: highway-env's objects read once per reset and step into a :class:`RoadSnapshot`.

:class:`HighwayEnvAdapter` wraps a highway-env environment (after safelane's traffic layout) and puts
the snapshot of the scene in ``info["snapshot"]`` after every reset and step, so that nothing above the
simulator tier (but hand-built scenes, :mod:`safelane.env.scenarios`, and rendering) reads highway-env's
object graph. It also watches the physics frames for the ego's first crash, so the snapshot carries the positions of
the impact frame (highway-env pushes the bodies apart afterwards, so the end-of-decision geometry does
not tell who hit whom).

:func:`lane_change_timing` simulates highway-env's own lateral controller: the safety shield asks it
how long the ego overlaps its old lane during a lane change.
"""

from __future__ import annotations

import functools
import math
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from highway_env.envs.common.observation import KinematicObservation, ObservationType
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle

from safelane.core.snapshot import READ_ONLY_FIELDS, RoadSnapshot, freeze


class _DriverRecord(NamedTuple):
    """What does not change during an episode about one body (its model's parameters and size)."""

    length: float
    width: float
    is_vehicle: bool
    brake_max: float
    accel_max: float
    idm_delta: float
    idm_comfort_acc: float
    idm_comfort_dec: float
    idm_distance_wanted: float
    idm_time_wanted: float
    max_braking_imposed: float
    linear_speed_gain: float
    linear_speed_difference_gain: float
    linear_distance_gain: float
    politeness: float


_FLOAT_FIELDS = tuple(f for f in _DriverRecord._fields if f != "is_vehicle")


def _driver_record(o: Any, is_vehicle: bool, assumed: type | None = None) -> _DriverRecord:
    """Read one body's static attributes (instance first, then class; IDM's values as defaults). ``assumed``: a
    drawn car whose type the shield does not see (``o.driver_type`` >= 0) reports that class's parameters (its
    nominal linear gains, if linear), all but its own IDM exponent."""
    model = assumed if assumed is not None and getattr(o, "driver_type", -1) >= 0 else o
    model_class = model if isinstance(model, type) else type(model)
    idm_formula = getattr(model_class, "acceleration", None) is IDMVehicle.acceleration
    # The linear model's gains (LinearVehicle and its subclasses): MOBIL's criterion uses that formula.
    linear = getattr(model, "ACCELERATION_PARAMETERS", None) if not idm_formula and is_vehicle else None
    gains = [float(g) for g in linear] if linear is not None and len(linear) == 3 else [np.nan] * 3
    mobil = linear is not None or idm_formula
    comfort_acc = float(getattr(model, "COMFORT_ACC_MAX", IDMVehicle.COMFORT_ACC_MAX))
    acc_max = float(getattr(model, "ACC_MAX", IDMVehicle.ACC_MAX))
    return _DriverRecord(
        length=float(getattr(o, "LENGTH", 5.0)),
        width=float(getattr(o, "WIDTH", 2.0)),
        is_vehicle=is_vehicle,
        brake_max=acc_max,
        accel_max=comfort_acc if idm_formula else acc_max,
        idm_delta=float(getattr(o, "DELTA", IDMVehicle.DELTA)),
        idm_comfort_acc=comfort_acc,
        idm_comfort_dec=float(getattr(model, "COMFORT_ACC_MIN", IDMVehicle.COMFORT_ACC_MIN)),
        idm_distance_wanted=float(getattr(model, "DISTANCE_WANTED", IDMVehicle.DISTANCE_WANTED)),
        idm_time_wanted=float(getattr(model, "TIME_WANTED", IDMVehicle.TIME_WANTED)),
        max_braking_imposed=float(getattr(model, "LANE_CHANGE_MAX_BRAKING_IMPOSED", 2.0)) if mobil else np.inf,
        linear_speed_gain=gains[0],
        linear_speed_difference_gain=gains[1],
        linear_distance_gain=gains[2],
        politeness=float(getattr(model, "POLITENESS", IDMVehicle.POLITENESS)) if mobil else 0.0,
    )


def bodies(road: Road) -> list[Any]:
    """Everything on a highway-env road the ego can interact with: vehicles, then collidable objects."""
    return [*road.vehicles, *(o for o in getattr(road, "objects", []) if getattr(o, "collidable", True))]


def _lane_frame(road: Road) -> tuple[StraightLane, int]:
    """Lane 0 of the road's first segment and the number of parallel lanes (straight roads only)."""
    graph = road.network.graph
    _from = next(iter(graph))
    _to = next(iter(graph[_from]))
    lanes = graph[_from][_to]
    if not isinstance(lanes[0], StraightLane):
        raise ValueError("simulator: only straight multi-lane roads (highway-v0 / highway-fast-v0) are supported")
    return lanes[0], len(lanes)


class _CrashWatch:
    """Replaces one road's ``step`` (one physics frame) to keep the positions around the ego's first
    crash: ``before`` (start of the impact frame) and ``after`` (end of it, bodies still overlapping,
    before highway-env applies its separating impulse on the next frame).

    Holds the road and the wrapped bound method as attributes, so a ``deepcopy`` of the road gets a
    watch of its own (the bound method is re-bound to the copy).
    """

    def __init__(self, road: Road, ego: Any) -> None:
        self.road = road
        self.ego = ego
        self.inner = road.step
        self.before: np.ndarray | None = None
        self.after: np.ndarray | None = None

    def _positions(self) -> np.ndarray:
        found = bodies(self.road)
        return np.array([o.position for o in found], dtype=float).reshape(len(found), 2)

    def __call__(self, dt: float) -> None:
        if self.before is not None or self.ego.crashed:
            self.inner(dt)
            return
        before = self._positions()
        self.inner(dt)
        if self.ego.crashed:
            self.before = before
            self.after = self._positions()


def watch_collisions(road: Road, ego: Any) -> _CrashWatch:
    """Record the impact frame of ``ego``'s next crash on ``road`` (idempotent); returns the watch."""
    watch = road.__dict__.get("step")
    if not isinstance(watch, _CrashWatch):
        watch = road.step = _CrashWatch(road, ego)  # type: ignore[method-assign]
    return watch


def snapshot_of(base: Any, cache: dict[int, _DriverRecord] | None = None) -> RoadSnapshot:
    """The :class:`RoadSnapshot` of a highway-env environment (``env.unwrapped``) now.

    ``cache`` keeps each body's static record between calls of one episode (keyed by ``id``; the
    caller clears it at reset). An environment with a driver mixture (:func:`safelane.sim.drivers.install_driver_mix`)
    gives each body's ``driver_type``, and the assumed type's parameters for drawn cars when the shield does not see
    the types.
    """
    road, ego = base.road, base.vehicle
    lane0, lanes_count = _lane_frame(road)
    found = bodies(road)
    n_vehicles = len(road.vehicles)
    cache = {} if cache is None else cache
    mixture = getattr(base, "safelane_driver_mix", None)  # safelane.sim.drivers.install_driver_mix
    assumed = mixture.assumed if mixture is not None else None
    records = []
    for k, o in enumerate(found):
        rec = cache.get(id(o))
        if rec is None:
            rec = cache[id(o)] = _driver_record(o, k < n_vehicles, assumed)
        records.append(rec)
    n = len(found)
    columns = {
        name: np.array([r[i] for r in records], dtype=float)
        for i, name in enumerate(_DriverRecord._fields)
        if name in _FLOAT_FIELDS
    }
    is_vehicle = np.array([r.is_vehicle for r in records], dtype=bool)
    lane_of = [getattr(o, "lane_index", None) for o in found]
    watch = road.__dict__.get("step")
    crashed_frame = isinstance(watch, _CrashWatch) and watch.before is not None
    ego_lane = getattr(ego, "lane", None)
    snap = RoadSnapshot(
        time=float(base.time),
        policy_frequency=float(base.config["policy_frequency"]),
        simulation_frequency=float(base.config["simulation_frequency"]),
        lanes_count=lanes_count,
        lane_width=float(lane0.width),
        lane_origin=np.asarray(lane0.start, dtype=float),
        lane_direction=np.asarray(lane0.direction, dtype=float),
        lane_lateral=np.asarray(lane0.direction_lateral, dtype=float),
        speed_limit=float(ego_lane.speed_limit)
        if ego_lane is not None and ego_lane.speed_limit is not None
        else math.inf,
        ego=next(k for k, o in enumerate(found) if o is ego),
        # a ContinuousAction ego (a plain Vehicle) has no set-points and no speed controller
        ego_target_speed=float(getattr(ego, "target_speed", math.nan)),
        ego_speed_index=int(getattr(ego, "speed_index", -1)),
        ego_target_speeds=tuple(float(s) for s in getattr(ego, "target_speeds", ())),
        ego_kp=float(type(ego).KP_A) if isinstance(ego, ControlledVehicle) else math.nan,
        ego_lane_offset=float(ego.lane.local_coordinates(ego.position)[1]),
        position=np.array([o.position for o in found], dtype=float).reshape(n, 2),
        speed=np.array([o.speed for o in found], dtype=float),
        heading=np.array([o.heading for o in found], dtype=float),
        target_speed=np.array([float(getattr(o, "target_speed", math.nan)) for o in found], dtype=float),
        lane=np.array([li[2] if li else -1 for li in lane_of], dtype=int),
        target_lane=np.array(
            [getattr(o, "target_lane_index", li)[2] if li else -1 for o, li in zip(found, lane_of, strict=True)],
            dtype=int,
        ),
        crashed=np.array([bool(getattr(o, "crashed", False)) for o in found], dtype=bool),
        is_vehicle=is_vehicle,
        can_change_lane=np.array(
            [isinstance(o, IDMVehicle) and bool(getattr(o, "enable_lane_change", False)) for o in found], dtype=bool
        ),
        impact_before=watch.before if crashed_frame else None,
        impact_after=watch.after if crashed_frame else None,
        driver_type=None
        if mixture is None
        else np.array([int(getattr(o, "driver_type", -1)) for o in found], dtype=np.int64),
        **columns,
    )
    freeze(getattr(snap, name) for name in READ_ONLY_FIELDS)  # typed as the fast simulator's
    return snap


class DiscardedObservation(ObservationType):
    """Stands in for highway-env's own observation, which safelane never reads.

    highway-env builds its Kinematics observation through pandas at every step (≈ 5 % of a
    ``highway-fast-v0`` decision); safelane computes its own from the snapshot, so this returns a constant array of the
    original space's shape instead. The original is read-only and draws no random numbers (order
    ``sorted``), so the episodes are unchanged.
    """

    def __init__(self, env: Any, space: gym.spaces.Space) -> None:
        super().__init__(env)
        self._space = space
        self._constant = np.zeros(space.shape, dtype=space.dtype)

    def space(self) -> gym.spaces.Space:
        """The replaced observation's space."""
        return self._space

    def observe(self) -> np.ndarray:
        """Zeros of the replaced observation's shape."""
        return self._constant.copy()  # a new array each call, as gymnasium expects


class HighwayEnvAdapter(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Puts the :class:`RoadSnapshot` of the highway-env scene in ``info["snapshot"]`` after every
    reset and step (and watches for the ego's impact frame). ``road_snapshot()`` rebuilds it on demand,
    e.g. after a scene was edited by hand.

    safelane computes its own observations from the snapshot, so after every reset highway-env's own
    observation is swapped for a :class:`DiscardedObservation` (highway-env rebuilds it at each reset),
    unless it draws random numbers (``order: shuffled``).
    """

    def __init__(self, env: gym.Env) -> None:
        gym.utils.RecordConstructorArgs.__init__(self)
        super().__init__(env)
        self._records: dict[int, _DriverRecord] = {}

    def road_snapshot(self, refresh: bool = False) -> RoadSnapshot:
        """The snapshot of the scene now; ``refresh`` re-reads every body's static attributes too."""
        if refresh:
            self._records.clear()
        return snapshot_of(self.env.unwrapped, self._records)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        obs, info = self.env.reset(**kwargs)
        base = self.env.unwrapped
        self._discard_own_observation(base)
        watch_collisions(base.road, base.vehicle)
        info["snapshot"] = self.road_snapshot(refresh=True)
        return obs, info

    @staticmethod
    def _discard_own_observation(base: Any) -> None:
        observer = getattr(base, "observation_type", None)
        if isinstance(observer, KinematicObservation) and observer.order == "sorted":
            base.observation_type = DiscardedObservation(base, base.observation_space)

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        obs, reward, terminated, truncated, info = self.env.step(action)
        info["snapshot"] = self.road_snapshot()
        return obs, reward, terminated, truncated, info


@functools.lru_cache(maxsize=64)
def lane_change_timing(simulation_frequency: float, speed: float) -> tuple[float, float]:
    """(leave, enter) times [s] of a highway-env lane change at ``speed`` [m/s].

    Simulates ``ControlledVehicle``'s own lateral controller on a straight 2-lane road at the given
    physics frequency. ``leave``: until the body no longer overlaps a vehicle centred in the old lane;
    ``enter``: until it overlaps a vehicle centred in the new lane. Rotated-body extents included.
    """
    network = RoadNetwork.straight_road_network(2, speed_limit=40)
    road = Road(network=network, np_random=np.random.default_rng(0))
    if speed <= 0.0:
        return math.inf, math.inf  # a car at a standstill does not move sideways
    vehicle = ControlledVehicle(road, network.get_lane(("0", "1", 0)).position(0, 0), speed=speed)
    vehicle.target_lane_index = ("0", "1", 1)
    road.vehicles.append(vehicle)
    width, half_len = vehicle.WIDTH, vehicle.LENGTH / 2
    lane_width = StraightLane.DEFAULT_WIDTH
    dt = 1.0 / simulation_frequency
    leave = enter = math.inf
    for k in range(1, int(6 * simulation_frequency)):
        vehicle.act()
        vehicle.step(dt)
        h = vehicle.heading
        extent = width / 2 * math.cos(h) + half_len * abs(math.sin(h))
        y = vehicle.position[1]
        if enter == math.inf and y + extent > lane_width - width / 2:
            enter = k * dt
        if y - extent >= width / 2:
            leave = k * dt
            break
    return leave, enter
