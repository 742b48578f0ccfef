"""The safety rule's inputs and output: the world's constants, the road around the ego, the verdict.

:class:`Dynamics` (the simulated world's constants and the rule's options, :mod:`safelane.safety.rule`),
:class:`RoadState` (the scene in lane coordinates, SI units), :class:`SafetyResult` (what the rule says about
the 5 meta-actions) and the constants of the rule (:mod:`safelane.safety.one_decision.reference` derives it).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Any, Literal, NamedTuple

import numpy as np

from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, SLOWER
from safelane.safety.rule import DEFAULTS, OPTION_NAMES, Rule

Mode = Literal["nominal", "robust"]
Formula = Literal["kinematic", "paper"]
Engine = Literal["compiled", "numpy"]
MODES: tuple[Mode, ...] = ("nominal", "robust")
"""The one-decision rule's modes (:mod:`safelane.safety.one_decision`)."""
SHIELD_MODES: tuple[str, ...] = (*MODES, "committed")
"""Every ``shield.mode`` a :class:`~safelane.safety.family.RuleFamily` implements."""
ENGINES: tuple[Engine, ...] = ("compiled", "numpy")
FORMULAS: tuple[Formula, ...] = ("kinematic", "paper")


def check_choices(
    mode: str | None = None,
    engine: str | None = None,
    formula: str | None = None,
    modes: tuple[str, ...] = MODES,
    prefix: str = "shield.",
) -> None:
    """A one-line :class:`ValueError` naming the first of ``mode`` (one of ``modes``), ``engine`` and ``formula``
    outside its allowed values (None: not checked); ``prefix`` starts the name (``shield.mode``)."""
    for name, value, allowed in (("mode", mode, modes), ("engine", engine, ENGINES), ("formula", formula, FORMULAS)):
        if value is not None and value not in allowed:
            raise ValueError(f"{prefix}{name}: got {value!r}; allowed: {', '.join(repr(a) for a in allowed)}")


MAX_HOLD_DECISIONS = 3
"""Fallbacks hold the speed target for 0..3 decisions before braking (lets a far leader and a close
follower be handled together: keep speed now, brake later)."""
TAIL_DECISIONS = 2
"""Decisions simulated after the speed target reaches its minimum (the P-controller's exponential tail)."""
BASE_DECISION_PERIOD = 1.0
"""[s] The decision period the horizon's decision count was designed at (the paper's 1 decision per second):
with the rule's ``full_horizon`` the horizon spans at least as many seconds at every decision rate."""
RELEVANCE_RANGE = 250.0  # [m] vehicles farther than this (longitudinally) cannot matter in the horizon
LATERAL_MOTION_THRESHOLD = 0.01  # [rad] |heading| above which a vehicle counts as changing lane (robust)
IDM_LANE_MARGIN = 1.0  # [m] highway-env's IDM sees a body within half a lane + this of its lane's centre
NOT_ZERO = 1e-2  # [m] highway-env's utils.not_zero: the smallest distance IDM divides by
MOBIL_MIN_ACC_GAIN = 0.2  # [m/s²] highway-env's IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN

OVERRIDE_ORDER: dict[int, tuple[int, ...]] = {
    LANE_LEFT: (LANE_LEFT, IDLE, SLOWER, FASTER, LANE_RIGHT),
    IDLE: (IDLE, SLOWER, FASTER, LANE_LEFT, LANE_RIGHT),
    LANE_RIGHT: (LANE_RIGHT, IDLE, SLOWER, FASTER, LANE_LEFT),
    FASTER: (FASTER, IDLE, SLOWER, LANE_LEFT, LANE_RIGHT),
    SLOWER: (SLOWER, IDLE, LANE_LEFT, LANE_RIGHT, FASTER),
}
"""For each chosen action, the actions closest to it, in order: the shield's override takes the first
safe one. Keeping the lane beats changing it; slowing beats speeding up."""

TIE_BREAK_ORDER = (SLOWER, IDLE, FASTER, LANE_RIGHT, LANE_LEFT)
"""Preference among equally bad actions when no action is safe."""


@dataclass(frozen=True)
class Dynamics:
    """Constants of the simulated world, read from highway-env at run time by the shield.

    All in SI units. ``target_speeds`` are the ego's discrete speed targets [m/s].
    """

    decision_period: float  # [s] 1 / policy_frequency
    frame_dt: float  # [s] 1 / simulation_frequency
    frames_per_decision: int
    ego_kp: float  # [1/s] ego speed P-gain (ControlledVehicle.KP_A)
    target_speeds: tuple[float, ...]  # [m/s]
    lane_width: float  # [m]
    lanes_count: int
    follower_reaction: float = 0.5  # [s] a follower may keep accelerating this long before it brakes
    ego_leave_time: float = 0.8  # [s] the ego still overlaps its old lane this long into a lane change
    cut_in_time: float = 0.4  # [s] fastest time for another vehicle to reach the ego's lane
    margin: float = 1.0  # [m] minimum bumper-to-bumper gap kept under the worst case
    body_width: float = 2.0  # [m] the other vehicles' width (highway-env's Vehicle.WIDTH), for body_extent
    mobil_min_gain: float = MOBIL_MIN_ACC_GAIN
    """[m/s²] MOBIL's incentive threshold in the rule's turn-in filter: highway-env's ``IDMVehicle``'s; under a driver
    mixture the least of its types' (:func:`~safelane.safety.driver_sets.least_min_acc_gain`), since an aggressive
    driver changes lanes for any gain and the snapshot does not say which car is one."""
    rule: Rule = DEFAULTS  # the rule's options (safelane.safety.rule)
    braking_decisions: int | None = None
    """Decisions the ego's braking to a standstill may take, counted at :data:`BASE_DECISION_PERIOD` as the rest of
    the horizon is: None, one per set-point (a meta-action ego steps one down per decision); an ego under continuous
    controls, its top speed over its braking per second."""

    def with_options(self, **changes: Any) -> Dynamics:
        """These dynamics with rule options (by name) and other fields changed: ``dyn.with_options(
        follower_idm=False, margin=2.0)``. An unknown name is a one-line error."""
        options = {k: v for k, v in changes.items() if k in OPTION_NAMES}
        others = {k: v for k, v in changes.items() if k not in OPTION_NAMES}
        return replace(self, rule=self.rule.with_options(**options), **others) if options else replace(self, **others)

    @property
    def horizon_decisions(self) -> int:
        """Decisions simulated: the action, the longest hold, braking to standstill, the tail — counted at
        :data:`BASE_DECISION_PERIOD`; with ``full_horizon``, as many seconds at a faster rate. (13 decisions
        are 2.6 s at 5 per second: the ego, the P-controller lagging its falling set-point, is still at
        8 m/s there, and the tail credited beyond the horizon assumes a set-point of 0 it has not reached —
        the invariant breaks after which 11 of the grid's crashes happened at 5 per second.)"""
        braking = len(self.target_speeds) if self.braking_decisions is None else self.braking_decisions
        base = 1 + MAX_HOLD_DECISIONS + braking + TAIL_DECISIONS
        if not self.rule.full_horizon:
            return base
        return max(base, math.ceil(base * BASE_DECISION_PERIOD / self.decision_period - 1e-9))

    @property
    def times(self) -> np.ndarray:
        """Frame times [s] of the horizon, starting at 0 (now)."""
        n = self.horizon_decisions * self.frames_per_decision
        return np.arange(n + 1) * self.frame_dt


@dataclass(frozen=True)
class RoadState:
    """A snapshot of the road around the ego, in lane coordinates (x along the road, y across).

    Lane ``i``'s centre is at ``y = i · lane_width``. Arrays describe the other vehicles, one entry
    each. Speeds are signed along x (``vx``) and y (``vy``) [m/s].
    """

    ego_x: float  # [m]
    ego_y: float  # [m]
    ego_speed: float  # [m/s] along x
    ego_lane: int
    ego_target_lane: int
    ego_target_speed: float  # [m/s] current speed set-point
    ego_speed_index: int  # index of the current set-point in Dynamics.target_speeds
    ego_length: float = 5.0  # [m]
    ego_heading: float = 0.0  # [rad] relative to the road (a lane change under way turns it)
    x: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m]
    y: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m]
    vx: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s]
    vy: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s]
    heading: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [rad]
    length: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m]
    crashed: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    brake_max: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s²] positive
    accel_max: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s²]
    # Each vehicle's lane-change rule (MOBIL safety criterion with its own IDM parameters);
    # ``can_change_lane`` False for vehicles that never change lane.
    can_change_lane: np.ndarray = field(default_factory=lambda: np.zeros(0, bool))
    idm_delta: np.ndarray = field(default_factory=lambda: np.zeros(0))
    idm_comfort_acc: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s²] > 0
    idm_comfort_dec: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s²] < 0
    idm_distance_wanted: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m]
    idm_time_wanted: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [s]
    max_braking_imposed: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s²] > 0
    # The linear acceleration model's gains (LinearVehicle.ACCELERATION_PARAMETERS) of drivers that use it
    # (Linear, Aggressive, Defensive), whose MOBIL criterion applies it to the new follower; NaN: IDM.
    linear_speed_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [1/s]
    linear_speed_difference_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [1/s]
    linear_distance_gain: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [1/s²]
    # MOBIL's politeness p of each vehicle (the weight of its followers' gain in its lane-change incentive);
    # empty: 0 for every vehicle.
    politeness: np.ndarray = field(default_factory=lambda: np.zeros(0))
    # Each vehicle's speed set-point (the simulator's ``target_speed``: a driver parameter like the ones above);
    # empty or NaN: unknown.
    target_speed: np.ndarray = field(default_factory=lambda: np.zeros(0))  # [m/s]
    speed_limit: float = 30.0  # [m/s] of the ego's lane (IDM clips the ego's set-point to it)

    @property
    def n(self) -> int:
        """Number of other vehicles."""
        return int(self.x.shape[0])

    def lane_of(self, y: np.ndarray | float, lanes_count: int, lane_width: float) -> np.ndarray:
        """Nearest lane index of lateral positions ``y`` [m]."""
        return np.clip(np.rint(np.asarray(y) / lane_width), 0, lanes_count - 1).astype(int)


@dataclass(frozen=True)
class SafetyResult:
    """What the safety model says about the 5 actions in one state."""

    mask: np.ndarray  # bool (5,): allowed actions (never all False)
    safe: np.ndarray  # bool (5,): actions that satisfy the rule (may be all False)
    available: np.ndarray  # bool (5,): highway-env's get_available_actions()
    fallback: bool  # no action was safe: ``mask`` holds the least-bad one
    min_gap: np.ndarray  # (5,) [m] worst-case smallest gap under the best fallback (inf: no conflict)
    conflicts: tuple[Conflict, ...] | None = None  # the conflict that decided each action (None: not reported)

    def info(self) -> dict[str, Any]:
        """The keys the shield adds to a step's ``info``: ``action_mask`` and ``fallback``."""
        return {"action_mask": self.mask.copy(), "fallback": bool(self.fallback)}


class Conflict(NamedTuple):
    """The conflict that decided an action: under the action's best fallback, the smallest worst-case ``gap``
    [m] (its ``min_gap``) is to ``vehicle`` (a row of the :class:`RoadState`'s arrays) in ``lane``; ``ahead``:
    the vehicle is a leader there (else a follower or a car turning in behind the ego)."""

    action: int
    vehicle: int
    lane: int
    gap: float
    ahead: bool
