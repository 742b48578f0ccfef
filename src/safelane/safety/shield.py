"""The safety shield: a gymnasium wrapper that exposes the safety model's mask to any agent.

``SafetyShield(env, mode="robust")`` reads the road from ``env.unwrapped`` (highway-env) after every
reset and step, turns it into a :class:`safelane.safety.model.RoadState` (SI units, lane coordinates) and
asks :func:`safelane.safety.model.evaluate` which of the 5 meta-actions are safe:

* ``action_masks()`` returns the mask (sb3-contrib's convention, so ``MaskablePPO`` uses it as is);
* ``info["action_mask"]``, ``info["fallback"]`` (no action was safe, the least-bad one is allowed)
  and ``info["shield_intervened"]`` (the override replaced the chosen action) are added;
* with ``override=True`` an unsafe action is replaced by the closest safe one
  (:data:`safelane.safety.model.OVERRIDE_ORDER`), so any agent — SB3's DQN, a random policy, a human —
  drives safely.

Every constant of the dynamics is read from highway-env's classes at run time (``KP_A``,
``ACC_MAX``, ``COMFORT_ACC_MAX``, IDM/MOBIL parameters, lane width, frequencies, target speeds);
lane-change timings come from simulating highway-env's own lateral controller.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from typing import Any, NamedTuple

import gymnasium as gym
import numpy as np
from highway_env.road.lane import StraightLane
from highway_env.road.road import Road, RoadNetwork
from highway_env.vehicle.behavior import IDMVehicle
from highway_env.vehicle.controller import ControlledVehicle

from safelane.safety.model import (
    OVERRIDE_ORDER,
    RELEVANCE_RANGE,
    Dynamics,
    Formula,
    Mode,
    RoadState,
    SafetyResult,
    evaluate,
)


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


def _lane_frame(road: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray, float, int, tuple[str, str]]:
    graph = road.network.graph
    _from = next(iter(graph))
    _to = next(iter(graph[_from]))
    lanes = graph[_from][_to]
    lane0 = lanes[0]
    if not isinstance(lane0, StraightLane):
        raise ValueError("shield: only straight multi-lane roads (highway-v0 / highway-fast-v0) are supported")
    return (
        np.asarray(lane0.start, dtype=float),
        np.asarray(lane0.direction, dtype=float),
        np.asarray(lane0.direction_lateral, dtype=float),
        float(lane0.width),
        len(lanes),
        (_from, _to),
    )


def dynamics_from_env(env: gym.Env) -> Dynamics:
    """The :class:`Dynamics` constants of a highway-env environment, read at run time."""
    base = env.unwrapped
    ego = base.vehicle
    sim_f = float(base.config["simulation_frequency"])
    pol_f = float(base.config["policy_frequency"])
    _, _, _, lane_width, lanes_count, _ = _lane_frame(base.road)
    # Fastest cut-in over plausible speeds; slowest ego exit (at low speed the lateral motion is slower).
    enter = min(lane_change_timing(sim_f, s)[1] for s in (15.0, 25.0, 35.0))
    return Dynamics(
        decision_period=1.0 / pol_f,
        frame_dt=1.0 / sim_f,
        frames_per_decision=int(sim_f // pol_f),
        ego_kp=float(type(ego).KP_A),
        target_speeds=tuple(float(s) for s in ego.target_speeds),
        lane_width=lane_width,
        lanes_count=lanes_count,
        cut_in_time=max(enter - 1.0 / sim_f, 0.0),
    )


class _VehicleRecord(NamedTuple):
    """What the safety model needs of one other vehicle (the :class:`RoadState` array of the same name)."""

    length: float
    crashed: bool
    brake_max: float
    accel_max: float
    can_change_lane: bool
    idm_delta: float
    idm_comfort_acc: float
    idm_comfort_dec: float
    idm_distance_wanted: float
    idm_time_wanted: float
    max_braking_imposed: float


def _vehicle_record(o: Any) -> _VehicleRecord:
    """Read one vehicle's attributes in one pass (instance first, then class; IDM's values as defaults)."""
    idm_formula = type(o).acceleration is IDMVehicle.acceleration
    comfort_acc = float(getattr(o, "COMFORT_ACC_MAX", IDMVehicle.COMFORT_ACC_MAX))
    acc_max = float(getattr(o, "ACC_MAX", IDMVehicle.ACC_MAX))
    return _VehicleRecord(
        length=float(getattr(o, "LENGTH", 5.0)),
        crashed=bool(getattr(o, "crashed", False)),
        brake_max=acc_max,
        accel_max=comfort_acc if idm_formula else acc_max,
        can_change_lane=isinstance(o, IDMVehicle) and bool(getattr(o, "enable_lane_change", False)),
        idm_delta=float(getattr(o, "DELTA", IDMVehicle.DELTA)),
        idm_comfort_acc=comfort_acc,
        idm_comfort_dec=float(getattr(o, "COMFORT_ACC_MIN", IDMVehicle.COMFORT_ACC_MIN)),
        idm_distance_wanted=float(getattr(o, "DISTANCE_WANTED", IDMVehicle.DISTANCE_WANTED)),
        idm_time_wanted=float(getattr(o, "TIME_WANTED", IDMVehicle.TIME_WANTED)),
        max_braking_imposed=float(getattr(o, "LANE_CHANGE_MAX_BRAKING_IMPOSED", 2.0)) if idm_formula else np.inf,
    )


def road_state(env: gym.Env, dyn: Dynamics) -> RoadState:
    """Snapshot of the road around the ego in lane coordinates (metres, m/s) for the safety model.

    Only vehicles within :data:`safelane.safety.model.RELEVANCE_RANGE` [m] of the ego along the road are
    included — the ones :func:`safelane.safety.model.evaluate` considers; their attributes are read in one
    pass, so the snapshot costs what the nearby traffic costs, not the whole road.
    """
    base = env.unwrapped
    ego = base.vehicle
    road = base.road
    start, direction, lateral, _, _, _ = _lane_frame(road)
    lane_heading = math.atan2(direction[1], direction[0])
    others = [v for v in road.vehicles if v is not ego]
    others += [o for o in getattr(road, "objects", []) if getattr(o, "collidable", True)]
    n = len(others)
    pos = np.array([o.position for o in others], dtype=float).reshape(n, 2) - start
    ego_rel = np.asarray(ego.position, dtype=float) - start
    ego_x = float(ego_rel @ direction)
    x_all = pos @ direction if n else np.zeros(0)
    near = np.flatnonzero((np.abs(x_all - ego_x) < RELEVANCE_RANGE) & np.isfinite(x_all))
    nearby = [others[i] for i in near]
    heading = np.array([o.heading for o in nearby], dtype=float) - lane_heading
    speed = np.array([o.speed for o in nearby], dtype=float)
    ego_heading = ego.heading - lane_heading
    records = [_vehicle_record(o) for o in nearby]
    columns = {
        name: np.array([r[k] for r in records], dtype=bool if name in ("crashed", "can_change_lane") else float)
        for k, name in enumerate(_VehicleRecord._fields)
    }
    lane = getattr(ego, "lane", None)
    return RoadState(
        ego_x=ego_x,
        ego_y=float(ego_rel @ lateral),
        ego_speed=float(ego.speed * math.cos(ego_heading)),
        ego_lane=int(ego.lane_index[2]),
        ego_target_lane=int(getattr(ego, "target_lane_index", ego.lane_index)[2]),
        ego_target_speed=float(getattr(ego, "target_speed", ego.speed)),
        ego_speed_index=int(getattr(ego, "speed_index", 0)),
        ego_length=float(ego.LENGTH),
        x=x_all[near],
        y=(pos @ lateral)[near] if n else np.zeros(0),
        vx=speed * np.cos(heading),
        vy=speed * np.sin(heading),
        heading=np.arctan2(np.sin(heading), np.cos(heading)),
        speed_limit=float(lane.speed_limit) if lane is not None and lane.speed_limit is not None else np.inf,
        **columns,
    )


class SafetyShield(gym.Wrapper, gym.utils.RecordConstructorArgs):
    """Gymnasium wrapper exposing the safety model's action mask (and optionally enforcing it).

    ``mode``: ``"nominal"`` (the paper's Q-masking) or ``"robust"`` (robust Q-masking).
    ``formula``: ``"kinematic"`` (derived for highway-env, docs/safety.md) or ``"paper"`` (eq. 12).
    ``override``: replace an unsafe chosen action by the closest safe one.
    """

    def __init__(
        self, env: gym.Env, mode: Mode = "robust", formula: Formula = "kinematic", override: bool = False
    ) -> None:
        if mode not in ("nominal", "robust"):
            raise ValueError(f"shield.mode: got {mode!r}; allowed: 'nominal', 'robust'")
        if formula not in ("kinematic", "paper"):
            raise ValueError(f"shield.formula: got {formula!r}; allowed: 'kinematic', 'paper'")
        gym.utils.RecordConstructorArgs.__init__(self, mode=mode, formula=formula, override=override)
        super().__init__(env)
        self.mode: Mode = mode
        self.formula: Formula = formula
        self.override = override
        self.dynamics: Dynamics | None = None
        self.result: SafetyResult | None = None

    def compute_result(self) -> SafetyResult:
        """Evaluate the safety model on the current road (no caching)."""
        if self.dynamics is None:
            self.dynamics = dynamics_from_env(self.env)
        state = road_state(self.env, self.dynamics)
        # The ego leaves its old lane more slowly at low speed (the steering turns the car in
        # proportion to its speed; at a standstill it never leaves). Time it at the lowest speed
        # the ego may have while still changing lane — its speed or set-point, minus what a
        # fallback SLOWER removes in the next second (4.5 m/s) — rounded down to 0.5 m/s so the
        # simulation is cached, plus one frame because the change starts at the next physics frame.
        slowest = min(state.ego_speed, state.ego_target_speed) - 4.5
        speed = float(np.clip(np.floor(slowest * 2) / 2, 0.0, 40.0))
        leave, _ = lane_change_timing(1.0 / self.dynamics.frame_dt, speed)
        dyn = dataclasses.replace(self.dynamics, ego_leave_time=leave + self.dynamics.frame_dt)
        return evaluate(state, dyn, self.mode, self.formula)

    def refresh(self) -> SafetyResult:
        """Recompute the verdict for the current road and cache it (after editing the road by hand)."""
        self.dynamics = None
        self.result = self.compute_result()
        return self.result

    def compute_mask(self) -> np.ndarray:
        """The mask of safe actions in the current state, recomputed (bool, shape (5,))."""
        return self.compute_result().mask

    def action_masks(self) -> np.ndarray:
        """The mask of the current state (sb3-contrib convention): bool array of shape (5,)."""
        if self.result is None:
            self.result = self.compute_result()
        return self.result.mask.copy()

    def _annotate(self, info: dict[str, Any]) -> None:
        self.result = self.compute_result()
        info["action_mask"] = self.result.mask.copy()
        info["fallback"] = bool(self.result.fallback)

    def reset(self, **kwargs: Any) -> tuple[Any, dict[str, Any]]:
        self.dynamics = None
        obs, info = self.env.reset(**kwargs)
        self._annotate(info)
        info["shield_intervened"] = False
        return obs, info

    def step(self, action: Any) -> tuple[Any, float, bool, bool, dict[str, Any]]:
        chosen = int(action)
        mask = self.action_masks()
        executed = chosen
        if self.override and not mask[chosen]:
            executed = next(a for a in OVERRIDE_ORDER[chosen] if mask[a])
        obs, reward, terminated, truncated, info = self.env.step(executed)
        info["shield_intervened"] = executed != chosen
        info["unsafe_action"] = not bool(mask[chosen])
        info["executed_action"] = executed
        self._annotate(info)
        return obs, reward, terminated, truncated, info
