"""The road snapshot: one array record of the scene, the seam between a simulator and everything else.

A simulator (the highway-env adapter, :class:`safelane.sim.highway.HighwayEnvAdapter`, or a faster one)
builds one :class:`RoadSnapshot` after every reset and step and puts it in ``info["snapshot"]``. The
observations, the reward, the safety model's ``RoadState``, the collision forensics and the
"vehicles passed" count are computed from it alone, so a second simulator only has to fill these arrays.

Conventions: world coordinates in metres (x along the road, y across; highway-env's straight road has
lane ``i``'s centre at ``y = i·lane_width``), speeds in m/s, angles in radians, times in seconds. One
entry per *body* — the vehicles in the simulator's order, then the collidable static objects
(``is_vehicle`` False) — and ``ego`` is the ego's index. Driver-model parameters describe each body's
limits and rules (IDM / MOBIL); bodies that are not IDM drivers carry IDM's defaults and
``can_change_lane`` False. In traffic drawn from a mixture of driver types (``traffic.driver_mix``) whose types
the shield does not see, each drawn car's driver parameters are those of the assumed type
(``traffic.assumed_driver``), all but its own IDM exponent; ``driver_type`` says which type it really is.

Snapshots are read-only: consumers never modify the arrays.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields

import numpy as np

DRIVER_FIELDS: tuple[str, ...] = (
    "brake_max",
    "accel_max",
    "can_change_lane",
    "idm_delta",
    "idm_comfort_acc",
    "idm_comfort_dec",
    "idm_distance_wanted",
    "idm_time_wanted",
    "max_braking_imposed",
    "linear_speed_gain",
    "linear_speed_difference_gain",
    "linear_distance_gain",
    "politeness",
)
"""The per-body driver-model arrays of a snapshot, in the order the safety model's ``RoadState`` uses."""
READ_ONLY_FIELDS: tuple[str, ...] = ("length", "width", "is_vehicle", "driver_type", *DRIVER_FIELDS)
"""The arrays of a snapshot that hold for the whole episode: every simulator hands them out read-only (the fast one
shares them between snapshots). numba compiles a kernel once per argument type, read-only included, so arrays typed
alike on both simulators (and in the shield's readings) compile each kernel once."""


def freeze(arrays: object) -> None:
    """Mark each numpy array in ``arrays`` (an iterable; None entries skipped) read-only."""
    for a in arrays:  # type: ignore[attr-defined]
        if isinstance(a, np.ndarray):
            a.flags.writeable = False


def _same(a: object, b: object) -> bool:
    """Exact equality of two snapshot field values, NaN equal to NaN (in arrays and as a number)."""
    if isinstance(a, np.ndarray) or isinstance(b, np.ndarray):
        if a is None or b is None:
            return False
        return bool(np.array_equal(a, b, equal_nan=np.asarray(a).dtype.kind == "f"))
    if isinstance(a, float) and isinstance(b, float) and math.isnan(a) and math.isnan(b):
        return True
    return bool(a == b)


@dataclass(frozen=True, eq=False)
class RoadSnapshot:
    """The scene at one instant: the road, every body on it and what the ego's controller holds."""

    # --- time and rates ------------------------------------------------------------------------
    time: float
    """[s] simulated time since the reset."""
    policy_frequency: float
    """[Hz] decisions per second."""
    simulation_frequency: float
    """[Hz] physics frames per second."""

    # --- the road: parallel straight lanes --------------------------------------------------------
    lanes_count: int
    lane_width: float
    """[m]"""
    lane_origin: np.ndarray
    """(2,) [m] start of lane 0 (the leftmost lane)."""
    lane_direction: np.ndarray
    """(2,) unit vector along the road."""
    lane_lateral: np.ndarray
    """(2,) unit vector across the road, towards higher lane indices."""
    speed_limit: float
    """[m/s] of the ego's lane (inf when the lane has none)."""

    # --- the ego's controller -------------------------------------------------------------------
    ego: int
    """Index of the ego in the body arrays."""
    ego_target_speed: float
    """[m/s] the ego's current speed set-point (NaN for an ego without set-points: highway-env's
    ContinuousAction)."""
    ego_speed_index: int
    """Index of the set-point in ``ego_target_speeds`` (-1 for an ego without set-points: highway-env's
    ContinuousAction)."""
    ego_target_speeds: tuple[float, ...]
    """[m/s] the ego's discrete set-points (MDPVehicle.target_speeds; () for an ego without set-points:
    highway-env's ContinuousAction)."""
    ego_kp: float
    """[1/s] the ego's speed P-gain (ControlledVehicle.KP_A; NaN for an ego without set-points: highway-env's
    ContinuousAction, whose acceleration is the action itself)."""
    ego_lane_offset: float
    """[m] the ego's lateral offset from its lane's centre (positive towards higher lane indices)."""

    # --- bodies (one entry each) ------------------------------------------------------------------
    position: np.ndarray
    """(N, 2) [m] world position of each body's centre."""
    speed: np.ndarray
    """(N,) [m/s] along the body's heading."""
    heading: np.ndarray
    """(N,) [rad] in world coordinates, as the simulator holds it (not wrapped)."""
    target_speed: np.ndarray
    """(N,) [m/s] each vehicle's speed set-point (its controller's ``target_speed``; NaN for a body without
    one, such as an ego without set-points: highway-env's ContinuousAction): the driver parameter of the
    free-road terms of IDM and the linear model."""
    lane: np.ndarray
    """(N,) int: the lane the simulator assigns the body to."""
    target_lane: np.ndarray
    """(N,) int: the lane its controller steers to (its own lane when not changing lanes, and for a body
    without a lane controller, such as highway-env's ContinuousAction ego)."""
    length: np.ndarray
    """(N,) [m]"""
    width: np.ndarray
    """(N,) [m]"""
    crashed: np.ndarray
    """(N,) bool"""
    is_vehicle: np.ndarray
    """(N,) bool: a vehicle (True) or a static collidable object (False)."""

    # --- driver models (DRIVER_FIELDS) --------------------------------------------------------------
    brake_max: np.ndarray
    """(N,) [m/s²] > 0: hardest braking the body's model can command (IDM's ACC_MAX)."""
    accel_max: np.ndarray
    """(N,) [m/s²]: hardest acceleration (IDM's COMFORT_ACC_MAX for IDM drivers)."""
    can_change_lane: np.ndarray
    """(N,) bool: the body changes lanes by MOBIL's rule."""
    idm_delta: np.ndarray
    """(N,) IDM's acceleration exponent δ."""
    idm_comfort_acc: np.ndarray
    """(N,) [m/s²] > 0"""
    idm_comfort_dec: np.ndarray
    """(N,) [m/s²] < 0"""
    idm_distance_wanted: np.ndarray
    """(N,) [m] jam distance."""
    idm_time_wanted: np.ndarray
    """(N,) [s] desired time gap."""
    max_braking_imposed: np.ndarray
    """(N,) [m/s²] > 0: MOBIL's safety criterion (inf: never checks it)."""
    linear_speed_gain: np.ndarray
    """(N,) [1/s]: ``LinearVehicle.ACCELERATION_PARAMETERS[0]`` of a driver with the linear acceleration
    model (Linear, Aggressive, Defensive), which its MOBIL criterion applies to its new follower; NaN for
    IDM's formula."""
    linear_speed_difference_gain: np.ndarray
    """(N,) [1/s]: ``ACCELERATION_PARAMETERS[1]`` (NaN for IDM's formula)."""
    linear_distance_gain: np.ndarray
    """(N,) [1/s²]: ``ACCELERATION_PARAMETERS[2]`` (NaN for IDM's formula)."""
    politeness: np.ndarray
    """(N,) MOBIL's politeness p (``POLITENESS``): how much the driver weighs its followers' gain when it changes
    lanes; 0 for a body without MOBIL."""

    # --- forensics ---------------------------------------------------------------------------------
    impact_before: np.ndarray | None = None
    """(N, 2) [m] positions at the start of the physics frame in which the ego first crashed (None: no
    crash yet, or the simulator did not record it)."""
    impact_after: np.ndarray | None = None
    """(N, 2) [m] positions at the end of that frame, bodies still overlapping."""

    # --- driver types --------------------------------------------------------------------------------
    driver_type: np.ndarray | None = None
    """(N,) int: each body's type, its index in the traffic's driver mixture (``traffic.driver_mix``); -1 for the
    ego and the bodies not drawn from it. None: the traffic has no mixture. The safety model does not read it."""

    def __eq__(self, other: object) -> bool:
        """Field-by-field equality, arrays and numbers compared exactly (NaN equal to NaN): same scene, same
        snapshot."""
        if not isinstance(other, RoadSnapshot):
            return NotImplemented
        return self.first_difference(other) is None

    def first_difference(self, other: RoadSnapshot) -> str | None:
        """The name of the first field (in declaration order) whose values differ, None when all are equal."""
        for f in fields(self):
            if not _same(getattr(self, f.name), getattr(other, f.name)):
                return f.name
        return None

    __hash__ = None  # type: ignore[assignment]  # mutable arrays inside: not hashable

    @property
    def n(self) -> int:
        """Number of bodies, the ego included."""
        return int(self.speed.shape[0])

    @property
    def ego_position(self) -> np.ndarray:
        """(2,) [m] the ego's position."""
        return self.position[self.ego]

    @property
    def ego_speed(self) -> float:
        """[m/s] the ego's speed along its heading."""
        return float(self.speed[self.ego])

    @property
    def ego_heading(self) -> float:
        """[rad] the ego's heading."""
        return float(self.heading[self.ego])

    @property
    def lane_heading(self) -> float:
        """[rad] the road's heading, ``atan2`` of the lane direction: lane coordinates measure headings from it."""
        direction = self.lane_direction
        return math.atan2(direction[1], direction[0])

    @property
    def ego_crashed(self) -> bool:
        """Whether the ego has crashed."""
        return bool(self.crashed[self.ego])

    def others(self, vehicles_only: bool = True) -> np.ndarray:
        """Indices of every body but the ego, in order (only vehicles unless ``vehicles_only`` is False)."""
        keep = self.is_vehicle.copy() if vehicles_only else np.ones(self.n, dtype=bool)
        keep[self.ego] = False
        return np.flatnonzero(keep)

    def longitudinal(self, positions: np.ndarray | None = None) -> np.ndarray:
        """(N,) [m] distance along the road from lane 0's start of ``positions`` (default: the bodies')."""
        pos = self.position if positions is None else positions
        return (pos - self.lane_origin) @ self.lane_direction
