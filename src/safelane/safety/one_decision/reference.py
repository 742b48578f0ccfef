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
  response to the ego's fallback (the rule's ``follower_idm``, :func:`idm_follower_positions`).

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

``robust ⊆ nominal ⊆ available`` holds by construction: robust adds conflicts and requires a joint fallback; its one
looser bound, a moving leader braking along its path (the rule's ``turning_leaders``), is also nominal's wherever it is
the looser (the rule's ``turning_in_nominal``). The mask is never empty: when no action is safe the least-bad one is
allowed and ``fallback`` is set (:func:`least_bad_action`), ranked first by a nominal forecast of the others (the rule's
``forecast_fallback``, :mod:`safelane.safety.one_decision.forecast`), which orders the unsafe actions and never makes
one safe.

The rule's options (:mod:`safelane.safety.rule`) travel in ``Dynamics.rule`` and are read by name
(``dyn.rule.follower_idm``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from safelane.core.spaces import IDLE, LANE_LEFT, LANE_RIGHT, N_ACTIONS
from safelane.safety.ego import (
    action_lanes,
    action_targets,
    available_actions,
    ego_last_frames,
    ego_trajectories,
    final_lane,
    speed_to_index,
)
from safelane.safety.one_decision.cut_ins import (
    cut_in_candidates,
    finishing_change,
    incentive_times,
    incentive_times_any_speed,
    linear_turn_in_incentive,
    linear_turn_in_incentive_braking,
    occupancy,
    passing_positions,
    permit_times,
    polite_turn_ins,
    required_gap,
    turn_in_incentive,
)
from safelane.safety.one_decision.forecast import forecast_gaps, forecast_keys, forecast_paths
from safelane.safety.others import (
    braking_positions,
    follower_positions,
    idm_acceleration_behind,
    idm_acceleration_behind_gap,
    idm_follower_positions,
    idm_followers,
    least_desired_gap,
    linear_acceleration_behind,
    set_points,
    turning_allowance,
)
from safelane.safety.world import (
    BASE_DECISION_PERIOD,
    IDM_LANE_MARGIN,
    LATERAL_MOTION_THRESHOLD,
    MAX_HOLD_DECISIONS,
    MOBIL_MIN_ACC_GAIN,
    NOT_ZERO,
    OVERRIDE_ORDER,
    RELEVANCE_RANGE,
    TAIL_DECISIONS,
    TIE_BREAK_ORDER,
    Conflict,
    Dynamics,
    Formula,
    Mode,
    RoadState,
    SafetyResult,
    check_choices,
)

__all__ = [
    "BASE_DECISION_PERIOD", "IDM_LANE_MARGIN", "LATERAL_MOTION_THRESHOLD", "MAX_HOLD_DECISIONS", "MOBIL_MIN_ACC_GAIN",
    "NOT_ZERO", "OVERRIDE_ORDER", "RELEVANCE_RANGE", "TAIL_DECISIONS", "TIE_BREAK_ORDER", "CarriedFollowers",
    "Conflict", "Dynamics", "Formula", "Mode", "RoadState", "RuleGaps", "SafetyResult", "action_lanes",
    "action_targets", "available_actions", "braking_positions", "cut_in_candidates", "ego_last_frames",
    "ego_trajectories", "evaluate", "final_lane", "finishing_change", "follower_positions", "forecast_of",
    "forecast_ranking", "idm_acceleration_behind", "idm_acceleration_behind_gap", "idm_follower_positions",
    "idm_followers", "incentive_times", "incentive_times_any_speed", "least_bad_action", "least_desired_gap",
    "linear_acceleration_behind", "linear_turn_in_incentive", "linear_turn_in_incentive_braking", "occupancy",
    "passing_positions", "permit_times", "polite_turn_ins",
    "required_gap", "rule_gaps", "rule_verdict", "set_points", "speed_to_index",
    "turn_in_incentive", "turning_allowance",
]  # fmt: skip


@dataclass(frozen=True)
class CarriedFollowers:
    """The follower bounds an earlier decision drew, carried to this state (a probe of bounds nested in time,
    docs/research/nested-follower-bound.md; the numpy reference only): per vehicle of the state, its position ``x``
    [m] along the
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


@dataclass(frozen=True)
class RuleGaps:
    """The rule's worst-case gaps [m] in one state, before its verdict: per action and fallback ((5, fallbacks)
    arrays; inf: no conflict), over every conflict of the mode (``joint``), those with vehicles ahead (``ahead``),
    and the same two over the nominal conflicts alone; ``nominal_ok`` (5,): every nominal conflict has some
    fallback that keeps the margin; ``allowance`` [m]: the leaders' turning allowance this pass used."""

    available: np.ndarray
    joint: np.ndarray
    ahead: np.ndarray
    nominal_joint: np.ndarray
    nominal_ahead: np.ndarray
    nominal_ok: np.ndarray
    allowance: float
    conflicts: tuple[Conflict, ...] | None


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
    check_choices(mode, formula=formula, prefix="")
    available = available_actions(state, dyn)
    if mode == "nominal" and formula == "paper":
        safe, gaps = _paper_eq12(state, dyn)
        return _finish(safe & available, available, gaps, gaps)
    gaps = rule_gaps(state, dyn, mode, nominal_leaders, carried)
    return rule_verdict(
        gaps, state, dyn, mode, lambda: _evaluate(state, dyn, mode, formula, nominal_leaders=True, carried=carried)
    )


def rule_gaps(
    state: RoadState, dyn: Dynamics, mode: Mode, nominal_leaders: bool, carried: CarriedFollowers | None = None
) -> RuleGaps:
    """The worst-case gaps [m] of :func:`evaluate`'s kinematic rule in ``state`` (``nominal_leaders``: the leaders
    bounded as nominal mode bounds them, as in robust's straight fallback), before its verdict
    (:func:`rule_verdict`)."""
    available = available_actions(state, dyn)
    t = dyn.times
    rule = dyn.rule
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
    lead_x = braking_positions(state.x[near], lead_v, brake[near], t, dyn.rule.reversing_leaders)
    if path_allowance > 0.0 and (not nominal_leaders or dyn.rule.turning_in_nominal):
        # turning_leaders: along its path, from its speed (docs/research/horizon-and-ego-speed.md); nominal takes it
        # only
        # where it is the looser (a fast car turning: v·sin h large), so robust ⊆ nominal by construction
        # (docs/research/robust-inside-nominal.md).
        vx_n, vy_n = state.vx[near], state.vy[near]
        path_v = np.where(turning, np.sqrt(vx_n * vx_n + vy_n * vy_n), lead_v)
        path_x = braking_positions(state.x[near], path_v, brake[near], t, dyn.rule.reversing_leaders)
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

    occ = occupancy(state, dyn, mode, near)
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
    cut_ins: dict[tuple[float, float, float], tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]] = {}
    permits: dict[tuple[float, float, float], np.ndarray] = {}  # cut_in_when_permitted, on the same key
    idm_paths: dict[tuple[int, bytes, bytes], np.ndarray] = {}  # follower_idm: per car and ego trajectory
    deciding: list[Conflict] = []  # SafetyResult.conflicts
    for a in range(N_ACTIONS):
        if not available[a]:
            continue
        ego_lanes = action_lanes(state, dyn, a)
        vehicles, lanes_v, starts, nominal_flags = occ.vehicle, occ.lane, occ.start, occ.nominal
        as_follower = [False] * len(vehicles)  # a conflict with a car turning in behind the ego (level_cut_ins)
        passing_paths: list[np.ndarray | None] = [None] * len(vehicles)  # passing_cut_ins: a leader's path
        if mode == "robust":
            occupied = {state.ego_lane, state.ego_target_lane}
            # IDLE and the lane changes share one longitudinal trajectory: compute their cut-ins once.
            key = (float(ego_x[a, 0, frames]), float(ego_v[a, 0, frames]), float(targets[a]))
            if key not in cut_ins:
                path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                cut_ins[key] = cut_in_candidates(state, dyn, near, *key, path)
                if dyn.rule.cut_in_when_permitted:  # MOBIL at every frame of the decision: who, and from when
                    permits[key] = permit_times(state, dyn, near, *path, float(targets[a]))
            permitted, unfiltered, level, level_entering, level_any = cut_ins[key]
            permit_time = permits.get(key)
            if permit_time is not None:
                permitted = unfiltered & np.isfinite(permit_time)
            extra_v, extra_l, extra_s, extra_p = [], [], [], []
            for lane, _ in ego_lanes:
                cands = permitted if lane in occupied else unfiltered
                adjacent = np.abs(lanes_near - lane) == 1
                for j in np.flatnonzero(cands & adjacent):
                    extra_v.append(int(near[j]))
                    extra_l.append(lane)
                    after = float(permit_time[j]) if permit_time is not None and lane in occupied else 0.0
                    extra_s.append(dyn.cut_in_time + after)
                    i = int(near[j])
                    passing = (
                        rule.passing_cut_ins and permit_time is not None and lane in occupied and not ahead[i]
                        and state.vx[i] >= 0.0 and (rule.linear_mobil or not np.isfinite(state.linear_speed_gain[i]))
                    )  # fmt: skip
                    if passing:  # behind now, it cuts in only ahead of the ego: a leader from then
                        path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                        extra_p.append(passing_positions(state, dyn, i, *path, float(targets[a]), after, allowance))
                    else:
                        extra_p.append(None)
            behind_v, behind_l, behind_s = [], [], []
            turn_time = frame_turns = None
            if rule.level_cut_ins and rule.level_incentive and rule.level_when_incentive:  # timing by the incentive
                path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                times_of = incentive_times_any_speed if dyn.rule.incentive_any_speed else incentive_times
                turn_time = times_of(state, dyn, near, *path)
            if dyn.rule.level_cut_ins:
                # A car level with or behind the ego in a next lane may turn in behind it after the cut-in
                # time and then follow it (accelerate for the reaction time, then brake): a follower.
                for lane, _ in ego_lanes:
                    by_level = lane in occupied or not rule.level_entering  # else every level car turns in
                    turning = level if lane in occupied else level_entering
                    polite = np.zeros(near.size, dtype=bool)
                    if rule.incentive_politeness and rule.level_incentive and by_level:
                        path = (ego_x[a, 0, : frames + 1], ego_v[a, 0, : frames + 1])
                        polite = level_any & polite_turn_ins(state, dyn, near, *path, lane)
                    if turn_time is not None and lane in occupied and rule.level_incentive_frames:
                        # MOBIL's incentive now and at the end misses a car whose desired gap behind the ego passes
                        # through zero within the decision (much slower than the ego, level with it): the incentive
                        # at every frame, the others at constant speed, decides too.
                        if frame_turns is None:
                            frame_turns = np.isfinite(incentive_times(state, dyn, near, *path))
                        turning = turning | (level_any & frame_turns)
                    # A car its followers' gain lets turn in (incentive_politeness) does so from the decision's start.
                    for j in np.flatnonzero((turning | polite) & (np.abs(lanes_near - lane) == 1)):
                        behind_v.append(int(near[j]))
                        behind_l.append(lane)
                        later = 0.0
                        if turn_time is not None and lane in occupied and np.isfinite(turn_time[j]) and not polite[j]:
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
        best_fallback = int(np.argmax(joint_gap[a]))  # what decided: the worst conflict under the best fallback
        c = int(np.argmin(worst[:, best_fallback]))
        lane_c = pairs[c][5]
        deciding.append(Conflict(a, int(vehicle[c]), int(lane_c), float(worst[c, best_fallback]), bool(is_ahead[c])))
        if is_ahead.any():
            ahead_gap[a] = worst[is_ahead].min(axis=0)
        if is_nominal.any():
            nominal_joint[a] = worst[is_nominal].min(axis=0)
            if (is_nominal & is_ahead).any():
                nominal_ahead[a] = worst[is_nominal & is_ahead].min(axis=0)
            nominal_ok[a] = bool((worst[is_nominal].max(axis=1) >= dyn.margin).all())
    return RuleGaps(
        available, joint_gap, ahead_gap, nominal_joint, nominal_ahead, nominal_ok, allowance, tuple(deciding)
    )


def rule_verdict(
    gaps: RuleGaps, state: RoadState, dyn: Dynamics, mode: Mode, straight: Callable[[], SafetyResult]
) -> SafetyResult:
    """:func:`evaluate`'s verdict from the worst-case gaps [m] of :func:`rule_gaps`: the safe actions, else the
    mask of ``straight`` (robust's straight fallback: the rule with nominal's leader bound, called only then), else
    the least-bad action, its forecast run on ``state``."""
    available, joint_gap, ahead_gap = gaps.available, gaps.joint, gaps.ahead
    nominal_joint, nominal_ahead, nominal_ok = gaps.nominal_joint, gaps.nominal_ahead, gaps.nominal_ok.copy()
    deciding, allowance = gaps.conflicts, gaps.allowance
    best_gap = np.where(available, joint_gap.max(axis=1), -np.inf)
    safe = ((best_gap >= dyn.margin) if mode == "robust" else nominal_ok) & available
    if not math.isfinite(dyn.ego_leave_time):
        # Too slow to move sideways: the ego would straddle two lanes indefinitely, unseen by the
        # new lane's followers (highway-env's IDM only sees a car within 3 m of its lane centre).
        safe[[LANE_LEFT, LANE_RIGHT]] = False
        nominal_ok[[LANE_LEFT, LANE_RIGHT]] = False
    if safe.any():
        return SafetyResult(safe.copy(), safe, available, False, best_gap, deciding)
    if mode == "robust" and dyn.rule.straight_fallback and allowance > 0.0:
        # The stricter leader bound narrows what the rule promises, not what it falls back to: a spawned
        # scene the turning allowance leaves without a safe action is driven as the rule with nominal's leader
        # bound drives it — without turning_in_nominal, the rule without the allowance (with
        # turning_leaders alone its least-bad choice crashed more of those scenes).
        return SafetyResult(straight().mask.copy(), safe, available, True, best_gap, deciding)
    # Least-bad choice. Robust picks among the nominally safe actions when there are some (so that
    # robust ⊆ nominal holds for the final masks too), else exactly what nominal would pick.
    nominal_safe = nominal_ok & available
    if mode == "robust" and nominal_safe.any():
        first, second, pool = ahead_gap, joint_gap, nominal_safe
    else:
        first, second, pool = nominal_ahead, nominal_joint, available
    forecast = None
    if dyn.rule.forecast_fallback:
        forecast = forecast_ranking(state, dyn, ego_trajectories(state, dyn)[0], available)
    choice = least_bad_action(first.max(axis=1), second.max(axis=1), pool, forecast)
    return replace(_fallback(choice, safe, available, best_gap), conflicts=deciding)


def forecast_ranking(state: RoadState, dyn: Dynamics, ego_x: np.ndarray, available: np.ndarray) -> np.ndarray:
    """(5,) the rule's ``forecast_fallback``'s first key of the least-bad choice: each action's gap [m] under
    :func:`safelane.safety.one_decision.forecast.forecast_gaps` (the others as they will most likely drive), capped at
    ``margin`` — actions the forecast keeps ``margin`` clear of everybody rank among themselves by their
    worst-case gaps, since past the margin the forecast says nothing about the risk the worst case measures —
    and −1 for every action the forecast sees collide (they too then rank by their worst-case gaps: the depth
    of a forecast overlap is no measure of harm; ranking by it drove FASTER into leaders,
    docs/research/fallback-choice.md).
    ``ego_x``: (5, fallbacks, frames + 1) the ego's positions [m] (:func:`ego_trajectories`)."""
    gaps = forecast_gaps(
        ego_x, ego_last_frames(state, dyn, available), available, dyn.frame_dt, state.ego_x, state.ego_length,
        dyn.lanes_count, dyn.lane_width, state.speed_limit, state.x, state.y, state.vx, state.vy, state.length,
        state.crashed, state.brake_max, state.accel_max, state.idm_delta, state.idm_comfort_acc,
        state.idm_comfort_dec, state.idm_distance_wanted, state.idm_time_wanted, state.linear_speed_gain,
        state.linear_speed_difference_gain, state.linear_distance_gain, set_points(state),
    )  # fmt: skip
    return forecast_keys(gaps, dyn.margin)


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
        state.linear_distance_gain, set_points(state),
    )  # fmt: skip


def least_bad_action(
    ahead_gaps: np.ndarray, gaps: np.ndarray, pool: np.ndarray, forecast: np.ndarray | None = None
) -> int:
    """The action to allow when none is safe: largest worst-case gap [m] to vehicles *ahead* (the ego's
    own responsibility), then to everybody, then :data:`TIE_BREAK_ORDER`. ``forecast`` (the rule's
    ``forecast_fallback``, :func:`forecast_ranking`): a key [m] ranked before all of these."""
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
        printed = dyn.with_options(crossed_lanes=False)  # as printed: the two lanes
        for lane, _ in action_lanes(state, printed, a):
            for i in np.flatnonzero(lanes == lane):
                denom = 2.0 * (abs(state.brake_max[i]) - ego_brake)
                p_safe = (state.vx[i] - state.ego_speed) ** 2 / denom if denom > 0 else 0.0
                gap = abs(state.x[i] - state.ego_x) - half[i]
                gaps[a] = min(gaps[a], gap - p_safe)
                if gap - p_safe <= 0:
                    safe[a] = False
    return safe, gaps
