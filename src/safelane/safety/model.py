"""The safety model: which of the 5 meta-actions are safe, from kinematics alone (paper Section IV).

Pure maths over a road snapshot in SI units (metres, m/s, seconds). It imports nothing from
highway-env, the agents or training: :mod:`safelane.safety.shield` reads the snapshot and the dynamics
constants from highway-env and calls :func:`evaluate`.

The rule (derivation in ``docs/safety.md``): an action is **safe** when, after executing it for one
decision period under the worst-case behaviour of the other vehicles, a *fallback* — hold the
speed target for ``k ∈ {0..MAX_HOLD_DECISIONS}`` decisions, then SLOWER at every decision until
standstill — keeps every longitudinal gap above ``margin`` in every lane the ego and the other
vehicle may share. The ego's own motion is simulated exactly as highway-env integrates it
(P-controller on the speed target, explicit Euler at the simulation step); the others are
bounded by their driver model's limits:

* a vehicle ahead may brake at its maximum deceleration (IDM's ``ACC_MAX``) from now on; one moving
  backwards (highway-env's jammed IDM cars roll back) keeps its reverse speed;
* a vehicle behind may accelerate at its maximum (IDM's ``COMFORT_ACC_MAX``) for a reaction time
  and then brake at ``ACC_MAX``; the IDM car right behind the ego in its lane instead brakes by IDM's own
  response to the ego's fallback (``Dynamics.follower_idm``, :func:`idm_follower_positions`).

Modes
-----
``nominal`` — the paper's Q-masking (Section IV.3, eqs. 8–11): only vehicles in the lanes the
action uses count, each with its own worst case and its own fallback (eq. 11's free space is
checked leader by leader, follower by follower). With ``formula="paper"`` the safe distance is
eq. 12 as printed, evaluated at decision time — kept as the faithful baseline, unsound here (see
docs/safety.md).

``robust`` — the paper's robust Q-masking (Section IV.4b, Fig. 5). In addition to nominal:
vehicles moving laterally (heading angle) are projected into the lane they move to; any vehicle in
a lane adjacent to a lane the ego uses may cut in, if its own lane-change rule (MOBIL's safety
criterion, with the ego as its new follower) allows it, and is then a leader braking fully; one level
with or behind the ego may turn in behind it, if MOBIL's incentive lets it, and is then a follower;
and **one** fallback must handle every leader braking and every follower accelerating at the same
time.

``robust ⊆ nominal ⊆ available`` holds by construction: robust adds conflicts and requires a
joint fallback; its one looser bound, a moving leader braking along its path (``Dynamics.turning_leaders``),
is also nominal's wherever it is the looser (``Dynamics.turning_in_nominal``). The mask is never empty:
when no action is safe the least-bad one is allowed and ``fallback`` is set (:func:`least_bad_action`), ranked
first by a nominal forecast of the others (``Dynamics.forecast_fallback``, :mod:`safelane.safety.forecast`;
with ``Dynamics.forecast_contact_time`` a forecast collision ranks by when it comes, with
``Dynamics.forecast_lane_changes`` the forecast's cars change lane by MOBIL), which orders the unsafe actions and
never makes one safe.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from safelane.core.spaces import FASTER, IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS, SLOWER
from safelane.safety.forecast import forecast_gaps, forecast_keys, forecast_paths

Mode = Literal["nominal", "robust"]
Formula = Literal["kinematic", "paper"]

MAX_HOLD_DECISIONS = 3
"""Fallbacks hold the speed target for 0..3 decisions before braking (lets a far leader and a close
follower be handled together: keep speed now, brake later)."""
TAIL_DECISIONS = 2
"""Decisions simulated after the speed target reaches its minimum (the P-controller's exponential tail)."""
BASE_DECISION_PERIOD = 1.0
"""[s] The decision period the horizon's decision count was designed at (the paper's 1 decision per second):
with ``Dynamics.full_horizon`` the horizon spans at least as many seconds at every decision rate."""
RELEVANCE_RANGE = 250.0  # [m] vehicles farther than this (longitudinally) cannot matter in the horizon
LATERAL_MOTION_THRESHOLD = 0.01  # [rad] |heading| above which a vehicle counts as changing lane (robust)
IDM_LANE_MARGIN = 1.0  # [m] highway-env's IDM sees a body within half a lane + this of its lane's centre
NOT_ZERO = 1e-2  # [m] highway-env's utils.not_zero: the smallest distance IDM divides by
MOBIL_MIN_ACC_GAIN = 0.2  # [m/s²] highway-env's IDMVehicle.LANE_CHANGE_MIN_ACC_GAIN (its POLITENESS is 0)

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
    projected_cut_ins: bool = False  # robust: a vehicle moving sideways may also cut in from the lane it moves to
    body_extent: bool = True  # robust: a vehicle also occupies every lane its rotated body overlaps
    body_width: float = 2.0  # [m] the other vehicles' width (highway-env's Vehicle.WIDTH), for body_extent
    linear_mobil: bool = True  # robust: linear-model drivers' MOBIL criterion with their formula (else: any cut-in)
    reversing_leaders: bool = True  # a leader moving backwards keeps its reverse speed (else: taken as stopped)
    level_cut_ins: bool = True  # robust: a car level with or behind the ego in a next lane may turn in behind it
    level_incentive: bool = True  # level_cut_ins: only if MOBIL's incentive (its gain behind the ego) allows it
    level_entering: bool = True  # level_incentive: not into a lane the ego is only entering (any level car there)
    least_bad_joint: bool = False  # no safe action: rank by the gap to everybody first (else: to vehicles ahead)
    full_horizon: bool = True  # the horizon spans the same seconds at every decision rate (else: the same decisions)
    ego_speed_magnitude: bool = True  # RoadState.ego_speed is the controller's speed (else: along the road)
    turning_leaders: bool = True  # a moving leader brakes along its path, less a lane change's cost
    robust_fallback: bool = False  # robust, nothing safe: least-bad of all available by robust gaps (experimental)
    straight_fallback: bool = True  # turning_leaders, nothing safe: the mask of the rule without it
    linear_incentive: bool = True  # level_incentive: linear-model drivers' incentive with their formula (else any)
    linear_incentive_braking: bool = True  # linear_incentive: also at every frame, their leaders braking fully
    reversing_cut_ins: bool = True  # a car moving backwards may change into the ego's lane whatever MOBIL says
    crossed_lanes: bool = True  # the ego occupies every lane between its lane and its target, until it is through
    lateral_schedule: bool = False  # the ego's time in each lane simulated from its lateral position and heading
    reversing_noses: bool = True  # robust: a car rolling backwards, turned, is also in the lane its nose points to
    follower_idm: bool = True  # the IDM car right behind the ego in its lane brakes by IDM's response to the ego
    follower_set_point: bool = False  # follower_idm: with its own set-point, and linear-model drivers by their formula
    finishing_changes: bool = True  # robust: a car moving toward its own lane's centre is not projected past it
    cut_in_when_permitted: bool = True  # robust: a cut-in starts from the first frame MOBIL's safety criterion allows
    leaving_lanes_seen: bool = False  # lateral_schedule: MOBIL filters cut-ins into a lane the ego leaves, seen there
    passing_cut_ins: bool = True  # cut_in_when_permitted: a car behind the ego cutting in ahead of it is a leader
    permit_any_speed: bool = True  # cut_in_when_permitted: MOBIL's IDM criterion at the car's loosest speed
    level_when_incentive: bool = True  # level turn-ins start from the first frame MOBIL's incentive allows them
    incentive_any_speed: bool = True  # level_when_incentive: that frame over every speed the cars can reach
    turning_in_nominal: bool = True  # turning_leaders: nominal's leader bound never below robust's (robust ⊆ nominal)
    forecast_fallback: bool = True  # nothing safe: rank the least-bad choice by a nominal forecast first (forecast.py)
    forecast_contact_time: bool = False  # experimental: forecast collisions rank by first contact, later first
    forecast_lane_changes: bool = False  # experimental: the forecast's cars change lane by MOBIL (forecast_fallback)
    ego_lateral_speed: float = math.nan  # [m/s] the speed that simulation runs at (per state, like ego_leave_time)
    ego_width: float = 2.0  # [m] the ego's width (Vehicle.WIDTH)
    kp_lateral: float = 1.0 / 0.6  # [1/s] ControlledVehicle.KP_LATERAL
    kp_heading: float = 1.0 / 0.2  # [1/s] ControlledVehicle.KP_HEADING
    max_steering: float = math.pi / 3  # [rad] ControlledVehicle.MAX_STEERING_ANGLE

    @property
    def horizon_decisions(self) -> int:
        """Decisions simulated: the action, the longest hold, braking to standstill, the tail — counted at
        :data:`BASE_DECISION_PERIOD`; with ``full_horizon``, as many seconds at a faster rate. (13 decisions
        are 2.6 s at 5 per second: the ego, the P-controller lagging its falling set-point, is still at
        8 m/s there, and the tail credited beyond the horizon assumes a set-point of 0 it has not reached —
        issue 15, the invariant breaks after which 11 of the grid's crashes happened at 5 per second.)"""
        base = 1 + MAX_HOLD_DECISIONS + len(self.target_speeds) + TAIL_DECISIONS
        if not self.full_horizon:
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


# --------------------------------------------------------------------------------------------
# Ego motion: highway-env's MDPVehicle, integrated exactly as the simulator does.
# --------------------------------------------------------------------------------------------


def speed_to_index(speed: np.ndarray | float, target_speeds: tuple[float, ...]) -> np.ndarray:
    """Index of the target speed closest to ``speed`` [m/s] (MDPVehicle.speed_to_index, rounding included)."""
    ts = target_speeds
    x = (np.asarray(speed, dtype=float) - ts[0]) / (ts[-1] - ts[0])
    return np.clip(np.round(x * (len(ts) - 1)), 0, len(ts) - 1).astype(int)


def action_targets(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """The ego's speed set-point [m/s] after each action (MDPVehicle.act)."""
    ts = dyn.target_speeds
    idx_now = int(speed_to_index(state.ego_speed, ts))
    target = np.full(N_ACTIONS, state.ego_target_speed, dtype=float)
    target[FASTER] = ts[min(idx_now + 1, len(ts) - 1)]
    target[SLOWER] = ts[max(idx_now - 1, 0)]
    return target


def ego_trajectories(state: RoadState, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """Ego positions [m] and speeds [m/s] for every (action, fallback) over the horizon.

    Returns arrays of shape ``(5, MAX_HOLD_DECISIONS + 1, frames + 1)``. Decision 0 applies the
    action (FASTER / SLOWER move the set-point one step from the *current speed's* index, as
    MDPVehicle does; IDLE and lane changes keep the set-point); fallback ``k`` then holds for ``k``
    decisions and sends SLOWER at every later decision. Per frame, as highway-env's
    ``Vehicle.step``: ``x += v·dt`` then ``v += KP_A·(target − v)·dt``.
    """
    ts = np.asarray(dyn.target_speeds, dtype=float)
    n_fb = MAX_HOLD_DECISIONS + 1
    shape = (N_ACTIONS, n_fb)
    v = np.full(shape, state.ego_speed, dtype=float)
    x = np.full(shape, state.ego_x, dtype=float)
    target = np.repeat(action_targets(state, dyn)[:, None], n_fb, axis=1)
    hold = np.arange(n_fb)[None, :]
    frames = dyn.frames_per_decision
    total = dyn.horizon_decisions * frames
    xs = np.empty((*shape, total + 1))
    vs = np.empty((*shape, total + 1))
    xs[..., 0], vs[..., 0] = x, v
    decay = 1.0 - dyn.ego_kp * dyn.frame_dt
    powers = decay ** np.arange(frames + 1)  # v_k = target + (v_0 - target)·decay^k
    # Distance covered since the decision's start: 0, then the running sum of v·dt (written in place:
    # this runs at every decision of every episode, so no temporaries beyond the ones numpy needs).
    covered = np.zeros((*shape, frames + 1))
    for d in range(dyn.horizon_decisions):
        if d >= 1:
            slower = ts[np.maximum(speed_to_index(v, dyn.target_speeds) - 1, 0)]
            target = np.where(d > hold, slower, target)
        sl = slice(d * frames, (d + 1) * frames + 1)
        # Consecutive decisions share a frame: decision d+1's first frame overwrites d's last, as before.
        v_frames, x_frames = vs[..., sl], xs[..., sl]
        np.multiply((v - target)[..., None], powers, out=v_frames)
        v_frames += target[..., None]
        np.cumsum(v_frames[..., :-1], axis=-1, out=covered[..., 1:])
        np.multiply(covered, dyn.frame_dt, out=x_frames)
        x_frames += x[..., None]
        x, v = x_frames[..., -1].copy(), v_frames[..., -1].copy()
    # Beyond the horizon the ego still creeps towards its final set-point: credit the remaining
    # distance of the exponential approach to the last frame so a stopped leader is not missed.
    tail = np.maximum(vs[..., -1] - 0.0, 0.0) / dyn.ego_kp
    xs[..., -1] += tail
    return xs, vs


# --------------------------------------------------------------------------------------------
# Other vehicles' worst cases.
# --------------------------------------------------------------------------------------------


def turning_allowance(dyn: Dynamics) -> float:
    """[m] What a lane change can cost a leader along the road, with ``Dynamics.turning_leaders`` (else 0).

    The leader bound brakes from the car's speed along the road, ``v·cos h``: a car turning out of the ego's
    lane has a lower one, which the next decision's bound keeps for the whole horizon — not nested in time
    (issue 15: 21 of the 22 holes of the 100 800-episode campaign). With the option a moving leader brakes
    from its speed along its path, less this allowance, ``lane_width·tan(π/8)`` (1.66 m: one lane width at
    the π/4 that highway-env holds a heading to); the same for a straight and a turning car (one lane change
    within the horizon). Not a closed-form bound — the path turns by ``heading + β`` (slip angle) — but
    measured against highway-env's controller: from any frame of a lane change at 1–30 m/s braking at up to
    ACC_MAX, 5–15 Hz physics, the car stays within 1.59 m of the braking bound
    (``tests/test_safety.py::test_turning_allowance_covers_highway_env_s_lane_change``)."""
    return dyn.lane_width * math.tan(math.pi / 8) if dyn.turning_leaders else 0.0


def braking_positions(
    x0: np.ndarray, v0: np.ndarray, brake: np.ndarray, t: np.ndarray, reversing: bool = False
) -> np.ndarray:
    """Positions [m] of vehicles braking at ``brake`` [m/s²] from speed ``v0`` [m/s] until standstill.

    A vehicle moving backwards (``v0 < 0``) counts as stopped, or with ``reversing`` keeps moving back at
    ``v0`` for the whole of ``t``: IDM has no bound on how long a jammed car rolls back (highway-env clips
    speeds to ±40 m/s only), and the ego behind it cannot reverse (docs/safety.md §6d)."""
    v_signed = v0[:, None]
    v0 = np.maximum(v0, 0.0)[:, None]
    b = np.maximum(brake, 1e-6)[:, None]
    tt = np.minimum(t[None, :], v0 / b)
    x = x0[:, None] + v0 * tt - 0.5 * b * tt**2
    if reversing:
        x = np.where(v_signed < 0.0, x + v_signed * t[None, :], x)
    return x


def follower_positions(
    x0: np.ndarray, v0: np.ndarray, accel: np.ndarray, brake: np.ndarray, reaction: float, t: np.ndarray
) -> np.ndarray:
    """Positions [m] of vehicles accelerating at ``accel`` for ``reaction`` s, then braking to a stop."""
    v0 = np.maximum(v0, 0.0)[:, None]
    a = accel[:, None]
    b = np.maximum(brake, 1e-6)[:, None]
    t_r = min(reaction, float(t[-1]))
    t1 = np.minimum(t[None, :], t_r)
    x1 = x0[:, None] + v0 * t1 + 0.5 * a * t1**2
    v1 = v0 + a * t_r
    t2 = np.clip(t[None, :] - t_r, 0.0, None)
    t2 = np.minimum(t2, v1 / b)
    return x1 + v1 * t2 - 0.5 * b * t2**2


def idm_acceleration_behind(
    state: RoadState,
    who: np.ndarray,
    gap_centres: np.ndarray,
    ego_speed: np.ndarray,
    ego_target: np.ndarray,
    own_speed: np.ndarray | None = None,
) -> np.ndarray:
    """IDM acceleration [m/s²] that vehicles ``who`` predict for the ego following them.

    This is the quantity of MOBIL's safety criterion (highway-env ``IDMVehicle.mobil``), computed
    with the cutting vehicle's own IDM parameters; ``gap_centres`` is the centre-to-centre distance
    [m] (highway-env's ``lane_distance_to``), ``ego_target`` the ego's set-point clipped to the
    speed limit; ``own_speed`` [m/s] the cutting vehicle's speed (default: its speed now).
    """
    acc = state.idm_comfort_acc[who]
    target = np.where(np.abs(ego_target) < 1e-2, 1e-2, ego_target)
    free = acc * (1 - np.power(np.maximum(ego_speed, 0.0) / np.abs(target), state.idm_delta[who]))
    ab = -acc * state.idm_comfort_dec[who]
    dv = ego_speed - (state.vx[who] if own_speed is None else own_speed)
    d_star = (
        state.idm_distance_wanted[who] + ego_speed * state.idm_time_wanted[who] + ego_speed * dv / (2 * np.sqrt(ab))
    )
    d = np.where(np.abs(gap_centres) < 1e-2, 1e-2, gap_centres)
    return free - acc * (d_star / d) ** 2


def least_desired_gap(
    state: RoadState, who: np.ndarray, ego_speed: float, speed_low: np.ndarray, speed_high: np.ndarray
) -> np.ndarray:
    """The least ``|d*|`` [m] of IDM's desired gap that vehicles ``who`` (their own parameters) predict for the
    ego (at ``ego_speed`` [m/s]) following them, over their speeds in ``[speed_low, speed_high]`` [m/s]:
    ``d* = d₀ + v·T + v·(v − v_car)/(2√(ab))`` is monotone in ``v_car``, so 0 where it changes sign in the
    range, else its endpoint nearer 0."""
    ab = -state.idm_comfort_acc[who] * state.idm_comfort_dec[who]
    base = state.idm_distance_wanted[who] + ego_speed * state.idm_time_wanted[who]
    d_hi = base + ego_speed * (ego_speed - speed_high) / (2 * np.sqrt(ab))  # the car at its fastest
    d_lo = base + ego_speed * (ego_speed - speed_low) / (2 * np.sqrt(ab))  # at its slowest
    lo, hi = np.minimum(d_hi, d_lo), np.maximum(d_hi, d_lo)
    return np.where(lo > 0.0, lo, np.where(hi < 0.0, -hi, 0.0))


def idm_acceleration_behind_gap(
    state: RoadState, who: np.ndarray, gap_centres: np.ndarray, ego_speed: np.ndarray, ego_target: np.ndarray,
    desired_gap: np.ndarray,
) -> np.ndarray:  # fmt: skip
    """:func:`idm_acceleration_behind` with IDM's desired gap ``desired_gap`` [m] given (e.g.
    :func:`least_desired_gap`) instead of computed from one speed of the car."""
    acc = state.idm_comfort_acc[who]
    target = np.where(np.abs(ego_target) < 1e-2, 1e-2, ego_target)
    free = acc * (1 - np.power(np.maximum(ego_speed, 0.0) / np.abs(target), state.idm_delta[who]))
    d = np.where(np.abs(gap_centres) < 1e-2, 1e-2, gap_centres)
    return free - acc * (desired_gap / d) ** 2


def linear_acceleration_behind(
    state: RoadState,
    who: np.ndarray,
    gap_centres: np.ndarray,
    ego_speed: np.ndarray,
    ego_target: np.ndarray,
    own_speed: np.ndarray | None = None,
) -> np.ndarray:
    """The acceleration [m/s²] a linear-model driver ``who`` (``LinearVehicle.acceleration``) predicts for
    the ego following it: ``k₀·(v* − v) + k₁·min(v_who − v, 0) + k₂·min(d − d_safe, 0)`` with
    ``d_safe = DISTANCE_WANTED + max(v, 0)·TIME_WANTED`` — MOBIL's safety criterion for Linear, Aggressive
    and Defensive drivers. ``gap_centres`` [m] centre to centre, ``ego_target`` [m/s] the ego's set-point
    (not clipped: highway-env reads ``target_speed``); the driver's speed is its whole speed (≥ its
    speed along the road), which can only make the criterion allow more; ``own_speed`` [m/s] overrides it."""
    if own_speed is None:
        own_speed = np.hypot(state.vx[who], state.vy[who])
    d_safe = state.idm_distance_wanted[who] + np.maximum(ego_speed, 0.0) * state.idm_time_wanted[who]
    return (
        state.linear_speed_gain[who] * (ego_target - ego_speed)
        + state.linear_speed_difference_gain[who] * np.minimum(own_speed - ego_speed, 0.0)
        + state.linear_distance_gain[who] * np.minimum(gap_centres - d_safe, 0.0)
    )


def set_points(state: RoadState) -> np.ndarray:
    """Each vehicle's speed set-point [m/s] (``RoadState.target_speed``), NaN where the state has none."""
    if state.target_speed.shape == state.x.shape:
        return state.target_speed
    return np.full(state.n, np.nan)


def idm_followers(state: RoadState, dyn: Dynamics, near: np.ndarray) -> np.ndarray:
    """Which vehicles ``near`` follow the ego by IDM, with ``Dynamics.follower_idm`` (else none): bool per row.

    highway-env's IDM brakes for the nearest body ahead of it within half a lane + 1 m of its lane's centre
    (``Road.neighbour_vehicles``, ``Lane.on_lane(margin=1)``) at every physics frame. The car right behind the
    ego in the ego's lane, driving straight (not moving sideways), with IDM's formula (not the linear model)
    and a lane-change rule (a driver, not an object), has the ego as that body: nothing else's centre lies
    between the two in the band. With ``Dynamics.follower_set_point`` a linear-model driver whose set-point
    is known counts too (its formula is linear in it, so it has no bound without it)."""
    rows = np.zeros(near.shape[0], dtype=bool)
    if not dyn.follower_idm:
        return rows
    v0 = set_points(state)
    centre = state.ego_lane * dyn.lane_width
    in_band = np.abs(state.y - centre) <= 0.5 * dyn.lane_width + IDM_LANE_MARGIN
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    for r, i in enumerate(near):
        if not (
            state.x[i] < state.ego_x
            and not state.crashed[i]
            and state.can_change_lane[i]
            and (np.isnan(state.linear_speed_gain[i]) or (dyn.follower_set_point and np.isfinite(v0[i])))
            and abs(state.heading[i]) <= LATERAL_MOTION_THRESHOLD
            and abs(state.vy[i]) <= 0.3
            and lanes[i] == state.ego_lane
        ):
            continue
        between = in_band & (state.x >= state.x[i]) & (state.x <= state.ego_x)
        between[i] = False
        rows[r] = not between.any()
    return rows


def idm_follower_positions(state: RoadState, dyn: Dynamics, i: int, ego_x: np.ndarray, ego_v: np.ndarray) -> np.ndarray:
    """Positions [m] of follower ``i`` (:func:`idm_followers`) braking by IDM for the ego, per fallback.

    ``ego_x``, ``ego_v``: (F, T) the ego's positions [m] and speeds [m/s] of one action's fallbacks. Frame
    by frame as highway-env's ``IDMVehicle.act`` then ``Vehicle.step``: ``a = acc·(1 − (v/v₀)^δ) −
    acc·(d*/d)²`` with ``d* = d₀ + v·T + v·(v − v_ego)/(2√(acc·b))`` and ``d`` the centre distance, clipped to
    ``[−brake_max, accel_max]``; then ``x += v·dt``, ``v += a·dt``. The driver's own set-point v₀ is not
    observed, so the free-road term is bounded by ``acc`` (v₀ = ∞): an upper bound on its acceleration in
    every state, not a proven envelope of its path (docs/safety.md §6k). With ``Dynamics.follower_set_point``
    and the set-point known, the free-road term is IDM's own (v₀ clipped to the speed limit), and a linear-model
    driver follows ``LinearVehicle.acceleration``: ``k₀·(v₀ − v) + k₁·min(v_ego − v, 0) + k₂·min(d − d_safe,
    0)``, ``d_safe = d₀ + max(v, 0)·T`` — the car's own path as highway-env drives it, while the ego is its
    leader. Beyond the last frame the car is credited what the follower bound lets it still cover (accelerate
    for the reaction time, then brake). Returns (F, T)."""
    acc = float(state.idm_comfort_acc[i])
    two_sqrt_ab = 2.0 * math.sqrt(-acc * float(state.idm_comfort_dec[i]))
    d0, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    a_max, b_max = float(state.accel_max[i]), float(state.brake_max[i])
    v0 = float(set_points(state)[i])
    exact = dyn.follower_set_point and math.isfinite(v0)
    linear = not math.isnan(float(state.linear_speed_gain[i]))
    k0, k1, k2 = (float(g[i]) for g in (state.linear_speed_gain, state.linear_speed_difference_gain,
                                        state.linear_distance_gain))  # fmt: skip
    target = min(max(v0, 0.0), state.speed_limit) if exact else 1.0  # IDM clips it to the lane's limit
    if not abs(target) > NOT_ZERO:
        target = NOT_ZERO if target >= 0.0 else -NOT_ZERO
    target = abs(target)
    delta = float(state.idm_delta[i])
    dt = dyn.frame_dt
    n_f, n_t = ego_x.shape
    out = np.empty((n_f, n_t))
    xf = np.full(n_f, float(state.x[i]))
    vf = np.full(n_f, float(state.vx[i]))
    out[:, 0] = xf
    for k in range(n_t - 1):
        if linear:  # only with exact: idm_followers picks linear drivers with a known set-point only
            d_safe = d0 + np.maximum(vf, 0.0) * tw
            a = (
                k0 * (v0 - vf)
                + k1 * np.minimum(ego_v[:, k] - vf, 0.0)
                + k2 * np.minimum((ego_x[:, k] - xf) - d_safe, 0.0)
            )
        else:
            free = acc * (1.0 - (np.maximum(vf, 0.0) / target) ** delta) if exact else acc
            d = ego_x[:, k] - xf
            d = np.where(np.abs(d) > NOT_ZERO, d, np.where(d >= 0.0, NOT_ZERO, -NOT_ZERO))
            ratio = (d0 + vf * tw + vf * (vf - ego_v[:, k]) / two_sqrt_ab) / d
            a = free - acc * (ratio * ratio)
        a = np.maximum(np.minimum(a, a_max), -b_max)
        xf = xf + vf * dt
        vf = vf + a * dt
        out[:, k + 1] = xf
    reaction = dyn.follower_reaction
    v = np.maximum(vf, 0.0)
    v1 = v + a_max * reaction
    out[:, -1] += v * reaction + 0.5 * a_max * (reaction * reaction) + v1 * v1 / (2.0 * max(b_max, 1e-6))
    return out


# --------------------------------------------------------------------------------------------
# Conflicts: (vehicle, lane, time window) pairs the ego must keep a gap to.
# --------------------------------------------------------------------------------------------


def _action_lanes(state: RoadState, dyn: Dynamics, action: int) -> list[tuple[int, float]]:
    """Lanes the ego occupies under ``action``, each with the time [s] until which it does (inf).

    With ``Dynamics.crossed_lanes`` also every lane the ego crosses on the way to its target: a lane
    change chained onto one under way (lane 0 → 1, then RIGHT again → 2) takes the ego through lane 1 whole,
    which the leave time of one lane change does not bound (issue 15, cells 2009 and 2833). With
    ``Dynamics.lateral_schedule`` (experimental) the lanes and times of :func:`ego_lane_windows` instead."""
    if dyn.lateral_schedule:
        return ego_lane_windows(state, dyn, final_lane(state, dyn, action))
    base = {state.ego_lane, state.ego_target_lane}
    if action not in (LANE_LEFT, LANE_RIGHT):
        if dyn.crossed_lanes:
            base |= set(range(min(base), max(base) + 1))
        return [(lane, math.inf) for lane in sorted(base)]
    new_target = final_lane(state, dyn, action)
    low, high = sorted((state.ego_lane, new_target))
    crossed = set(range(low + 1, high)) if dyn.crossed_lanes else set()
    lanes = [(lane, math.inf if lane in crossed else dyn.ego_leave_time) for lane in sorted(base | crossed)]
    return [*[(lane, until) for lane, until in lanes if lane != new_target], (new_target, math.inf)]


def final_lane(state: RoadState, dyn: Dynamics, action: int) -> int:
    """The lane the ego steers for after ``action``: highway-env moves the *target* lane one step (clipped to
    the road), and IDLE, FASTER and SLOWER keep a lane change under way."""
    if action not in (LANE_LEFT, LANE_RIGHT):
        return state.ego_target_lane
    step = -1 if action == LANE_LEFT else 1
    return min(max(state.ego_target_lane + step, 0), dyn.lanes_count - 1)


def ego_lane_windows(state: RoadState, dyn: Dynamics, final: int) -> list[tuple[int, float]]:
    """:func:`lateral_schedule`'s windows."""
    return lateral_schedule(state, dyn, final)[0]


def lateral_schedule(state: RoadState, dyn: Dynamics, final: int) -> tuple[list[tuple[int, float]], set[int]]:
    """``Dynamics.lateral_schedule``: the lanes the ego's body overlaps (a vehicle of ``body_width`` centred in
    them) while it steers for lane ``final``, each with the time [s] until which it does: the first frame it is
    clear of the lane plus one frame, as :func:`safelane.safety.shield.ego_leave_time_at` counts (from a lane
    centre, exactly that function's leave time); inf: still overlapped when the simulation ended unsettled (the
    horizon, a standstill). ``final`` always, from now on.

    highway-env's own lateral controller (``ControlledVehicle.steering_control``: lateral P-control to a
    heading reference, heading P-control to a slip angle, the bicycle model of ``Vehicle.step``) simulated from
    the ego's lateral position and heading at ``ego_lateral_speed`` (the slowest speed the ego may have while
    changing lane), on a straight road. It replaces the leave time of a lane change from a lane centre, which
    each decision restarted: at 3 and 5 decisions per second the rule promised the ego out of its lane by
    then and, one decision later, by a fifth of a second later (issue 15, cell 2569). It stops once the body
    overlaps ``final`` alone and no longer moves away from its centre. Scalar arithmetic in a fixed order,
    the compiled engine's ``_ego_lane_windows`` line for line (bit-identical).

    Also the lanes the ego leaves *seen*: its centre within IDM's band of the lane (half a lane +
    :data:`IDM_LANE_MARGIN` from its centre) now, and never overlapping the lane from outside that band.
    highway-env's MOBIL finds a lane's vehicles by that band (``Road.neighbour_vehicles``), not by their lane
    index: while the ego's centre is in it, a car changing into the lane judges the ego as its new follower, so
    with ``Dynamics.leaving_lanes_seen`` its cut-ins there are MOBIL-filtered as in the ego's own lane — after
    the ego's lane index has flipped to the lane it enters (issue 15, tenth session: the breaks
    ``lateral_schedule`` added, §6j)."""
    lanes, width = dyn.lanes_count, dyn.lane_width
    band = 0.5 * width + IDM_LANE_MARGIN
    seen = [abs(state.ego_y - lane * width) <= band for lane in range(lanes)]
    frames = dyn.horizon_decisions * dyn.frames_per_decision
    dt, speed = dyn.frame_dt, dyn.ego_lateral_speed
    half_length = 0.5 * state.ego_length
    y, heading = state.ego_y, state.ego_heading
    target_y = final * width
    last = [-1] * lanes
    end = frames  # the frame the simulation ended at
    for k in range(frames + 1):
        reach = 0.5 * dyn.ego_width * math.cos(heading) + half_length * abs(math.sin(heading))
        alone = True
        for lane in range(lanes):
            if abs(y - lane * width) < reach + 0.5 * dyn.body_width:
                last[lane] = k
                alone = alone and lane == final
                if abs(y - lane * width) > band:  # overlapped, but out of MOBIL's sight there
                    seen[lane] = False
        end = k
        if k == frames or not speed > 0.0 or (alone and (y - target_y) * heading <= 0.0):
            break
        lateral_speed_command = -dyn.kp_lateral * (y - target_y)
        heading_command = math.asin(min(max(lateral_speed_command / speed, -1.0), 1.0))
        heading_ref = min(max(heading_command, -0.25 * math.pi), 0.25 * math.pi)
        heading_rate_command = dyn.kp_heading * (heading_ref - heading)
        slip = math.asin(min(max(half_length / speed * heading_rate_command, -1.0), 1.0))
        steering = min(max(math.atan(2.0 * math.tan(slip)), -dyn.max_steering), dyn.max_steering)
        beta = math.atan(0.5 * math.tan(steering))
        y = y + speed * math.sin(heading + beta) * dt
        heading = heading + speed * math.sin(beta) / half_length * dt
    windows = []
    for lane in range(lanes):
        if lane == final or last[lane] < 0:
            continue
        # Still overlapped when the simulation ended without settling (the horizon, a standstill): for good.
        windows.append((lane, math.inf if last[lane] == end else (last[lane] + 1) * dt + dt))  # clear, +1 frame
    return [*windows, (final, math.inf)], {lane for lane in range(lanes) if seen[lane] and lane != final}


def available_actions(state: RoadState, dyn: Dynamics) -> np.ndarray:
    """highway-env's ``DiscreteMetaAction.get_available_actions()`` as a bool mask."""
    avail = np.zeros(N_ACTIONS, dtype=bool)
    avail[IDLE] = True
    avail[LANE_LEFT] = state.ego_lane > 0
    avail[LANE_RIGHT] = state.ego_lane < dyn.lanes_count - 1
    avail[FASTER] = state.ego_speed_index < len(dyn.target_speeds) - 1
    avail[SLOWER] = state.ego_speed_index > 0
    return avail


@dataclass
class _Occupancy:
    """For each other vehicle, the lanes it may occupy and from when [s] (robust adds cut-ins)."""

    vehicle: list[int] = field(default_factory=list)
    lane: list[int] = field(default_factory=list)
    start: list[float] = field(default_factory=list)
    nominal: list[bool] = field(default_factory=list)  # also a conflict of the nominal model

    def add(self, vehicle: int, lane: int, start: float, nominal: bool) -> None:
        self.vehicle.append(vehicle)
        self.lane.append(lane)
        self.start.append(start)
        self.nominal.append(nominal)


def _occupancy(state: RoadState, dyn: Dynamics, mode: Mode, near: np.ndarray) -> _Occupancy:
    occ = _Occupancy()
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    for i in near:
        own = int(lanes[i])
        occ.add(int(i), own, 0.0, True)
        if mode != "robust":
            continue
        # Heading angle (Section IV.4b): a vehicle already moving sideways is in the next lane too.
        nxt = -10
        if abs(state.heading[i]) > LATERAL_MOTION_THRESHOLD or abs(state.vy[i]) > 0.3:
            direction = 1 if state.vy[i] > 0 else -1
            nxt = own + direction
            if dyn.finishing_changes and finishing_change(state, dyn, int(i), own, direction):
                nxt = -10  # it may still cut in from its lane: a cut-in candidate there, MOBIL-filtered
            elif 0 <= nxt < dyn.lanes_count:
                occ.add(int(i), nxt, 0.0, False)
        if dyn.reversing_noses and state.vx[i] < 0.0 and abs(state.heading[i]) > LATERAL_MOTION_THRESHOLD:
            # Rolling backwards it moves away from the lane its nose points to, and drives there as soon as
            # it moves forward again (a jammed IDM car: issue 15, the agents' cell 126).
            nose = own + (1 if state.heading[i] > 0 else -1)
            if nose != nxt and 0 <= nose < dyn.lanes_count:
                occ.add(int(i), nose, 0.0, False)
        if dyn.body_extent:
            # Its body, rotated by its heading, reaches this far either side of its centre [m]; it is
            # in every lane whose band that overlaps (a slow car turning hard sticks its rear corner
            # into the lane it is leaving: issue 15, cell00537).
            reach = abs(0.5 * state.length[i] * math.sin(state.heading[i])) + abs(
                0.5 * dyn.body_width * math.cos(state.heading[i])
            )
            for side in (own - 1, own + 1):
                if side == nxt or not 0 <= side < dyn.lanes_count:
                    continue
                centre, half_lane = side * dyn.lane_width, 0.5 * dyn.lane_width
                if state.y[i] + reach > centre - half_lane and state.y[i] - reach < centre + half_lane:
                    occ.add(int(i), side, 0.0, False)
    return occ


def permit_times(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray, ego_target: float
) -> np.ndarray:
    """The first frame time [s] of the decision at which MOBIL's safety criterion lets each vehicle of ``near``
    change into the ego's lane ahead of it, the ego its new follower (``Dynamics.cut_in_when_permitted``): the
    criterion of :func:`_cut_in_candidates` at every frame of the decision instead of now and at its end, the
    ego on the action's path (``ego_xs`` [m], ``ego_vs`` [m/s]: frames 0 … frames) and the car at its fastest
    (accelerating at its limit from now, which only makes the criterion allow more and earlier); inf: at none.
    0 for a car moving backwards with ``reversing_cut_ins`` (any lane change). With the option a permitted
    cut-in starts at this time plus the cut-in time rather than at the cut-in time from now: the car decides
    its lane change only when MOBIL lets it (issue 15, twelfth session: a car passing a stopped ego in the next
    lane, 3 m ahead, is not allowed to cut in now — the ego would have to brake at 28 m/s² — but is at the end
    of the decision, 24 m ahead; it was assumed in the ego's lane from now)."""
    out = np.full(near.size, np.inf)
    if near.size == 0:
        return out
    t = dyn.times[: ego_xs.shape[0]]
    target = np.clip(ego_target, 0.0, state.speed_limit)
    linear = np.isfinite(state.linear_speed_gain[near])
    accel = np.maximum(state.accel_max[near], 0.0)
    brake = np.maximum(state.brake_max[near], 1e-6)
    limit = -state.max_braking_imposed[near]
    for f in range(t.size):
        tau = t[f]
        x_f = state.x[near] + state.vx[near] * tau + 0.5 * accel * tau * tau
        v_f = state.vx[near] + accel * tau
        d = x_f - ego_xs[f]
        ego_v = np.full(near.size, ego_vs[f])
        if dyn.permit_any_speed:
            # IDM's desired gap d* falls with the car's speed and can go negative (a car much faster than the
            # ego); highway-env squares d*/d, so the criterion is loosest at the car's speed with the least
            # |d*| in [braking from now, accelerating from now], not at its fastest (issue 15, thirteenth session).
            v_lo = np.maximum(state.vx[near] - brake * tau, 0.0)
            q = least_desired_gap(state, near, ego_vs[f], v_lo, v_f)
            a = idm_acceleration_behind_gap(state, near, d, ego_v, np.full(near.size, target), q)
            a = np.where(d > 0.0, a, -np.inf)  # MOBIL sees the ego as the new follower only behind the car
        else:
            a = idm_acceleration_behind(state, near, d, ego_v, np.full(near.size, target), v_f)
        if linear.any() and dyn.linear_mobil:
            own = np.hypot(state.vx[near], state.vy[near]) + accel * tau
            a_lin = linear_acceleration_behind(state, near, d, ego_v, np.full(near.size, float(ego_target)), own)
            a = np.where(linear, a_lin, a)
        elif linear.any():
            a = np.where(linear, np.inf, a)
        newly = (a >= limit) & ~np.isfinite(out)
        out[newly] = tau
    if dyn.reversing_cut_ins:
        out[state.vx[near] < 0.0] = 0.0
    return out


def required_gap(state: RoadState, i: int, ego_speed: float, ego_target: float, tau: float) -> float:
    """The smallest centre distance [m] ahead of the ego at which MOBIL's safety criterion lets vehicle ``i``
    cut in front of it at time ``tau`` [s] (the ego at ``ego_speed`` [m/s], set-point ``ego_target``), whatever
    speed the car has then within its reach since now: the criterion of :func:`permit_times` solved for the
    distance; inf where it allows it at none. IDM drivers:
    ``a = free − acc·(d*/d)² ≥ −b_safe`` gives ``d ≥ |d*| / √((free + b_safe)/acc)``, with the least ``|d*|``
    over the car's speeds in reach (:func:`least_desired_gap`, as ``permit_any_speed`` takes it); linear-model
    drivers (with ``linear_mobil``): ``d ≥ d_safe − (C + b_safe)/k₂`` with ``C`` the formula's other terms at
    the car's fastest (the formula grows with its speed). Never below 0:
    MOBIL sees the ego as the new follower only while the car's centre is ahead of the ego's."""
    limit = -float(state.max_braking_imposed[i])
    accel = max(float(state.accel_max[i]), 0.0)
    dw, tw = float(state.idm_distance_wanted[i]), float(state.idm_time_wanted[i])
    if math.isfinite(float(state.linear_speed_gain[i])):
        own = math.hypot(float(state.vx[i]), float(state.vy[i])) + accel * tau
        k0, k1 = float(state.linear_speed_gain[i]), float(state.linear_speed_difference_gain[i])
        k2 = float(state.linear_distance_gain[i])
        other = k0 * (ego_target - ego_speed) + k1 * min(own - ego_speed, 0.0)
        if not (other >= limit and k2 > 0.0):
            return math.inf
        d_safe = dw + max(ego_speed, 0.0) * tw
        return max(d_safe - (other - limit) / k2, 0.0)
    acc, delta = float(state.idm_comfort_acc[i]), float(state.idm_delta[i])
    target = min(max(ego_target, 0.0), float(state.speed_limit))
    target = 1e-2 if abs(target) < 1e-2 else target
    free = acc * (1 - math.pow(max(ego_speed, 0.0) / abs(target), delta))
    room = (free - limit) / acc
    if not room > 0.0:
        return math.inf
    b = max(float(state.brake_max[i]), 1e-6)
    v_lo, v_hi = max(float(state.vx[i]) - b * tau, 0.0), float(state.vx[i]) + accel * tau
    who = np.array([i])
    q = float(least_desired_gap(state, who, ego_speed, np.array([v_lo]), np.array([v_hi]))[0])
    return q / math.sqrt(room)


def passing_positions(
    state: RoadState, dyn: Dynamics, i: int, ego_xs: np.ndarray, ego_vs: np.ndarray, ego_target: float,
    first: float, allowance: float,
) -> np.ndarray:  # fmt: skip
    """A lower bound on the position [m] along the road, at every frame of the horizon, of vehicle ``i`` — now
    behind the ego in a next lane — once it has cut into the ego's lane *ahead* of it (``passing_cut_ins``):
    MOBIL's safety criterion is judged with the ego as the new follower, so the car decides only while it is
    at least :func:`required_gap` ahead, at a frame of the decision from ``first`` [s] (:func:`permit_times`)
    on; its body is in the lane from that frame plus the cut-in time, and it brakes at its limit from its
    lowest speed then (braking from now). The minimum over those decision frames, less ``allowance`` [m]
    (:func:`turning_allowance`); inf before the earliest entry. ``ego_xs`` [m], ``ego_vs`` [m/s]: the ego on
    the action's path at the decision's frames (0 … frames). Why (issue 15, thirteenth session): a car passing a
    slow or stopped ego in the next lane, behind it now, was bounded as a follower entering the ego's lane —
    driving on through the ego — though MOBIL lets it in only ahead."""
    t = dyn.times
    out = np.full(t.size, np.inf)
    b = max(float(state.brake_max[i]), 1e-6)
    for f in range(ego_xs.shape[0]):
        tau = float(t[f])
        if not tau >= first:
            continue
        d_req = required_gap(state, i, float(ego_vs[f]), ego_target, tau)
        if not math.isfinite(d_req):
            continue
        v = max(float(state.vx[i]) - b * tau, 0.0)
        lo = int(np.searchsorted(t, tau + dyn.cut_in_time, side="left"))
        s = t[lo:] - tau
        tt = np.minimum(s, v / b)
        x = ((float(ego_xs[f]) + d_req) + (v * tt - 0.5 * b * (tt * tt))) - allowance
        out[lo:] = np.minimum(out[lo:], x)
    return out


def finishing_change(state: RoadState, dyn: Dynamics, i: int, own: int, direction: int) -> bool:
    """Whether vehicle ``i``, in lane ``own`` and moving sideways in ``direction`` (±1 lane), is finishing a
    lane change *into* that lane (``Dynamics.finishing_changes``): moving forward, its centre short of the
    lane's centre [m] and moving toward it.

    highway-env steers a car to its target lane's centre and changes the target only by a new MOBIL decision,
    taken while its lane is its target (``IDMVehicle.change_lane_policy``). A car that has crossed into a lane
    and is moving toward its centre is either settling there or has just decided to go on; the heading
    projection put it in the lane beyond from now — the lane next to it, the ego's — whatever MOBIL says
    (issue 15: 283 of 295 sampled 'second_lane_cut_in' breaks, a car from two lanes over settling in the lane
    next to the ego). With the option it is a cut-in candidate from its own lane like any car there: into the
    ego's lane only if MOBIL's safety criterion allows it, from the cut-in time. A car rolling backwards
    steers the wrong way and keeps the projection."""
    if not state.vx[i] >= 0.0:
        return False
    return (own * dyn.lane_width - float(state.y[i])) * direction > 0.0


def _cut_in_candidates(
    state: RoadState,
    dyn: Dynamics,
    near: np.ndarray,
    ego_x_end: float,
    ego_v_end: float,
    ego_target: float,
    ego_path: tuple[np.ndarray, np.ndarray],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Vehicles that may change into a lane the ego uses: (ahead, into a lane the ego is in; ahead, into a
    lane the ego is entering; level with or behind the ego, into a lane the ego is in; level with or behind
    the ego, into a lane it is entering — the last two for ``level_cut_ins``).

    Into a lane the ego already occupies, a vehicle changes lane only if its own rule allows it:
    MOBIL's safety criterion (highway-env) requires the acceleration its own model predicts for its new
    follower — the ego — to stay ≥ −LANE_CHANGE_MAX_BRAKING_IMPOSED: IDM's formula
    (:func:`idm_acceleration_behind`), or the linear model's for Linear, Aggressive and Defensive drivers
    (:func:`linear_acceleration_behind`). The ego is taken as that follower
    (conservative and independent of the other vehicles, which keeps the model monotone); the
    criterion is checked now and at the end of the decision period (others at constant speed, the ego
    on the action's trajectory). Into a lane the ego is only *entering*, the other driver cannot see the
    ego there when it decides, so any moving vehicle ahead may cut in.

    A vehicle whose centre is behind the ego's, now or at the end of the period (the ego overtaking it),
    sees the ego as its new *leader*: MOBIL's safety criterion then protects its new follower, not the
    ego, so any of them may turn in (issue 15, cell 470: a car just overtaken turned into the ego's
    rear flank). With ``level_cut_ins`` the rule counts them as followers entering the ego's lanes; with
    ``level_incentive`` only those MOBIL's incentive lets move behind the ego (:func:`turn_in_incentive`).
    That incentive is judged with the ego in the lane, so into a lane the ego is only *entering* it does
    not hold either (issue 15, the trained agents' cells 169 and 440: a car two lanes over, level with the
    ego, changed into the lane the ego was changing into — it saw no ego there when it decided): with
    ``level_entering`` every level car counts there.
    A car moving backwards steers the wrong way (highway-env's steering assumes forward motion: a lane change
    away from the ego swings its nose into the ego's lane; the trained agents' cell 615): with
    ``reversing_cut_ins`` it may enter the ego's lanes whatever MOBIL says, ahead or level.
    ``ego_path``: the ego's positions [m] and speeds [m/s] at the decision's frames (0 … frames), for
    ``linear_incentive_braking``.
    """
    if near.size == 0:
        return (np.zeros(0, dtype=bool),) * 4
    can = state.can_change_lane[near] & (np.abs(state.vx[near]) >= 1.0)
    target = np.clip(ego_target, 0.0, state.speed_limit)
    d_now = state.x[near] - state.ego_x
    d_end = state.x[near] + state.vx[near] * dyn.decision_period - ego_x_end
    v_now, v_end = np.full(near.size, state.ego_speed), np.full(near.size, ego_v_end)
    a_now = idm_acceleration_behind(state, near, d_now, v_now, np.full(near.size, target))
    a_end = idm_acceleration_behind(state, near, d_end, v_end, np.full(near.size, target))
    linear = np.isfinite(state.linear_speed_gain[near])
    if linear.any() and dyn.linear_mobil:  # Linear / Aggressive / Defensive drivers: their own formula
        who, set_point = near[linear], np.full(int(linear.sum()), float(ego_target))
        a_now[linear] = linear_acceleration_behind(state, who, d_now[linear], v_now[linear], set_point)
        a_end[linear] = linear_acceleration_behind(state, who, d_end[linear], v_end[linear], set_point)
    elif linear.any():  # the earlier rule: their criterion was not modelled, so any cut-in was allowed
        a_now[linear] = np.inf
    limit = -state.max_braking_imposed[near]
    ahead = (d_now > 0) | (d_end > 0)
    level_any = (d_now <= 0) | (d_end <= 0)
    if dyn.level_cut_ins and dyn.level_incentive:
        incentive = turn_in_incentive(state, dyn, near, d_now, d_end, ego_v_end)
        if dyn.linear_incentive:  # linear-model drivers' incentive with their own formula
            linear_gain = linear_turn_in_incentive(state, dyn, near, d_now, d_end, ego_v_end)
            if dyn.linear_incentive_braking:
                linear_gain = linear_gain | linear_turn_in_incentive_braking(state, dyn, near, *ego_path)
            level = np.where(linear, linear_gain, incentive)
        else:  # the earlier rule: their incentive was not modelled, so any turn-in was assumed
            level = np.where(linear, level_any, incentive)
    else:
        level = level_any
    permitted = (a_now >= limit) | (a_end >= limit)
    if dyn.reversing_cut_ins:  # steering assumes forward motion: reversing, a lane change away swings its nose in
        reversing = state.vx[near] < 0.0
        permitted, level = permitted | reversing, level | (reversing & level_any)
    level_entering = level_any if dyn.level_entering else level
    return can & ahead & permitted, can & ahead, can & level, can & level_entering


def _gap_ratio(state: RoadState, who: np.ndarray, front_speed: np.ndarray, gap: np.ndarray) -> np.ndarray:
    """IDM's ``d*/d`` for vehicles ``who`` following a vehicle at ``front_speed`` [m/s], ``gap`` [m] centre to
    centre (``IDMVehicle.desired_gap`` over ``not_zero(lane_distance_to)``), with their own parameters."""
    v = state.vx[who]
    ab = -state.idm_comfort_acc[who] * state.idm_comfort_dec[who]
    d_star = state.idm_distance_wanted[who] + v * state.idm_time_wanted[who] + v * (v - front_speed) / (2 * np.sqrt(ab))
    d = np.where(np.abs(gap) < 1e-2, 1e-2, gap)
    return d_star / d


def turn_in_incentive(
    state: RoadState, dyn: Dynamics, near: np.ndarray, d_now: np.ndarray, d_end: np.ndarray, ego_v_end: float
) -> np.ndarray:
    """Whether each vehicle of ``near``, with its centre behind the ego's (``d_now`` / ``d_end`` [m]: its
    offset ahead of the ego now / at the end of the decision, others at constant speed), may gain by moving
    behind the ego: MOBIL's incentive with politeness 0 (highway-env's ``IDMVehicle``), ``a(behind the
    ego) − a(behind its leader) ≥`` :data:`MOBIL_MIN_ACC_GAIN`. The free-road terms cancel, leaving
    ``acc·(d*/d)²_leader − acc·(d*/d)²_ego``. Its leader's term is taken as the largest over every vehicle
    ahead of it in its lane (IDM sees the nearest; the largest can only overstate the gain, and it keeps
    the rule monotone: adding a vehicle never removes a conflict); none: 0. Checked now and at the end of
    the decision, as the cut-in criterion is (an approximation within the decision, not a bound): a car in
    free flow loses by tucking in behind the ego at a short gap; one stuck in a slow queue gains (cell 470)."""
    x, v, t = state.x[near], state.vx[near], dyn.decision_period
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    acc = state.idm_comfort_acc[near]
    lead_now = np.zeros(near.size)
    lead_end = np.zeros(near.size)
    for j in range(near.size):
        rows = np.flatnonzero((lanes == lanes[j]) & (x > x[j]))  # every vehicle ahead of it in its lane
        if rows.size:
            who = np.full(rows.size, near[j])
            q_now = _gap_ratio(state, who, v[rows], x[rows] - x[j])
            q_end = _gap_ratio(state, who, v[rows], (x[rows] + v[rows] * t) - (x[j] + v[j] * t))
            lead_now[j] = (q_now * q_now).max()
            lead_end[j] = (q_end * q_end).max()
    q_ego_now = _gap_ratio(state, near, np.full(near.size, state.ego_speed), -d_now)
    q_ego_end = _gap_ratio(state, near, np.full(near.size, ego_v_end), -d_end)
    gain_now = acc * lead_now - acc * (q_ego_now * q_ego_now)
    gain_end = acc * lead_end - acc * (q_ego_end * q_ego_end)
    return ((d_now <= 0) & (gain_now >= MOBIL_MIN_ACC_GAIN)) | ((d_end <= 0) & (gain_end >= MOBIL_MIN_ACC_GAIN))


def linear_turn_in_incentive(
    state: RoadState, dyn: Dynamics, near: np.ndarray, d_now: np.ndarray, d_end: np.ndarray, ego_v_end: float
) -> np.ndarray:
    """:func:`turn_in_incentive` for drivers with the linear acceleration model (Linear, Aggressive,
    Defensive; NaN gains elsewhere give False), with their own formula, as highway-env's ``IDMVehicle.mobil``
    applies it through ``LinearVehicle.acceleration``: politeness 0, so the gain is
    ``a(behind the ego) − a(behind its leader)``, and the target-speed term ``k₀·(v* − v)`` cancels, leaving
    ``k₁·min(v_front − v, 0) + k₂·min(d − d_safe, 0)`` per front vehicle, ``d_safe = DISTANCE_WANTED +
    max(v, 0)·TIME_WANTED`` [m], ``d`` [m] centre to centre. No leader: its term is 0, so a car on a free lane
    never gains by moving behind the ego. The leader's term is the most negative over every vehicle ahead of
    it in its lane (monotone, as for IDM). The threshold is :data:`MOBIL_MIN_ACC_GAIN` (0.2 m/s², Linear's);
    Aggressive and Defensive drivers need 1.0, so the rule assumes more turn-ins than they make."""
    x, v, t = state.x[near], state.vx[near], dyn.decision_period
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_now = np.zeros(near.size)
    lead_end = np.zeros(near.size)
    for j in range(near.size):
        if not np.isfinite(state.linear_speed_gain[near[j]]):
            continue
        rows = np.flatnonzero((lanes == lanes[j]) & (x > x[j]))  # every vehicle ahead of it in its lane
        if rows.size:
            closing = k1[j] * np.minimum(v[rows] - v[j], 0.0)
            gap_end = (x[rows] + v[rows] * t) - (x[j] + v[j] * t)
            lead_now[j] = (closing + k2[j] * np.minimum((x[rows] - x[j]) - d_safe[j], 0.0)).min()
            lead_end[j] = (closing + k2[j] * np.minimum(gap_end - d_safe[j], 0.0)).min()
    ego_now = k1 * np.minimum(state.ego_speed - v, 0.0) + k2 * np.minimum(-d_now - d_safe, 0.0)
    ego_end = k1 * np.minimum(ego_v_end - v, 0.0) + k2 * np.minimum(-d_end - d_safe, 0.0)
    gain_now = ego_now - lead_now
    gain_end = ego_end - lead_end
    return ((d_now <= 0) & (gain_now >= MOBIL_MIN_ACC_GAIN)) | ((d_end <= 0) & (gain_end >= MOBIL_MIN_ACC_GAIN))


def linear_turn_in_incentive_braking(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """:func:`linear_turn_in_incentive` at every physics frame of the decision (``ego_xs`` [m], ``ego_vs``
    [m/s]: the ego's positions and speeds at its frames 0 … frames) with every vehicle ahead of the driver in
    its lane braking at its maximum from now (a crashed one stopped), the driver itself at constant speed:
    ``shield.linear_incentive_braking``. Its leader braking only makes the driver's own lane worse, so this
    can only find more turn-ins than the check now and at the end at constant speeds (which it is OR-ed
    with). Why (issue 15, seventh session, cell 535): a Linear car closing on a slow car 9 m ahead at 7.5
    m/s gained −5.4 m/s² now and −1 at the end by moving behind the ego, and turned in within the decision
    as its leader braked."""
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    lead_b = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    out = np.zeros(near.size, dtype=bool)
    for j in range(near.size):
        if not np.isfinite(state.linear_speed_gain[near[j]]):
            continue
        rows = np.flatnonzero((lanes == lanes[j]) & (x > x[j]))
        for f in range(times.size):
            tau = times[f]
            own_x = x[j] + v[j] * tau
            d = own_x - ego_xs[f]
            if not d <= 0:
                continue
            # np.minimum, not min: NaN propagates as in the compiled kernel.
            ego_term = k1[j] * np.minimum(ego_vs[f] - v[j], 0.0) + k2[j] * np.minimum(-d - d_safe[j], 0.0)
            lead_term = 0.0
            for q, r in enumerate(rows):
                tt = np.minimum(tau, lead_v0[r] / lead_b[r])
                lx = x[r] + lead_v0[r] * tt - 0.5 * lead_b[r] * (tt * tt)
                lv = lead_v0[r] - lead_b[r] * tt
                term = k1[j] * np.minimum(lv - v[j], 0.0) + k2[j] * np.minimum((lx - own_x) - d_safe[j], 0.0)
                lead_term = term if q == 0 else np.minimum(lead_term, term)
            if ego_term - lead_term >= MOBIL_MIN_ACC_GAIN:
                out[j] = True
                break
    return out


def _desired_gap_range(
    dw: float, tw: float, root_ab: float, v_lo: float, v_hi: float, front_lo: float, front_hi: float
) -> tuple[float, float]:
    """The least and largest of IDM's desired gap ``d* = d₀ + v·T + v·(v − v_front)/(2√(ab))`` [m] over a
    driver's speeds ``v`` in ``[v_lo, v_hi]`` and its front vehicle's in ``[front_lo, front_hi]`` [m/s]
    (``v ≥ 0``): falling in ``v_front``; convex in ``v``, so the largest at an end of the range and the least
    at the vertex ``(v_front − T·2√(ab))/2`` clipped to it."""
    c = 2 * root_ab
    top = max(dw + v * tw + v * (v - front_lo) / c for v in (v_lo, v_hi))
    vertex = min(max(0.5 * (front_hi - tw * c), v_lo), v_hi)
    bottom = dw + vertex * tw + vertex * (vertex - front_hi) / c
    return bottom, top


def incentive_times_any_speed(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """:func:`incentive_times` as a bound (``Dynamics.incentive_any_speed``): the first frame time [s] of the
    decision at which MOBIL's incentive *could* let each vehicle of ``near`` turn in behind the ego, whatever
    it and the vehicles ahead of it in its lane do within their limits — each between braking at its limit
    from now (a crashed one stopped) and accelerating at its limit from now, the ego on the action's path.
    The gain ``a(behind the ego) − a(behind its leader)`` is bounded above by the least its term behind the
    ego can be (the car slowest, farthest back) and the largest its leader's can be (the car fastest, the
    leader slowest and nearest; a gap that can close: unbounded), the leader's term the largest over every
    vehicle ahead of it, as :func:`turn_in_incentive` takes it. Its centre must be able to be behind the
    ego's. inf: at none. Why: :func:`incentive_times` (others at constant speed) was decided one physics
    frame late by 5 of 45 highway-env turn-ins (``examples/turn_in_timing.py``; issue 15, fourteenth session)."""
    out = np.full(near.size, np.inf)
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    brake = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    accel = np.where(state.crashed[near], 0.0, np.maximum(state.accel_max[near], 0.0))
    speed = np.where(state.crashed[near], 0.0, np.hypot(v, state.vy[near]))
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    for f in range(times.size):
        tau = times[f]
        stop = np.minimum(tau, v0 / brake)
        x_lo = x + v0 * stop - 0.5 * brake * (stop * stop)  # braking at its limit from now
        v_lo = v0 - brake * stop
        x_hi = x + v0 * tau + 0.5 * accel * (tau * tau)  # accelerating at its limit from now
        v_hi = speed + accel * tau  # IDM and MOBIL read the whole speed, not only along the road
        for j in range(near.size):
            if np.isfinite(out[j]) or not x_lo[j] - ego_xs[f] <= 0:
                continue
            i = near[j]
            linear = bool(np.isfinite(state.linear_speed_gain[i]))
            rows = np.flatnonzero((lanes == lanes[j]) & (x > x[j]))  # every vehicle ahead of it in its lane
            gap_ego = ego_xs[f] - x_lo[j]  # [m] centre to centre, the car farthest back
            if linear and dyn.linear_incentive:
                k1, k2 = state.linear_speed_difference_gain[i], state.linear_distance_gain[i]
                dw, tw = state.idm_distance_wanted[i], state.idm_time_wanted[i]
                ego_term = k1 * min(ego_vs[f] - v_lo[j], 0.0) + k2 * min(gap_ego - (dw + v_lo[j] * tw), 0.0)
                lead = 0.0  # no vehicle ahead: its term is 0
                if rows.size:
                    closing = k1 * np.minimum(v_lo[rows] - v_hi[j], 0.0)  # leaders slowest, the car fastest
                    gap = x_lo[rows] - x_hi[j]
                    lead = float((closing + k2 * np.minimum(gap - (dw + v_hi[j] * tw), 0.0)).min())
                if ego_term - lead >= MOBIL_MIN_ACC_GAIN:
                    out[j] = tau
            elif not linear:
                acc, dw, tw = state.idm_comfort_acc[i], state.idm_distance_wanted[i], state.idm_time_wanted[i]
                root_ab = float(np.sqrt(-acc * state.idm_comfort_dec[i]))
                lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo[j], v_hi[j], ego_vs[f], ego_vs[f])
                least = lo if lo > 0.0 else (-hi if hi < 0.0 else 0.0)
                q_ego = least / max(gap_ego, 1e-2)
                ego_term = q_ego * q_ego
                lead = 0.0
                for r in rows:
                    gap = x_lo[r] - x_hi[j]
                    if not gap >= 1e-2:
                        lead = np.inf  # the gap may close: IDM's term has no bound
                        break
                    lo, hi = _desired_gap_range(dw, tw, root_ab, v_lo[j], v_hi[j], v_lo[r], v_hi[r])
                    q = max(hi, -lo) / gap
                    lead = max(lead, q * q)
                if acc * lead - acc * ego_term >= MOBIL_MIN_ACC_GAIN:
                    out[j] = tau
    return out


def incentive_times(
    state: RoadState, dyn: Dynamics, near: np.ndarray, ego_xs: np.ndarray, ego_vs: np.ndarray
) -> np.ndarray:
    """The first frame time [s] of the decision at which MOBIL's incentive lets each vehicle of ``near`` turn
    in behind the ego (``Dynamics.level_when_incentive`` with ``incentive_any_speed`` false — issue 15's thirteenth
    session's timing, not a bound; :func:`incentive_times_any_speed` is): :func:`turn_in_incentive` (IDM) or
    :func:`linear_turn_in_incentive` (linear-model drivers) at every frame instead of now and at the end, the
    others at constant speed and the ego on the action's path; for linear-model drivers also
    :func:`linear_turn_in_incentive_braking`'s frames. Its centre must be behind the ego's at that frame. inf:
    at none (then only the now-and-end verdict, from the cut-in time)."""
    out = np.full(near.size, np.inf)
    x, v = state.x[near], state.vx[near]
    lanes = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    acc = state.idm_comfort_acc[near]
    k1, k2 = state.linear_speed_difference_gain[near], state.linear_distance_gain[near]
    d_safe = state.idm_distance_wanted[near] + np.maximum(v, 0.0) * state.idm_time_wanted[near]
    lead_v0 = np.where(state.crashed[near], 0.0, np.maximum(v, 0.0))
    lead_b = np.maximum(np.where(state.crashed[near], 1e9, state.brake_max[near]), 1e-6)
    times = np.arange(ego_xs.shape[0]) * dyn.frame_dt
    for j in range(near.size):
        linear = bool(np.isfinite(state.linear_speed_gain[near[j]]))
        rows = np.flatnonzero((lanes == lanes[j]) & (x > x[j]))
        who = np.full(rows.size, near[j])
        for f in range(times.size):
            tau = times[f]
            own_x = x[j] + v[j] * tau
            d = own_x - ego_xs[f]
            if not d <= 0:
                continue
            if linear and dyn.linear_incentive:
                ego_term = k1[j] * np.minimum(ego_vs[f] - v[j], 0.0) + k2[j] * np.minimum(-d - d_safe[j], 0.0)
                lead = braking = 0.0  # no vehicle ahead: its term is 0
                if rows.size:
                    gap = (x[rows] + v[rows] * tau) - own_x
                    lead = (k1[j] * np.minimum(v[rows] - v[j], 0.0) + k2[j] * np.minimum(gap - d_safe[j], 0.0)).min()
                    tt = np.minimum(tau, lead_v0[rows] / lead_b[rows])
                    lx = x[rows] + lead_v0[rows] * tt - 0.5 * lead_b[rows] * (tt * tt)
                    lv = lead_v0[rows] - lead_b[rows] * tt
                    braking = (
                        k1[j] * np.minimum(lv - v[j], 0.0) + k2[j] * np.minimum((lx - own_x) - d_safe[j], 0.0)
                    ).min()
                gains = ego_term - lead >= MOBIL_MIN_ACC_GAIN
                if dyn.linear_incentive_braking:
                    gains = gains or ego_term - braking >= MOBIL_MIN_ACC_GAIN
                if gains:
                    out[j] = tau
                    break
            elif not linear:
                lead = 0.0
                if rows.size:
                    q = _gap_ratio(state, who, v[rows], (x[rows] + v[rows] * tau) - own_x)
                    lead = float((q * q).max())
                q_ego = float(_gap_ratio(state, near[j : j + 1], np.array([ego_vs[f]]), np.array([-d]))[0])
                if acc[j] * lead - acc[j] * (q_ego * q_ego) >= MOBIL_MIN_ACC_GAIN:
                    out[j] = tau
                    break
    return out


@dataclass(frozen=True)
class CarriedFollowers:
    """The follower bounds an earlier decision drew, carried to this state (a probe of bounds nested in time,
    docs/safety.md §6s; the numpy reference only): per vehicle of the state, its position ``x`` [m] along the
    road and speed ``vx`` [m/s] ``age`` seconds ago (NaN: none carried)."""

    x: np.ndarray
    vx: np.ndarray
    age: float


def evaluate(
    state: RoadState,
    dyn: Dynamics,
    mode: Mode = "robust",
    formula: Formula = "kinematic",
    carried: CarriedFollowers | None = None,
) -> SafetyResult:
    """The safety mask of ``state`` (see the module docstring for the rule and the modes). ``carried``: a car
    behind is also bounded by the follower bound drawn ``carried.age`` s ago from where it was then
    (accelerate for the reaction time from then, then brake), the nearer of the two bounds kept — the rule's
    follower bound nested in time instead of started again (a diagnostic; the shield never passes it)."""
    return _evaluate(state, dyn, mode, formula, nominal_leaders=mode == "nominal", carried=carried)


def _evaluate(
    state: RoadState,
    dyn: Dynamics,
    mode: Mode,
    formula: Formula,
    nominal_leaders: bool,
    carried: CarriedFollowers | None = None,
) -> SafetyResult:
    """:func:`evaluate`; ``nominal_leaders``: the leaders bounded as nominal mode bounds them (nominal mode, and
    robust's straight fallback), else by ``turning_leaders``' bound."""
    if mode not in ("nominal", "robust"):
        raise ValueError(f"mode: got {mode!r}; allowed: 'nominal', 'robust'")
    if formula not in ("kinematic", "paper"):
        raise ValueError(f"formula: got {formula!r}; allowed: 'kinematic', 'paper'")
    available = available_actions(state, dyn)
    if mode == "nominal" and formula == "paper":
        safe, gaps = _paper_eq12(state, dyn)
        return _finish(safe & available, available, gaps, gaps)

    t = dyn.times
    ego_x, ego_v = ego_trajectories(state, dyn)  # (5, F, T)
    half = 0.5 * (state.length + state.ego_length)  # centre distance at contact [m]
    dx0 = state.x - state.ego_x
    near = np.flatnonzero((np.abs(dx0) < RELEVANCE_RANGE) & np.isfinite(state.x))
    ahead = dx0 >= 0
    # Worst-case longitudinal motion of every nearby vehicle: leaders brake, followers surge.
    stopped = state.crashed  # a crashed vehicle is treated as a wall where it stands
    brake = np.where(stopped, 1e9, state.brake_max)
    lead_v = np.where(stopped[near], 0.0, state.vx[near])
    # A heading effect, like cut-ins and body extent: robust only. Nominal's leaders keep braking along the road
    # (with turning_in_nominal: unless robust's bound is looser), and so does the straight fallback below: its
    # mask is chosen among nominal's bounds, so nominal ⊇ robust stays true of the final masks.
    path_allowance = turning_allowance(dyn)
    allowance = 0.0 if nominal_leaders else path_allowance
    turning = lead_v > 0.0
    lead_x = braking_positions(state.x[near], lead_v, brake[near], t, dyn.reversing_leaders)
    if path_allowance > 0.0 and (not nominal_leaders or dyn.turning_in_nominal):
        # turning_leaders: along its path, from its speed (issue 15, docs/safety.md §6f); nominal takes it only
        # where it is the looser (a fast car turning: v·sin h large), so robust ⊆ nominal by construction (§6o).
        vx_n, vy_n = state.vx[near], state.vy[near]
        path_v = np.where(turning, np.sqrt(vx_n * vx_n + vy_n * vy_n), lead_v)
        path_x = braking_positions(state.x[near], path_v, brake[near], t, dyn.reversing_leaders)
        path_x = np.where(turning[:, None], path_x - path_allowance, lead_x)
        lead_x = np.maximum(lead_x, path_x) if nominal_leaders else path_x
    foll_x = follower_positions(
        state.x[near], state.vx[near], state.accel_max[near], state.brake_max[near], dyn.follower_reaction, t
    )
    if carried is not None:
        then = np.isfinite(carried.x[near])
        earlier = follower_positions(
            np.where(then, carried.x[near], 0.0), np.where(then, carried.vx[near], 0.0), state.accel_max[near],
            state.brake_max[near], dyn.follower_reaction, t + carried.age,
        )  # fmt: skip
        foll_x = np.where(then[:, None], np.minimum(foll_x, earlier), foll_x)
    other_x = np.where(ahead[near][:, None], lead_x, foll_x)  # (m, T)
    row_of = {int(v): r for r, v in enumerate(near)}
    by_idm = idm_followers(state, dyn, near)  # follower_idm: these brake for the ego by IDM, per fallback

    occ = _occupancy(state, dyn, mode, near)
    targets = action_targets(state, dyn)
    frames = dyn.frames_per_decision
    n_fb = MAX_HOLD_DECISIONS + 1
    # Worst gap [m] per (action, fallback) over all conflicts of the mode, over those with vehicles
    # ahead only, and the same two over the nominal conflicts alone (for a consistent least-bad choice).
    joint_gap = np.full((N_ACTIONS, n_fb), np.inf)
    ahead_gap = np.full((N_ACTIONS, n_fb), np.inf)
    nominal_joint = np.full((N_ACTIONS, n_fb), np.inf)
    nominal_ahead = np.full((N_ACTIONS, n_fb), np.inf)
    nominal_ok = np.ones(N_ACTIONS, dtype=bool)  # every nominal conflict has *some* good fallback
    lanes_near = state.lane_of(state.y[near], dyn.lanes_count, dyn.lane_width)
    # _occupancy's sideways test: the lane each moving vehicle moves to (valid lanes only).
    moving_near = (np.abs(state.heading[near]) > LATERAL_MOTION_THRESHOLD) | (np.abs(state.vy[near]) > 0.3)
    projected_near = lanes_near + np.where(state.vy[near] > 0, 1, -1)
    moving_near &= (projected_near >= 0) & (projected_near < dyn.lanes_count)
    cut_ins: dict[tuple[float, float, float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    permits: dict[tuple[float, float, float], np.ndarray] = {}  # cut_in_when_permitted, on the same key
    idm_paths: dict[tuple[int, bytes, bytes], np.ndarray] = {}  # follower_idm: per car and ego trajectory
    for a in range(N_ACTIONS):
        if not available[a]:
            continue
        ego_lanes = _action_lanes(state, dyn, a)
        vehicles, lanes_v, starts, nominal_flags = occ.vehicle, occ.lane, occ.start, occ.nominal
        as_follower = [False] * len(vehicles)  # a conflict with a car turning in behind the ego (level_cut_ins)
        passing_paths: list[np.ndarray | None] = [None] * len(vehicles)  # passing_cut_ins: a leader's path
        if mode == "robust":
            occupied = {state.ego_lane, state.ego_target_lane}
            if dyn.lateral_schedule and dyn.leaving_lanes_seen:  # MOBIL still sees the ego in the lanes it leaves
                occupied |= lateral_schedule(state, dyn, final_lane(state, dyn, a))[1]
            # IDLE and the lane changes share one longitudinal trajectory: compute their cut-ins once.
            key = (float(ego_x[a, 0, frames]), float(ego_v[a, 0, frames]), float(targets[a]))
            if key not in cut_ins:
                path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                cut_ins[key] = _cut_in_candidates(state, dyn, near, *key, path)
                if dyn.cut_in_when_permitted:  # MOBIL at every frame of the decision: who, and from when
                    permits[key] = permit_times(state, dyn, near, *path, float(targets[a]))
            permitted, unfiltered, level, level_entering = cut_ins[key]
            permit_time = permits.get(key)
            if permit_time is not None:
                permitted = unfiltered & np.isfinite(permit_time)
            extra_v, extra_l, extra_s, extra_p = [], [], [], []
            for lane, _ in ego_lanes:
                cands = permitted if lane in occupied else unfiltered
                adjacent = np.abs(lanes_near - lane) == 1
                if dyn.projected_cut_ins:
                    # A vehicle already moving sideways toward the lane next to this one may finish that
                    # change and cut in from there (issue 15: 'second_lane_cut_in' breaks).
                    adjacent = adjacent | (moving_near & (np.abs(projected_near - lane) == 1))
                for j in np.flatnonzero(cands & adjacent):
                    extra_v.append(int(near[j]))
                    extra_l.append(lane)
                    after = float(permit_time[j]) if permit_time is not None and lane in occupied else 0.0
                    extra_s.append(dyn.cut_in_time + after)
                    i = int(near[j])
                    passing = (
                        dyn.passing_cut_ins and permit_time is not None and lane in occupied and not ahead[i]
                        and state.vx[i] >= 0.0 and (dyn.linear_mobil or not np.isfinite(state.linear_speed_gain[i]))
                    )  # fmt: skip
                    if passing:  # behind now, it cuts in only ahead of the ego: a leader from then
                        path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                        extra_p.append(passing_positions(state, dyn, i, *path, float(targets[a]), after, allowance))
                    else:
                        extra_p.append(None)
            behind_v, behind_l, behind_s = [], [], []
            turn_time = None
            if dyn.level_cut_ins and dyn.level_incentive and dyn.level_when_incentive:  # timing by the incentive
                path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                times_of = incentive_times_any_speed if dyn.incentive_any_speed else incentive_times
                turn_time = times_of(state, dyn, near, *path)
            if dyn.level_cut_ins:
                # A car level with or behind the ego in a next lane may turn in behind it after the cut-in
                # time and then follow it (accelerate for the reaction time, then brake): a follower.
                for lane, _ in ego_lanes:
                    turning = level if lane in occupied else level_entering
                    for j in np.flatnonzero(turning & (np.abs(lanes_near - lane) == 1)):
                        behind_v.append(int(near[j]))
                        behind_l.append(lane)
                        later = 0.0
                        if turn_time is not None and lane in occupied and np.isfinite(turn_time[j]):
                            later = float(turn_time[j])
                        behind_s.append(dyn.cut_in_time + later)
            vehicles = vehicles + extra_v + behind_v
            lanes_v = lanes_v + extra_l + behind_l
            starts = starts + extra_s + behind_s
            nominal_flags = nominal_flags + [False] * (len(extra_v) + len(behind_v))
            as_follower = as_follower + [False] * len(extra_v) + [True] * len(behind_v)
            passing_paths = passing_paths + extra_p + [None] * len(behind_v)
        # Every (vehicle, lane) pair that shares a lane with the ego, with the window in which both do.
        pairs = [
            (row_of[vi], start, until, is_nominal, follows, lane, path)
            for vi, lane, start, is_nominal, follows, path in zip(
                vehicles, lanes_v, starts, nominal_flags, as_follower, passing_paths, strict=True
            )
            for ego_lane, until in ego_lanes
            if ego_lane == lane
        ]
        if not pairs:
            continue
        rows = np.array([p[0] for p in pairs])
        window = (t[None, :] >= np.array([p[1] for p in pairs])[:, None]) & (
            t[None, :] <= np.array([p[2] for p in pairs])[:, None]
        )  # (c, T)
        is_nominal = np.array([p[3] for p in pairs], dtype=bool)
        follows = np.array([p[4] for p in pairs], dtype=bool)
        vehicle = near[rows]
        passing = np.array([p[6] is not None for p in pairs], dtype=bool)
        is_ahead = (ahead[vehicle] & ~follows) | passing
        sign = np.where(is_ahead, 1.0, -1.0)
        motion = np.where(follows[:, None], foll_x[rows], other_x[rows])[:, None, :]  # a car turning in follows
        for c in np.flatnonzero(passing):  # passing_cut_ins: cutting in ahead of the ego, a leader from then
            motion[c, 0] = pairs[c][6]
        idm_pairs = by_idm[rows] & ~follows & ~passing & (np.array([p[5] for p in pairs]) == state.ego_lane)
        if idm_pairs.any():  # follower_idm: the car behind responds to each fallback of the ego its own way
            motion = np.repeat(motion, n_fb, axis=1)
            for c in np.flatnonzero(idm_pairs):
                # IDLE and the lane changes share one longitudinal trajectory: simulate its response once
                # (a Python loop over the horizon's frames, a large share of the numpy reference's time).
                key = (int(vehicle[c]), ego_x[a].tobytes(), ego_v[a].tobytes())
                if key not in idm_paths:
                    idm_paths[key] = idm_follower_positions(state, dyn, key[0], ego_x[a], ego_v[a])
                motion[c] = idm_paths[key]
        gap = sign[:, None, None] * (motion - ego_x[a][None]) - half[vehicle][:, None, None]
        worst = np.where(window[:, None, :], gap, np.inf).min(axis=-1)  # (c, F) worst gap per fallback
        joint_gap[a] = worst.min(axis=0)
        if is_ahead.any():
            ahead_gap[a] = worst[is_ahead].min(axis=0)
        if is_nominal.any():
            nominal_joint[a] = worst[is_nominal].min(axis=0)
            if (is_nominal & is_ahead).any():
                nominal_ahead[a] = worst[is_nominal & is_ahead].min(axis=0)
            nominal_ok[a] = bool((worst[is_nominal].max(axis=1) >= dyn.margin).all())
    best_gap = np.where(available, joint_gap.max(axis=1), -np.inf)
    safe = ((best_gap >= dyn.margin) if mode == "robust" else nominal_ok) & available
    if not math.isfinite(dyn.ego_leave_time):
        # Too slow to move sideways: the ego would straddle two lanes indefinitely, unseen by the
        # new lane's followers (highway-env's IDM only sees a car within 3 m of its lane centre).
        safe[[LANE_LEFT, LANE_RIGHT]] = False
        nominal_ok[[LANE_LEFT, LANE_RIGHT]] = False
    if safe.any():
        return SafetyResult(safe.copy(), safe, available, False, best_gap)
    if mode == "robust" and dyn.straight_fallback and allowance > 0.0:
        # The stricter leader bound narrows what the rule promises, not what it falls back to: a spawned
        # scene the turning allowance leaves without a safe action is driven as the rule with nominal's leader
        # bound drives it — without turning_in_nominal, the rule without the allowance (issue 15: with
        # turning_leaders alone its least-bad choice crashed more of those scenes).
        straight = _evaluate(state, dyn, mode, formula, nominal_leaders=True, carried=carried)
        return SafetyResult(straight.mask.copy(), safe, available, True, best_gap)
    # Least-bad choice. Robust picks among the nominally safe actions when there are some (so that
    # robust ⊆ nominal holds for the final masks too), else exactly what nominal would pick.
    nominal_safe = nominal_ok & available
    if mode == "robust" and dyn.robust_fallback:  # every available action, by its robust gaps
        first, second, pool = ahead_gap, joint_gap, available
    elif mode == "robust" and nominal_safe.any():
        first, second, pool = ahead_gap, joint_gap, nominal_safe
    else:
        first, second, pool = nominal_ahead, nominal_joint, available
    if dyn.least_bad_joint:  # the worst gap to anybody first: a follower's or a car alongside's counts as much
        first, second = second, first
    forecast = forecast_ranking(state, dyn, ego_x, available) if dyn.forecast_fallback else None
    choice = least_bad_action(first.max(axis=1), second.max(axis=1), pool, forecast)
    return _fallback(choice, safe, available, best_gap)


def ego_last_frames(state: RoadState, dyn: Dynamics, available: np.ndarray) -> np.ndarray:
    """(5, lanes) the last frame of the horizon (:attr:`Dynamics.times`) in which the ego occupies each lane
    under each available action (:func:`_action_lanes`); −1: never."""
    t = dyn.times
    last = np.full((N_ACTIONS, dyn.lanes_count), -1, dtype=np.int64)
    for a in np.flatnonzero(available):
        for lane, until in _action_lanes(state, dyn, int(a)):
            last[a, lane] = max(last[a, lane], int(np.count_nonzero(t <= until)) - 1)  # NaN: never
    return last


def forecast_ranking(state: RoadState, dyn: Dynamics, ego_x: np.ndarray, available: np.ndarray) -> np.ndarray:
    """(5,) ``Dynamics.forecast_fallback``'s first key of the least-bad choice: each action's gap [m] under
    :func:`safelane.safety.forecast.forecast_gaps` (the others as they will most likely drive), capped at
    ``margin`` — actions the forecast keeps ``margin`` clear of everybody rank among themselves by their
    worst-case gaps, since past the margin the forecast says nothing about the risk the worst case measures —
    and −1 for every action the forecast sees collide (they too then rank by their worst-case gaps: the depth
    of a forecast overlap is no measure of harm; ranking by it drove FASTER into leaders, docs/safety.md §6q) —
    or, with ``Dynamics.forecast_contact_time``, a key in [−2, −1) that grows with the whole decisions before
    the first forecast contact (docs/safety.md §6r).
    ``ego_x``: (5, fallbacks, frames + 1) the ego's positions [m] (:func:`ego_trajectories`)."""
    gaps, contact_time = forecast_gaps(
        ego_x, ego_last_frames(state, dyn, available), available, dyn.frame_dt, state.ego_x, state.ego_length,
        dyn.lanes_count, dyn.lane_width, state.speed_limit, state.x, state.y, state.vx, state.vy, state.length,
        state.crashed, state.brake_max, state.accel_max, state.idm_delta, state.idm_comfort_acc,
        state.idm_comfort_dec, state.idm_distance_wanted, state.idm_time_wanted, state.linear_speed_gain,
        state.linear_speed_difference_gain, state.linear_distance_gain, set_points(state),
        dyn.forecast_contact_time, dyn.forecast_lane_changes, state.can_change_lane, state.max_braking_imposed,
        state.ego_lane,
    )  # fmt: skip
    horizon = dyn.frame_dt * (ego_x.shape[2] - 1)
    return forecast_keys(gaps, contact_time, dyn.margin, horizon, dyn.decision_period, dyn.forecast_contact_time)


def _finish(safe: np.ndarray, available: np.ndarray, gaps: np.ndarray, ahead_gaps: np.ndarray) -> SafetyResult:
    if safe.any():
        return SafetyResult(safe.copy(), safe, available, False, gaps)
    return _fallback(least_bad_action(ahead_gaps, gaps, available), safe, available, gaps)


def _fallback(choice: int, safe: np.ndarray, available: np.ndarray, gaps: np.ndarray) -> SafetyResult:
    mask = np.zeros(N_ACTIONS, dtype=bool)
    mask[choice] = True
    return SafetyResult(mask, safe, available, True, gaps)


def forecast_of(state: RoadState, dyn: Dynamics, action: int, fallback: int) -> tuple[np.ndarray, np.ndarray, float]:
    """The nominal forecast beside one of the ego's trajectories (``action`` then fallback ``fallback``, as
    :func:`ego_trajectories`): (indices of the forecast vehicles in ``state``, their positions [m] per frame of
    the horizon but the last, the smallest bumper gap [m] to the ego in a lane it occupies). For inspection and
    tests; the rule ranks by :func:`forecast_ranking`."""
    ego_x, _ = ego_trajectories(state, dyn)
    last = ego_last_frames(state, dyn, available_actions(state, dyn) | (np.arange(N_ACTIONS) == action))
    return forecast_paths(
        ego_x[action, fallback], last[action], dyn.frame_dt, state.ego_x, state.ego_length, dyn.lanes_count,
        dyn.lane_width, state.speed_limit, state.x, state.y, state.vx, state.vy, state.length, state.crashed,
        state.brake_max, state.accel_max, state.idm_delta, state.idm_comfort_acc, state.idm_comfort_dec,
        state.idm_distance_wanted, state.idm_time_wanted, state.linear_speed_gain, state.linear_speed_difference_gain,
        state.linear_distance_gain, set_points(state), dyn.forecast_lane_changes, state.can_change_lane,
        state.max_braking_imposed, state.ego_lane,
    )  # fmt: skip


def least_bad_action(
    ahead_gaps: np.ndarray, gaps: np.ndarray, pool: np.ndarray, forecast: np.ndarray | None = None
) -> int:
    """The action to allow when none is safe: largest worst-case gap [m] to vehicles *ahead* (the ego's
    own responsibility), then to everybody, then :data:`TIE_BREAK_ORDER` (``Dynamics.least_bad_joint``
    passes the two gap arrays the other way round). ``forecast`` (``Dynamics.forecast_fallback``,
    :func:`forecast_ranking`): a key [m] ranked before all of these."""
    best: tuple[float, float, float, int] | None = None
    choice = IDLE
    for rank, a in enumerate(TIE_BREAK_ORDER):
        if not pool[a]:
            continue
        first = 0.0 if forecast is None else float(forecast[a])
        key = (first, float(np.minimum(ahead_gaps[a], 1e6)), float(np.minimum(gaps[a], 1e6)), -rank)
        if best is None or key > best:
            best, choice = key, a
    return choice


def _paper_eq12(state: RoadState, dyn: Dynamics) -> tuple[np.ndarray, np.ndarray]:
    """Eq. 11–12 as printed: ``P_f + P_safe < P < P_l − P_safe`` at decision time, with
    ``P_safe = (v_l − v_ego)² / (2(|a_max,l| − |a_max,ego|))`` (point masses, plus the body lengths).

    Unsound here: the ego's P-controller brakes harder at first (KP_A·ΔV = 8.3 m/s²) than IDM's
    ACC_MAX (6 m/s²), so the denominator is negative and the formula demands no distance at all
    (taken as 0): only overlapping vehicles are excluded. Kept only as the faithful baseline.
    """
    ego_brake = dyn.ego_kp * (dyn.target_speeds[1] - dyn.target_speeds[0])
    lanes = state.lane_of(state.y, dyn.lanes_count, dyn.lane_width)
    safe = np.ones(N_ACTIONS, dtype=bool)
    gaps = np.full(N_ACTIONS, np.inf)
    half = 0.5 * (state.length + state.ego_length)
    for a in range(N_ACTIONS):
        printed = replace(dyn, crossed_lanes=False, lateral_schedule=False)  # as printed: the two lanes
        for lane, _ in _action_lanes(state, printed, a):
            for i in np.flatnonzero(lanes == lane):
                denom = 2.0 * (abs(state.brake_max[i]) - ego_brake)
                p_safe = (state.vx[i] - state.ego_speed) ** 2 / denom if denom > 0 else 0.0
                gap = abs(state.x[i] - state.ego_x) - half[i]
                gaps[a] = min(gaps[a], gap - p_safe)
                if gap - p_safe <= 0:
                    safe[a] = False
    return safe, gaps
