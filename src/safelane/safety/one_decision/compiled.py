"""The safety model compiled: :func:`safelane.safety.one_decision.reference.evaluate` as one numba kernel per state.

:func:`evaluate_compiled` has ``evaluate``'s signature and returns the same :class:`SafetyResult` —
the same mask, safe, available and fallback, and ``min_gap`` to the bit — in microseconds instead of
a millisecond. :mod:`safelane.safety.one_decision.reference` stays the readable specification; this module follows it
operation by operation and in the same order, so the IEEE-754 arithmetic (no fastmath) rounds the
same way: numpy's ``x**2`` on arrays is ``x*x``, ``np.cumsum`` a sequential sum, ``np.minimum`` /
``np.maximum`` propagate NaN (``compiled_parts.nmin``, ``nmax``), ``np.power`` / ``np.cos`` & co. are
libm's, as numba's calls are (checked: numpy dispatches no SIMD transcendental on this build's
x86-64-v3 baseline; SVML is not used by numba here). The constants that depend only on the dynamics
(frame times, the P-controller's decay powers) are computed by numpy exactly as the reference does,
once per :class:`Dynamics`, and handed to the kernel.

:func:`evaluate_snapshot` is the shield's fast path: it reads a :class:`RoadSnapshot` directly and
builds the :class:`RoadState` arrays inside the kernel (as :func:`safelane.safety.family.road_state`
does, bit for bit on axis-aligned roads — every highway-env straight road), so no Python object per
vehicle and no ``RoadState`` is built.

The kernel is :func:`safelane.safety.one_decision.compiled_rule.evaluate_rule` (its pieces in
:mod:`safelane.safety.one_decision.compiled_parts`); this module adds the straight fallback, the snapshot's projection
and the Python entries. Units: metres, m/s, seconds. ``formula="paper"`` (eq. 12, nominal only) is delegated to the
numpy reference: it is a baseline evaluated at decision time, not on the shield's hot path.
"""

from __future__ import annotations

import functools
import math
from typing import NamedTuple

import numpy as np
from numba import njit

from safelane.core import spaces
from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.core.snapshot import RoadSnapshot
from safelane.safety import rule
from safelane.safety.one_decision import compiled_parts, compiled_rule, forecast, reference
from safelane.safety.one_decision.compiled_parts import IDM_LANE_MARGIN, N_ACTIONS, N_FALLBACKS, NOT_ZERO
from safelane.safety.one_decision.compiled_rule import (
    C_BODY_WIDTH,
    C_CUT_IN_TIME,
    C_DECISION_PERIOD,
    C_EGO_KP,
    C_FOLLOWER_REACTION,
    C_FRAME_DT,
    C_FRAMES,
    C_HORIZON,
    C_LANE_WIDTH,
    C_LANES_COUNT,
    C_LATERAL_THRESHOLD,
    C_MARGIN,
    C_MIN_ACC_GAIN,
    C_RELEVANCE,
    C_TURNING_ALLOWANCE,
    N_CONSTS,
    evaluate_rule,
    rule_gaps_kernel,
)
from safelane.safety.one_decision.cut_ins import politeness_of
from safelane.safety.rule import (
    FLAG_EGO_SPEED_MAGNITUDE,
    FLAG_FORECAST_FALLBACK,
    FLAG_STRAIGHT_FALLBACK,
    FLAG_TURNING_IN_NOMINAL,
)
from safelane.safety.world import Dynamics, Formula, Mode, RoadState, SafetyResult, check_choices

# These kernels compile in the rule's kernel, its parts, the forecast and the rule's bits: numba's cache watches
# this file only.
drop_stale_kernel_cache(__file__, (compiled_rule.__file__, compiled_parts.__file__, forecast.__file__, rule.__file__))

# The kernels use the action indices and the model's literals as frozen globals (numba freezes globals at compile
# time, and its disk cache only watches their file): check here that they are still the core's and the model's.
assert (spaces.LANE_LEFT, spaces.IDLE, spaces.LANE_RIGHT, spaces.FASTER, spaces.SLOWER) == (0, 1, 2, 3, 4)
assert spaces.N_ACTIONS == N_ACTIONS and reference.MAX_HOLD_DECISIONS + 1 == N_FALLBACKS, "update compiled_parts.py"
assert (reference.IDM_LANE_MARGIN, reference.NOT_ZERO) == (IDM_LANE_MARGIN, NOT_ZERO), "update compiled_parts.py"

# The model's other constants travel as arguments for the same reason (no stale cached kernel).
_TIE_BREAK = np.array(reference.TIE_BREAK_ORDER, dtype=np.int64)
_RELEVANCE = float(reference.RELEVANCE_RANGE)
_LATERAL = float(reference.LATERAL_MOTION_THRESHOLD)

__all__ = [
    "C_BODY_WIDTH", "C_CUT_IN_TIME", "C_DECISION_PERIOD", "C_EGO_KP", "C_FOLLOWER_REACTION", "C_FRAMES",
    "C_FRAME_DT", "C_HORIZON", "C_LANES_COUNT", "C_LANE_WIDTH", "C_LATERAL_THRESHOLD", "C_MARGIN", "C_MIN_ACC_GAIN",
    "C_RELEVANCE", "C_TURNING_ALLOWANCE", "N_CONSTS", "KernelConstants", "axis_aligned", "compiled_gaps",
    "dynamics_consts", "evaluate_compiled", "evaluate_snapshot", "kernel_constants", "snapshot_kernel",
]  # fmt: skip


@njit(cache=True, error_model="numpy")
def _evaluate(
    ego_x: float, ego_speed: float, ego_lane: int, ego_target_lane: int, ego_target_speed: float,
    ego_speed_index: int, ego_length: float, speed_limit: float,
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, politeness: np.ndarray, target_speed: np.ndarray,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray, consts: np.ndarray, flags: int,
    robust: bool, ego_leave_time: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """:func:`evaluate_rule`, and with ``straight_fallback`` (``model.evaluate``) a state the turning
    allowance leaves without a safe action gets the mask of the rule without it. The allowance is robust only
    (``model.evaluate``: nominal keeps the straight leader bound)."""
    turning_allowance = consts[C_TURNING_ALLOWANCE]
    allowance = turning_allowance
    if not robust:
        allowance = 0.0
    # turning_in_nominal: nominal's leader bound, in nominal mode and in robust's straight fallback
    nominal_allowance = turning_allowance if flags & FLAG_TURNING_IN_NOMINAL else 0.0
    main_nominal_allowance = 0.0 if robust else nominal_allowance  # robust: turning_leaders' own bound
    # With the straight fallback below, a fallback state's mask is the straight rule's: the main rule's least-bad
    # choice is discarded, so its forecast (about 0.06 ms) is not run (reference.evaluate returns first).
    straight = robust and (flags & FLAG_STRAIGHT_FALLBACK) != 0 and turning_allowance > 0.0
    forecast_on = (flags & FLAG_FORECAST_FALLBACK) != 0
    main_forecast = forecast_on and not straight
    out = evaluate_rule(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, ego_length, speed_limit,
        x, y, vx, vy, heading, length, crashed, brake_max, accel_max, can_change_lane, idm_delta,
        idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, max_braking_imposed,
        lin_k0, lin_k1, lin_k2, politeness, target_speed, ts, t, powers, tie_break, consts, flags, robust,
        ego_leave_time, allowance, main_nominal_allowance, main_forecast,
    )  # fmt: skip
    if not (out[4] and straight):
        return out
    straight_out = evaluate_rule(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, ego_length, speed_limit,
        x, y, vx, vy, heading, length, crashed, brake_max, accel_max, can_change_lane, idm_delta,
        idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, max_braking_imposed,
        lin_k0, lin_k1, lin_k2, politeness, target_speed, ts, t, powers, tie_break, consts, flags, robust,
        ego_leave_time, 0.0, nominal_allowance, forecast_on,
    )  # fmt: skip
    return straight_out[0].copy(), out[1], out[2], out[3], True


@njit(cache=True, error_model="numpy")
def _evaluate_snapshot(
    position: np.ndarray, speed: np.ndarray, heading: np.ndarray, length: np.ndarray, crashed: np.ndarray,
    brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray, idm_delta: np.ndarray,
    idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray, idm_distance_wanted: np.ndarray,
    idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, politeness: np.ndarray, target_speed: np.ndarray,
    ego: int, ego_lane: int, ego_target_lane: int, ego_target_speed: float, ego_speed_index: int,
    origin: np.ndarray, direction: np.ndarray, lateral: np.ndarray, lane_heading: float, speed_limit: float,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray, consts: np.ndarray, flags: int,
    robust: bool, ego_leave_time: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """``shield.road_state`` then :func:`_evaluate`, without building the state in Python.

    The projections on the lane frame are written as ``p·d = p₀d₀ + p₁d₁``: the reference's ``@``
    (BLAS) may round differently for an oblique frame, so the caller only comes here for the
    axis-aligned one, where every order gives the same bits.
    """
    relevance = consts[C_RELEVANCE]
    n = speed.shape[0]
    e0 = position[ego, 0] - origin[0]
    e1 = position[ego, 1] - origin[1]
    ego_x = e0 * direction[0] + e1 * direction[1]
    # shield.road_state: the controller's speed, or (without ego_speed_magnitude) its component along the road.
    along = speed[ego] * math.cos(heading[ego] - lane_heading)
    ego_speed = speed[ego] if flags & FLAG_EGO_SPEED_MAGNITUDE else along
    keep = np.empty(n, dtype=np.int64)
    xk = np.empty(n)
    m = 0
    for k in range(n):  # the other bodies (static objects included) within range, in order
        if k == ego:
            continue
        xv = (position[k, 0] - origin[0]) * direction[0] + (position[k, 1] - origin[1]) * direction[1]
        if abs(xv - ego_x) < relevance and np.isfinite(xv):
            keep[m] = k
            xk[m] = xv
            m += 1
    keep, x = keep[:m], xk[:m].copy()
    y = np.empty(m)
    vx = np.empty(m)
    vy = np.empty(m)
    rel_heading = np.empty(m)
    for r in range(m):
        k = keep[r]
        y[r] = (position[k, 0] - origin[0]) * lateral[0] + (position[k, 1] - origin[1]) * lateral[1]
        h = heading[k] - lane_heading
        c, s = np.cos(h), np.sin(h)
        vx[r] = speed[k] * c
        vy[r] = speed[k] * s
        rel_heading[r] = np.arctan2(s, c)
    return _evaluate(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, length[ego], speed_limit,
        x, y, vx, vy, rel_heading, length[keep], crashed[keep], brake_max[keep], accel_max[keep],
        can_change_lane[keep], idm_delta[keep], idm_comfort_acc[keep], idm_comfort_dec[keep],
        idm_distance_wanted[keep], idm_time_wanted[keep], max_braking_imposed[keep],
        lin_k0[keep], lin_k1[keep], lin_k2[keep], politeness[keep], target_speed[keep],
        ts, t, powers, tie_break, consts, flags, robust, ego_leave_time,
    )  # fmt: skip


# --------------------------------------------------------------------------------------------
# Python entries.
# --------------------------------------------------------------------------------------------


@functools.lru_cache(maxsize=64)
def _horizon_arrays(
    frame_dt: float, frames: int, horizon: int, ego_kp: float, target_speeds: tuple[float, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(target speeds [m/s], frame times [s], decay powers) computed by numpy exactly as the reference does."""
    ts = np.asarray(target_speeds, dtype=float)
    t = np.arange(horizon * frames + 1) * frame_dt  # Dynamics.times
    powers = (1.0 - ego_kp * frame_dt) ** np.arange(frames + 1)  # ego_trajectories' decay^k
    for a in (ts, t, powers):
        a.flags.writeable = False
    return ts, t, powers


class KernelConstants(NamedTuple):
    """A :class:`Dynamics` as the kernels take it (everything but ``ego_leave_time``, the per-state one): the
    horizon's arrays, the numbers (:func:`dynamics_consts`) and the rule's options as one integer."""

    ts: np.ndarray  # [m/s] the ego's set-points
    t: np.ndarray  # [s] the horizon's frame times
    powers: np.ndarray  # the P-controller's decay per frame, to the power 0..frames
    tie_break: np.ndarray  # reference.TIE_BREAK_ORDER
    consts: np.ndarray  # float64 (N_CONSTS,), at the C_* indices
    flags: int  # safelane.safety.rule.Rule.flags


def dynamics_consts(dyn: Dynamics) -> np.ndarray:
    """The numbers of ``dyn`` the kernels read, as a read-only float64 array at the ``C_*`` indices (the
    integers ``frames``, ``horizon`` and ``lanes_count`` are exact in a double)."""
    consts = np.empty(N_CONSTS)
    consts[C_DECISION_PERIOD] = dyn.decision_period
    consts[C_FRAME_DT] = dyn.frame_dt
    consts[C_FRAMES] = dyn.frames_per_decision
    consts[C_HORIZON] = dyn.horizon_decisions
    consts[C_EGO_KP] = dyn.ego_kp
    consts[C_LANE_WIDTH] = dyn.lane_width
    consts[C_LANES_COUNT] = dyn.lanes_count
    consts[C_FOLLOWER_REACTION] = dyn.follower_reaction
    consts[C_CUT_IN_TIME] = dyn.cut_in_time
    consts[C_MARGIN] = dyn.margin
    consts[C_RELEVANCE] = _RELEVANCE
    consts[C_LATERAL_THRESHOLD] = _LATERAL
    consts[C_BODY_WIDTH] = dyn.body_width
    consts[C_TURNING_ALLOWANCE] = reference.turning_allowance(dyn)
    consts[C_MIN_ACC_GAIN] = dyn.mobil_min_gain
    consts.flags.writeable = False
    return consts


_CONSTANTS: dict[int, tuple[Dynamics, KernelConstants]] = {}
"""The kernel's constants per Dynamics object: the shield evaluates one Dynamics for a whole episode, and
building them costs as much as a small kernel."""


def kernel_constants(dyn: Dynamics) -> KernelConstants:
    """``dyn``'s constants in the kernels' form (the arrays computed as the reference does)."""
    hit = _CONSTANTS.get(id(dyn))
    if hit is not None and hit[0] is dyn:  # the entry holds dyn, so its id is not reused meanwhile
        return hit[1]
    ts, t, powers = _horizon_arrays(
        dyn.frame_dt, dyn.frames_per_decision, dyn.horizon_decisions, dyn.ego_kp, dyn.target_speeds
    )
    constants = KernelConstants(ts, t, powers, _TIE_BREAK, dynamics_consts(dyn), dyn.rule.flags)
    if len(_CONSTANTS) >= 256:
        _CONSTANTS.clear()
    _CONSTANTS[id(dyn)] = (dyn, constants)
    return constants


snapshot_kernel = _evaluate_snapshot
"""The njit kernel behind :func:`evaluate_snapshot` (its arguments: the snapshot's arrays, the ego's
lane, target lane, set-point [m/s] and speed index, the lane frame, the speed limit [m/s], then
:func:`kernel_constants`'s fields, ``robust`` and ``ego_leave_time`` [s]): for a caller that evaluates many
scenes inside one numba call."""


def _result(out: tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]) -> SafetyResult:
    mask, safe, available, min_gap, fallback = out
    return SafetyResult(mask, safe, available, bool(fallback), min_gap)


def evaluate_compiled(
    state: RoadState, dyn: Dynamics, mode: Mode = "robust", formula: Formula = "kinematic"
) -> SafetyResult:
    """The safety mask of ``state`` — :func:`safelane.safety.one_decision.reference.evaluate`, compiled.

    Same arguments (positions in metres, speeds in m/s, times in seconds), same errors, same result:
    mask, safe, available and fallback identical, ``min_gap`` [m] bit for bit. ``formula="paper"`` in
    nominal mode is computed by the numpy reference (eq. 12 is a baseline off the hot path; robust
    mode ignores the formula, as the reference does).
    """
    check_choices(mode, formula=formula, prefix="")
    if mode == "nominal" and formula == "paper":
        return reference.evaluate(state, dyn, mode, formula)
    s = state
    out = _evaluate(
        s.ego_x, s.ego_speed, s.ego_lane, s.ego_target_lane, s.ego_target_speed, s.ego_speed_index,
        s.ego_length, s.speed_limit, s.x, s.y, s.vx, s.vy, s.heading, s.length, s.crashed, s.brake_max,
        s.accel_max, s.can_change_lane, s.idm_delta, s.idm_comfort_acc, s.idm_comfort_dec,
        s.idm_distance_wanted, s.idm_time_wanted, s.max_braking_imposed, s.linear_speed_gain,
        s.linear_speed_difference_gain, s.linear_distance_gain, politeness_of(s), reference.set_points(s),
        *kernel_constants(dyn), mode == "robust", dyn.ego_leave_time,
    )  # fmt: skip
    return _result(out)


def axis_aligned(snap: RoadSnapshot) -> bool:
    """Whether the snapshot's lane frame is x along the road, y across (every highway-env straight road):
    there :func:`evaluate_snapshot` reproduces ``road_state``'s projections bit for bit."""
    d, lat = snap.lane_direction, snap.lane_lateral
    return bool(d[0] == 1.0 and d[1] == 0.0 and lat[0] == 0.0 and lat[1] == 1.0)


def evaluate_snapshot(
    snap: RoadSnapshot, dyn: Dynamics, mode: Mode = "robust", *, lane_heading: float, ego_leave_time: float
) -> SafetyResult:
    """``evaluate_compiled(road_state(snap, dyn.rule.ego_speed_magnitude), replace(dyn, ego_leave_time=...),
    mode)`` in one kernel.

    The shield's fast path (formula ``kinematic``): the :class:`RoadState` is built inside the kernel,
    bit for bit as :func:`safelane.safety.shield.road_state` builds it, for an :func:`axis_aligned`
    snapshot (the caller checks). ``lane_heading`` [rad]: ``atan2`` of the lane direction, computed
    once per episode; ``ego_leave_time`` [s] replaces ``dyn``'s.
    """
    check_choices(mode, prefix="")
    e = snap.ego
    out = _evaluate_snapshot(
        snap.position, snap.speed, snap.heading, snap.length, snap.crashed, snap.brake_max, snap.accel_max,
        snap.can_change_lane, snap.idm_delta, snap.idm_comfort_acc, snap.idm_comfort_dec,
        snap.idm_distance_wanted, snap.idm_time_wanted, snap.max_braking_imposed, snap.linear_speed_gain,
        snap.linear_speed_difference_gain, snap.linear_distance_gain, snap.politeness, snap.target_speed,
        e, int(snap.lane[e]), int(snap.target_lane[e]), snap.ego_target_speed, snap.ego_speed_index,
        snap.lane_origin, snap.lane_direction, snap.lane_lateral, lane_heading, snap.speed_limit,
        *kernel_constants(dyn), mode == "robust", ego_leave_time,
    )  # fmt: skip
    return _result(out)


def compiled_gaps(state: RoadState, dyn: Dynamics, nominal_leaders: bool = False) -> reference.RuleGaps:
    """:func:`safelane.safety.one_decision.reference.rule_gaps` of the robust rule, compiled (the same bits): the
    worst-case gaps [m] before the verdict; ``nominal_leaders``: the straight fallback's pass (the leaders bounded as
    nominal mode bounds them). The deciding conflicts are not reported (``conflicts`` None)."""
    s = state
    constants = kernel_constants(dyn)
    turning = float(constants.consts[C_TURNING_ALLOWANCE])
    allowance = 0.0 if nominal_leaders else turning
    # The nominal leaders' looser bound (turning_in_nominal) in the straight pass; the main robust pass has none.
    nominal = turning if nominal_leaders and constants.flags & FLAG_TURNING_IN_NOMINAL else 0.0
    out = rule_gaps_kernel(
        s.ego_x, s.ego_speed, s.ego_lane, s.ego_target_lane, s.ego_target_speed, s.ego_speed_index,
        s.ego_length, s.speed_limit, s.x, s.y, s.vx, s.vy, s.heading, s.length, s.crashed, s.brake_max,
        s.accel_max, s.can_change_lane, s.idm_delta, s.idm_comfort_acc, s.idm_comfort_dec,
        s.idm_distance_wanted, s.idm_time_wanted, s.max_braking_imposed, s.linear_speed_gain,
        s.linear_speed_difference_gain, s.linear_distance_gain, politeness_of(s), reference.set_points(s),
        *constants, True, dyn.ego_leave_time, allowance, nominal,
    )  # fmt: skip
    available, joint, ahead, nominal_joint, nominal_ahead, nominal_ok = out[:6]
    return reference.RuleGaps(available, joint, ahead, nominal_joint, nominal_ahead, nominal_ok, allowance, None)
