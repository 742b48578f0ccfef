"""The compiled rule's kernel: :func:`evaluate_rule`, ``safelane.safety.one_decision.reference._evaluate`` (formula
``kinematic``) for one state, operation by operation and in the same order (bit-identical; metres, m/s,
seconds): :func:`rule_gaps_kernel` (``reference.rule_gaps``), then the verdict. The rule's options arrive as one
integer (:attr:`safelane.safety.rule.Rule.flags`), tested bit by bit; the dynamics' numbers as one float64 array at
the ``C_*`` indices below.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from safelane.core.kernel_cache import drop_stale_kernel_cache
from safelane.safety import rule
from safelane.safety.one_decision import compiled_parts, forecast
from safelane.safety.one_decision.compiled_parts import (
    FASTER,
    IDLE,
    IDM_LANE_MARGIN,
    LANE_LEFT,
    LANE_RIGHT,
    N_ACTIONS,
    N_FALLBACKS,
    SLOWER,
    braking_from_now,
    follower_row,
    gap_ratio,
    idm_behind,
    idm_behind_gap,
    idm_follower_window,
    incentive_first,
    incentive_first_any_speed,
    lane_index,
    least_desired_gap,
    linear_behind,
    nmax,
    nmin,
    passing_path,
    polite_first,
    speed_index,
)
from safelane.safety.one_decision.forecast import current_accelerations, forecast_keys_of
from safelane.safety.rule import (
    FLAG_BODY_EXTENT,
    FLAG_CROSSED_LANES,
    FLAG_CUT_IN_WHEN_PERMITTED,
    FLAG_FINISHING_CHANGES,
    FLAG_FOLLOWER_IDM,
    FLAG_INCENTIVE_ACCELERATIONS,
    FLAG_INCENTIVE_ANY_SPEED,
    FLAG_INCENTIVE_LEADERS_BAND,
    FLAG_INCENTIVE_POLITENESS,
    FLAG_LEVEL_CUT_INS,
    FLAG_LEVEL_ENTERING,
    FLAG_LEVEL_INCENTIVE,
    FLAG_LEVEL_INCENTIVE_FRAMES,
    FLAG_LEVEL_WHEN_INCENTIVE,
    FLAG_LINEAR_INCENTIVE,
    FLAG_LINEAR_INCENTIVE_BRAKING,
    FLAG_LINEAR_MOBIL,
    FLAG_PASSING_CUT_INS,
    FLAG_PERMIT_ANY_SPEED,
    FLAG_REVERSING_CUT_INS,
    FLAG_REVERSING_LEADERS,
    FLAG_REVERSING_NOSES,
)

# The kernel compiles in the parts, the forecast and the rule's bits: numba's cache watches this file only.
drop_stale_kernel_cache(__file__, (compiled_parts.__file__, forecast.__file__, rule.__file__))

# The numeric constants of a Dynamics as one float64 array (the kernels' ``consts``), at these indices.
C_DECISION_PERIOD, C_FRAME_DT, C_FRAMES, C_HORIZON, C_EGO_KP, C_LANE_WIDTH, C_LANES_COUNT = 0, 1, 2, 3, 4, 5, 6
C_FOLLOWER_REACTION, C_CUT_IN_TIME, C_MARGIN, C_RELEVANCE, C_LATERAL_THRESHOLD, C_BODY_WIDTH = 7, 8, 9, 10, 11, 12
C_TURNING_ALLOWANCE, C_MIN_ACC_GAIN = 13, 14
N_CONSTS = 15


@njit(cache=True, error_model="numpy")
def rule_gaps_kernel(
    ego_x: float, ego_speed: float, ego_lane: int, ego_target_lane: int, ego_target_speed: float,
    ego_speed_index: int, ego_length: float, speed_limit: float,
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, politeness: np.ndarray, target_speed: np.ndarray,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray, consts: np.ndarray, flags: int,
    robust: bool, ego_leave_time: float, turning_allowance: float, nominal_allowance: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:  # fmt: skip
    """``model.rule_gaps`` of one state, the worst-case gaps [m] before the verdict: (available, joint, ahead,
    nominal_joint, nominal_ahead (each (5, fallbacks)), nominal_ok, the ego's positions ``xs`` [m] (actions, frames,
    fallbacks) and the last frame it occupies each lane per action); the arguments as :func:`evaluate_rule`'s."""
    decision_period, frame_dt = consts[C_DECISION_PERIOD], consts[C_FRAME_DT]
    frames, horizon, lanes_count = int(consts[C_FRAMES]), int(consts[C_HORIZON]), int(consts[C_LANES_COUNT])
    ego_kp, lane_width, follower_reaction = consts[C_EGO_KP], consts[C_LANE_WIDTH], consts[C_FOLLOWER_REACTION]
    cut_in_time, margin, relevance = consts[C_CUT_IN_TIME], consts[C_MARGIN], consts[C_RELEVANCE]
    lateral_threshold, body_width = consts[C_LATERAL_THRESHOLD], consts[C_BODY_WIDTH]
    min_acc_gain = consts[C_MIN_ACC_GAIN]
    body_extent = (flags & FLAG_BODY_EXTENT) != 0
    linear_mobil = (flags & FLAG_LINEAR_MOBIL) != 0
    reversing_leaders = (flags & FLAG_REVERSING_LEADERS) != 0
    level_cut_ins = (flags & FLAG_LEVEL_CUT_INS) != 0
    level_incentive = (flags & FLAG_LEVEL_INCENTIVE) != 0
    level_entering = (flags & FLAG_LEVEL_ENTERING) != 0
    linear_incentive = (flags & FLAG_LINEAR_INCENTIVE) != 0
    linear_incentive_braking = (flags & FLAG_LINEAR_INCENTIVE_BRAKING) != 0
    reversing_cut_ins = (flags & FLAG_REVERSING_CUT_INS) != 0
    crossed_lanes = (flags & FLAG_CROSSED_LANES) != 0
    reversing_noses = (flags & FLAG_REVERSING_NOSES) != 0
    follower_idm = (flags & FLAG_FOLLOWER_IDM) != 0
    finishing_changes = (flags & FLAG_FINISHING_CHANGES) != 0
    cut_in_when_permitted = (flags & FLAG_CUT_IN_WHEN_PERMITTED) != 0
    permit_any_speed = (flags & FLAG_PERMIT_ANY_SPEED) != 0
    passing_cut_ins = (flags & FLAG_PASSING_CUT_INS) != 0
    level_when_incentive = (flags & FLAG_LEVEL_WHEN_INCENTIVE) != 0
    incentive_any_speed = (flags & FLAG_INCENTIVE_ANY_SPEED) != 0
    level_incentive_frames = (flags & FLAG_LEVEL_INCENTIVE_FRAMES) != 0
    incentive_leaders_band = (flags & FLAG_INCENTIVE_LEADERS_BAND) != 0
    incentive_politeness = (flags & FLAG_INCENTIVE_POLITENESS) != 0
    incentive_accelerations = (flags & FLAG_INCENTIVE_ACCELERATIONS) != 0
    n_ts = ts.shape[0]
    n_t = t.shape[0]  # frames of the horizon + 1
    total = n_t - 1

    # --- available_actions -------------------------------------------------------------------
    available = np.zeros(N_ACTIONS, dtype=np.bool_)
    available[IDLE] = True
    available[LANE_LEFT] = ego_lane > 0
    available[LANE_RIGHT] = ego_lane < lanes_count - 1
    available[FASTER] = ego_speed_index < n_ts - 1
    available[SLOWER] = ego_speed_index > 0

    # --- action_targets ----------------------------------------------------------------------
    idx_now = speed_index(ego_speed, ts)
    targets = np.full(N_ACTIONS, ego_target_speed)
    targets[FASTER] = ts[min(idx_now + 1, n_ts - 1)]
    targets[SLOWER] = ts[max(idx_now - 1, 0)]

    # --- ego_trajectories: xs[a, frame, k] (the reference's (5, F, T) transposed, so the gap loop
    # below runs the 4 fallbacks side by side); the speeds only where evaluate reads them ----------
    xs = np.empty((N_ACTIONS, n_t, N_FALLBACKS))
    vs = np.empty((N_ACTIONS, n_t if follower_idm else 0, N_FALLBACKS))  # the speeds, for IDM followers
    v_key = np.empty(N_ACTIONS)  # ego_v[a, 0, frames]: the cut-in key
    v4 = np.empty(N_FALLBACKS)  # per fallback: speed, position, set-point at the decision's start...
    x4 = np.empty(N_FALLBACKS)
    tg4 = np.empty(N_FALLBACKS)
    dv4 = np.empty(N_FALLBACKS)
    vp4 = np.empty(N_FALLBACKS)  # ...the frame's speed and the running sum of the speeds
    cov4 = np.empty(N_FALLBACKS)
    for a in range(N_ACTIONS):
        # IDLE and the lane changes share their set-point (FASTER / SLOWER may too): one trajectory per
        # distinct set-point, copied — the same computation on the same inputs, so the same bits.
        src = -1
        for b in range(a):
            if targets[b] == targets[a]:
                src = b
                break
        if src >= 0:
            xs[a] = xs[src]
            if follower_idm:
                vs[a] = vs[src]
            v_key[a] = v_key[src]
            continue
        for k in range(N_FALLBACKS):
            v4[k], x4[k], tg4[k] = ego_speed, ego_x, targets[a]
        for d in range(horizon):
            base = d * frames
            for k in range(N_FALLBACKS):
                if d > k:  # fallback k sends SLOWER from decision k + 1 on (its hold is over)
                    tg4[k] = ts[max(speed_index(v4[k], ts) - 1, 0)]
                dv4[k] = v4[k] - tg4[k]
                # Frame 0 of the decision: covered = 0, so x = 0·dt + x. The reference writes it over
                # the previous decision's last frame: for the speed that is (v − target)·1 + target,
                # which can differ from v in the last bit — and ego_v[a, 0, frames] is read below.
                xs[a, base, k] = 0.0 * frame_dt + x4[k]
                vp4[k] = dv4[k] * powers[0] + tg4[k]
                if follower_idm:
                    vs[a, base, k] = vp4[k]
            if d == 1:
                v_key[a] = vp4[0]
            for j in range(1, frames + 1):
                p = powers[j]
                for k in range(N_FALLBACKS):  # the 4 fallbacks side by side: independent chains
                    # np.cumsum: out[0] = in[0], then out[j] = out[j − 1] + in[j] (sequential).
                    cov4[k] = vp4[k] if j == 1 else cov4[k] + vp4[k]
                    vp4[k] = dv4[k] * p + tg4[k]
                    xs[a, base + j, k] = cov4[k] * frame_dt + x4[k]
                    if follower_idm:
                        vs[a, base + j, k] = vp4[k]
            if d == 0:
                v_key[a] = vp4[0]  # kept when the horizon is a single decision
            for k in range(N_FALLBACKS):
                x4[k] = xs[a, base + frames, k]
                v4[k] = vp4[k]
        for k in range(N_FALLBACKS):
            xs[a, total, k] += nmax(v4[k] - 0.0, 0.0) / ego_kp  # the exponential tail beyond the horizon

    # --- nearby vehicles and their worst-case motion -------------------------------------------
    n = x.shape[0]
    near = np.empty(n, dtype=np.int64)
    m = 0
    for i in range(n):
        if abs(x[i] - ego_x) < relevance and np.isfinite(x[i]):
            near[m] = i
            m += 1
    other_x = np.empty((m, n_t))  # leaders brake, followers surge (only the one used is computed)
    is_ahead = np.empty(m, dtype=np.bool_)
    half = np.empty(m)
    lanes_near = np.empty(m, dtype=np.int64)
    band_near = np.full(m, -10, dtype=np.int64)  # model.band_lanes: the next lane whose IDM band holds it
    t_last = t[n_t - 1]
    t_r = follower_reaction if not (t_last < follower_reaction) else t_last  # Python's min()
    for r in range(m):
        i = near[r]
        half[r] = 0.5 * (length[i] + ego_length)
        lanes_near[r] = lane_index(y[i], lane_width, lanes_count)
        if incentive_leaders_band:
            for side in (-1, 1):
                other = lanes_near[r] + side
                inside = abs(y[i] - other * lane_width) <= 0.5 * lane_width + IDM_LANE_MARGIN
                if inside and other >= 0 and other < lanes_count:
                    band_near[r] = other
        is_ahead[r] = x[i] - ego_x >= 0
        if is_ahead[r]:  # braking_positions; a crashed vehicle is a wall where it stands
            v_signed = 0.0 if crashed[i] else vx[i]
            # model.evaluate's turning_leaders: a moving leader brakes along its path (its speed), less
            # what a lane change can cost along the road (turning_allowance > 0 when the option is on).
            turning = turning_allowance > 0.0 and v_signed > 0.0
            if turning:
                v_signed = math.sqrt(vx[i] * vx[i] + vy[i] * vy[i])
            v0 = nmax(v_signed, 0.0)
            b = nmax(1e9 if crashed[i] else brake_max[i], 1e-6)
            stop = v0 / b
            hb = 0.5 * b
            back = reversing_leaders and v_signed < 0.0  # a leader rolling backwards keeps its speed
            # model.evaluate's turning_in_nominal (nominal's leader bound): the looser of braking along the road
            # and along its path less the allowance (nominal_allowance > 0 when the option is on).
            looser = nominal_allowance > 0.0 and v_signed > 0.0
            v_path = math.sqrt(vx[i] * vx[i] + vy[i] * vy[i]) if looser else 0.0
            stop_path = v_path / b
            for j in range(n_t):
                tt = nmin(t[j], stop)
                other_x[r, j] = x[i] + v0 * tt - hb * (tt * tt)
                if back:
                    other_x[r, j] = other_x[r, j] + v_signed * t[j]
                if turning:
                    other_x[r, j] = other_x[r, j] - turning_allowance
                if looser:
                    tt = nmin(t[j], stop_path)
                    other_x[r, j] = nmax(other_x[r, j], (x[i] + v_path * tt - hb * (tt * tt)) - nominal_allowance)
        else:  # follower_positions
            follower_row(other_x[r], x[i], vx[i], accel_max[i], brake_max[i], t_r, t)
    # level_cut_ins: a car turning in behind the ego follows it, wherever it is now (ahead rows too).
    level_rows = robust and level_cut_ins
    # model.incentive_times' accelerations now (incentive_accelerations), where incentive_first runs: one kernel for
    # both engines.
    now_acc = np.zeros(0)
    frames_timed = level_rows and level_incentive and level_when_incentive
    if frames_timed and incentive_accelerations and (level_incentive_frames or not incentive_any_speed):
        now_acc = current_accelerations(
            ego_x, lanes_count, lane_width, speed_limit, x, y, vx, vy, length, crashed, brake_max, accel_max,
            idm_delta, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1,
            lin_k2, target_speed,
        )  # fmt: skip
    foll_x = np.empty((m if level_rows else 0, n_t))
    for r in range(foll_x.shape[0]):
        if is_ahead[r]:
            i = near[r]
            follower_row(foll_x[r], x[i], vx[i], accel_max[i], brake_max[i], t_r, t)
        else:
            foll_x[r] = other_x[r]
    # model.idm_followers: the IDM car right behind the ego in its lane, nothing between them in IDM's band.
    by_idm = np.zeros(m, dtype=np.bool_)
    if follower_idm:
        centre = ego_lane * lane_width
        band = 0.5 * lane_width + IDM_LANE_MARGIN
        for r in range(m):
            i = near[r]
            if not (
                x[i] < ego_x and not crashed[i] and can_change_lane[i]
                and math.isnan(lin_k0[i])
                and abs(heading[i]) <= lateral_threshold and abs(vy[i]) <= 0.3 and lanes_near[r] == ego_lane
            ):  # fmt: skip
                continue
            clear = True
            for j in range(n):
                if j != i and abs(y[j] - centre) <= band and x[j] >= x[i] and x[j] <= ego_x:
                    clear = False
                    break
            by_idm[r] = clear
    xf4 = np.empty(N_FALLBACKS)  # an IDM follower's position and speed per fallback
    vf4 = np.empty(N_FALLBACKS)

    # --- model.occupancy: (row, lane, nominal); every entry starts at t = 0 -------------------------
    occ_row = np.empty(4 * m, dtype=np.int64)
    occ_lane = np.empty(4 * m, dtype=np.int64)
    occ_nominal = np.empty(4 * m, dtype=np.bool_)
    n_occ = 0
    for r in range(m):
        i = near[r]
        own = lanes_near[r]
        occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, own, True
        n_occ += 1
        nxt = -10
        if abs(heading[i]) > lateral_threshold or abs(vy[i]) > 0.3:
            direction = 1 if vy[i] > 0 else -1
            nxt = own + direction
            # model.finishing_change: moving forward toward its own lane's centre, short of it
            finishing = finishing_changes and vx[i] >= 0.0 and (own * lane_width - y[i]) * direction > 0.0
            if finishing:
                nxt = -10  # a cut-in candidate from its own lane instead (MOBIL-filtered)
            elif robust and 0 <= nxt < lanes_count:
                occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, nxt, False
                n_occ += 1
        if robust and reversing_noses and vx[i] < 0.0 and abs(heading[i]) > lateral_threshold:
            nose = own + (1 if heading[i] > 0 else -1)  # model.occupancy: the lane its nose points to
            if nose != nxt and 0 <= nose < lanes_count:
                occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, nose, False
                n_occ += 1
        if robust and body_extent:  # model.occupancy: every lane the rotated body overlaps
            reach = abs(0.5 * length[i] * math.sin(heading[i])) + abs(0.5 * body_width * math.cos(heading[i]))
            for side in (own - 1, own + 1):
                if side == nxt or not (0 <= side < lanes_count):
                    continue
                centre, half_lane = side * lane_width, 0.5 * lane_width
                if y[i] + reach > centre - half_lane and y[i] - reach < centre + half_lane:
                    occ_row[n_occ], occ_lane[n_occ], occ_nominal[n_occ] = r, side, False
                    n_occ += 1

    # Windows are contiguous ranges of the increasing frame times: [first t >= start, last t <= until]
    # (NaN bounds give empty ranges, as the reference's comparisons do).
    lo_now = 0
    while lo_now < n_t and not (t[lo_now] >= 0.0):
        lo_now += 1
    lo_cut = 0
    while lo_cut < n_t and not (t[lo_cut] >= cut_in_time):
        lo_cut += 1

    inf = math.inf
    joint_gap = np.full((N_ACTIONS, N_FALLBACKS), inf)
    ahead_gap = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_joint = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_ahead = np.full((N_ACTIONS, N_FALLBACKS), inf)
    nominal_ok = np.ones(N_ACTIONS, dtype=np.bool_)
    worst = np.empty(N_FALLBACKS)
    # model.cut_in_candidates, memoised on its key as the reference does (IDLE and the lane changes share it).
    keys = np.empty((N_ACTIONS, 3))
    n_keys = 0
    permitted = np.zeros((N_ACTIONS, m), dtype=np.bool_)
    permit_lo = np.zeros((N_ACTIONS, m), dtype=np.int64)  # cut_in_when_permitted: a cut-in's first frame
    permit_first = np.full((N_ACTIONS, m), inf)  # the same as a time [s] (model.permit_times)
    pass_x = np.empty(n_t)  # passing_cut_ins: one car's leader path (model.passing_positions)
    unfiltered = np.zeros((N_ACTIONS, m), dtype=np.bool_)
    level = np.zeros((N_ACTIONS, m), dtype=np.bool_)  # level with or behind the ego (level_cut_ins)
    level_any = np.zeros((N_ACTIONS, m), dtype=np.bool_)  # the same, no incentive filter (level_entering)
    ego_lanes = np.empty(lanes_count + 1, dtype=np.int64)
    ego_hi = np.empty(lanes_count + 1, dtype=np.int64)  # the last frame of that window (t <= until)
    ego_last = np.full((N_ACTIONS, lanes_count), -1, dtype=np.int64)  # per action: the last frame in each lane
    hi_leave = n_t - 1
    while hi_leave >= 0 and not (t[hi_leave] <= ego_leave_time):
        hi_leave -= 1
    hi_inf = n_t - 1
    target_clip = 0.0
    for a in range(N_ACTIONS):
        if not available[a]:
            continue
        # model.action_lanes: the sorted set {ego_lane, ego_target_lane} (with crossed_lanes every lane between
        # them), then a lane change's new lane (model.final_lane).
        lane_change = (a == LANE_LEFT) | (a == LANE_RIGHT)
        final = ego_target_lane
        if lane_change:
            final = min(max(ego_target_lane + (-1 if a == LANE_LEFT else 1), 0), lanes_count - 1)
        lo_l, hi_l = min(ego_lane, ego_target_lane), max(ego_lane, ego_target_lane)
        n_el = 0
        if not lane_change:
            for lane in range(lo_l, hi_l + 1):
                if lane == lo_l or lane == hi_l or crossed_lanes:  # noqa: SIM109 (numba)
                    ego_lanes[n_el], ego_hi[n_el] = lane, hi_inf
                    n_el += 1
        else:
            lo_x, hi_x = min(ego_lane, final), max(ego_lane, final)  # crossed: strictly between
            for lane in range(min(lo_l, lo_x), max(hi_l, hi_x) + 1):
                if lane == final:
                    continue
                crossed = crossed_lanes and lo_x < lane < hi_x
                if crossed or lane == lo_l or lane == hi_l:  # noqa: SIM109 (numba) still overlapped until it has left
                    ego_lanes[n_el], ego_hi[n_el] = lane, hi_inf if crossed else hi_leave
                    n_el += 1
            ego_lanes[n_el], ego_hi[n_el] = final, hi_inf
            n_el += 1
        for e in range(n_el):  # forecast_fallback: model.ego_last_frames
            ego_last[a, ego_lanes[e]] = max(ego_last[a, ego_lanes[e]], ego_hi[e])

        slot = -1
        if robust:
            kx, kv, kt = xs[a, frames, 0], v_key[a], targets[a]
            for s in range(n_keys):
                if keys[s, 0] == kx and keys[s, 1] == kv and keys[s, 2] == kt:
                    slot = s
                    break
            if slot < 0:
                slot = n_keys
                keys[slot, 0], keys[slot, 1], keys[slot, 2] = kx, kv, kt
                n_keys += 1
                target_clip = nmin(nmax(kt, 0.0), speed_limit)  # np.clip(ego_target, 0, speed_limit)
                for r in range(m):
                    i = near[r]
                    can = can_change_lane[i] and abs(vx[i]) >= 1.0
                    d_now = x[i] - ego_x
                    d_end = x[i] + vx[i] * decision_period - kx
                    ahead_c = d_now > 0 or d_end > 0
                    unfiltered[slot, r] = can and ahead_c
                    level_any[slot, r] = can and (d_now <= 0 or d_end <= 0)
                    if level_rows and level_incentive and not np.isfinite(lin_k0[i]):
                        # model.turn_in_incentive: MOBIL's gain behind the ego, now or at the end.
                        dw, tw, v = idm_distance_wanted[i], idm_time_wanted[i], vx[i]
                        acc, dec = idm_comfort_acc[i], idm_comfort_dec[i]
                        lead_now = lead_end = 0.0  # the largest (d*/d)² over the vehicles ahead in its lane
                        found = False
                        for k in range(m):
                            lx = x[near[k]]
                            if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and lx > x[i]:
                                lv = vx[near[k]]
                                q = gap_ratio(dw, tw, acc, dec, v, lv, lx - x[i])
                                gap_end = (lx + lv * decision_period) - (x[i] + v * decision_period)
                                qe = gap_ratio(dw, tw, acc, dec, v, lv, gap_end)
                                if found:
                                    lead_now, lead_end = nmax(lead_now, q * q), nmax(lead_end, qe * qe)
                                else:
                                    lead_now, lead_end, found = q * q, qe * qe, True
                        q_en = gap_ratio(dw, tw, acc, dec, v, ego_speed, -d_now)
                        q_ee = gap_ratio(dw, tw, acc, dec, v, kv, -d_end)
                        gain_now = acc * lead_now - acc * (q_en * q_en)
                        gain_end = acc * lead_end - acc * (q_ee * q_ee)
                        level[slot, r] = can and (
                            (d_now <= 0 and gain_now >= min_acc_gain) or (d_end <= 0 and gain_end >= min_acc_gain)
                        )
                    elif level_rows and level_incentive and linear_incentive:
                        # model.linear_turn_in_incentive: the linear model's gain behind the ego.
                        k1, k2, v = lin_k1[i], lin_k2[i], vx[i]
                        d_safe = idm_distance_wanted[i] + nmax(v, 0.0) * idm_time_wanted[i]
                        lead_now = lead_end = 0.0  # the most negative term over the vehicles ahead in its lane
                        found = False
                        for k in range(m):
                            lx = x[near[k]]
                            if (lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]) and lx > x[i]:
                                lv = vx[near[k]]
                                closing = k1 * nmin(lv - v, 0.0)
                                gap_end = (lx + lv * decision_period) - (x[i] + v * decision_period)
                                an = closing + k2 * nmin((lx - x[i]) - d_safe, 0.0)
                                ae = closing + k2 * nmin(gap_end - d_safe, 0.0)
                                if found:
                                    lead_now, lead_end = nmin(lead_now, an), nmin(lead_end, ae)
                                else:
                                    lead_now, lead_end, found = an, ae, True
                        ego_now = k1 * nmin(ego_speed - v, 0.0) + k2 * nmin(-d_now - d_safe, 0.0)
                        ego_end = k1 * nmin(kv - v, 0.0) + k2 * nmin(-d_end - d_safe, 0.0)
                        gain_now = ego_now - lead_now
                        gain_end = ego_end - lead_end
                        level[slot, r] = can and (
                            (d_now <= 0 and gain_now >= min_acc_gain) or (d_end <= 0 and gain_end >= min_acc_gain)
                        )
                        if linear_incentive_braking and can and not level[slot, r]:
                            # model.linear_turn_in_incentive_braking: at every frame of the decision, the
                            # vehicles ahead of it in its lane braking at their maximum, itself at constant speed.
                            for f in range(frames + 1):
                                tau = t[f]
                                own_x = x[i] + v * tau
                                d = own_x - xs[a, f, 0]
                                if not d <= 0:
                                    continue
                                ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
                                ego_term = k1 * nmin(ego_vf - v, 0.0) + k2 * nmin(-d - d_safe, 0.0)
                                lead_term = 0.0
                                found = False
                                for k in range(m):
                                    ii = near[k]
                                    leads = lanes_near[k] == lanes_near[r] or band_near[k] == lanes_near[r]
                                    if leads and x[ii] > x[i]:
                                        lx, lv = braking_from_now(x[ii], vx[ii], crashed[ii], brake_max[ii], tau)
                                        term = k1 * nmin(lv - v, 0.0) + k2 * nmin((lx - own_x) - d_safe, 0.0)
                                        lead_term = nmin(lead_term, term) if found else term
                                        found = True
                                if ego_term - lead_term >= min_acc_gain:
                                    level[slot, r] = True
                                    break
                    else:
                        level[slot, r] = level_any[slot, r]
                    if reversing_cut_ins and can and vx[i] < 0.0:  # model.cut_in_candidates: any lane change
                        level[slot, r] = level[slot, r] or level_any[slot, r]
                    if can and ahead_c:
                        acc, delta, dec = idm_comfort_acc[i], idm_delta[i], idm_comfort_dec[i]
                        dw, tw = idm_distance_wanted[i], idm_time_wanted[i]
                        limit = -max_braking_imposed[i]
                        if np.isfinite(lin_k0[i]) and not linear_mobil:  # without linear_mobil: any cut-in
                            ok = True
                        elif np.isfinite(lin_k0[i]):  # model.linear_acceleration_behind, now then at the end
                            k0, k1, k2, own = lin_k0[i], lin_k1[i], lin_k2[i], math.hypot(vx[i], vy[i])
                            ok = linear_behind(k0, k1, k2, dw, tw, own, d_now, ego_speed, kt) >= limit
                            if not ok:
                                ok = linear_behind(k0, k1, k2, dw, tw, own, d_end, kv, kt) >= limit
                        else:
                            ok = idm_behind(acc, delta, dec, dw, tw, vx[i], d_now, ego_speed, target_clip) >= limit
                            if not ok:  # the end-of-period check only matters when the one of now fails
                                ok = idm_behind(acc, delta, dec, dw, tw, vx[i], d_end, kv, target_clip) >= limit
                        permitted[slot, r] = ok or (reversing_cut_ins and vx[i] < 0.0)
                        if cut_in_when_permitted:
                            # model.permit_times: the first frame MOBIL allows it, the car at its fastest.
                            t_first = inf
                            if np.isfinite(lin_k0[i]) and not linear_mobil:
                                t_first = 0.0
                            else:
                                accel = nmax(accel_max[i], 0.0)
                                for f in range(frames + 1):
                                    tau = t[f]
                                    d = (x[i] + vx[i] * tau + 0.5 * accel * tau * tau) - xs[a, f, 0]
                                    ego_vf = kv if f == frames else (ego_speed - kt) * powers[f] + kt
                                    if np.isfinite(lin_k0[i]):
                                        own = math.hypot(vx[i], vy[i]) + accel * tau
                                        af = linear_behind(lin_k0[i], lin_k1[i], lin_k2[i], dw, tw, own, d, ego_vf, kt)
                                    elif permit_any_speed:  # model.permit_times: IDM at its loosest speed
                                        v_lo = nmax(vx[i] - nmax(brake_max[i], 1e-6) * tau, 0.0)
                                        q = least_desired_gap(acc, dec, dw, tw, ego_vf, v_lo, vx[i] + accel * tau)
                                        af = idm_behind_gap(acc, delta, ego_vf, target_clip, d, q) if d > 0.0 else -inf
                                    else:
                                        af = idm_behind(
                                            acc, delta, dec, dw, tw, vx[i] + accel * tau, d, ego_vf, target_clip
                                        )
                                    if af >= limit:
                                        t_first = tau
                                        break
                            if reversing_cut_ins and vx[i] < 0.0:
                                t_first = 0.0
                            permitted[slot, r] = t_first < inf
                            permit_first[slot, r] = t_first
                            start = cut_in_time + t_first
                            lo_p = 0
                            while lo_p < n_t and not (t[lo_p] >= start):
                                lo_p += 1
                            permit_lo[slot, r] = lo_p
                    else:
                        permitted[slot, r] = False

        # Every conflict: (row, window, nominal). The order of the reference's pairs only matters to
        # its min / max reductions, which are order-free here (NaN propagates either way).
        n_cut = n_occ + (n_el * m if robust else 0)
        n_conf = n_cut + (n_el * m if level_rows else 0)
        for c in range(n_conf):
            follows = False
            passing = False
            if c < n_occ:
                r, lane_c, nominal = occ_row[c], occ_lane[c], occ_nominal[c]
                lo = lo_now
            elif c >= n_cut:  # level_cut_ins: a car level with or behind the ego turning in behind it
                e_idx, r = divmod(c - n_cut, m)
                lane_c = ego_lanes[e_idx]
                occupied = (lane_c == ego_lane) | (lane_c == ego_target_lane)
                # model.cut_in_candidates: MOBIL's incentive is judged with the ego in the lane, which a
                # lane it is only entering does not hold (level_entering: any level car there).
                by_level = occupied or not level_entering
                turning = level[slot, r] if by_level else level_any[slot, r]
                adjacent = abs(lanes_near[r] - lane_c) == 1
                timed = level_when_incentive and level_incentive and occupied
                # model.polite_turn_ins: its followers' gain may let it turn in, from the decision's start.
                i = near[r]
                polite = False
                polite_on = incentive_politeness and level_incentive and by_level and adjacent and level_any[slot, r]
                if polite_on and politeness[i] > 0.0 and not np.isfinite(lin_k0[i]):
                    polite = polite_first(
                        i, r, m, near, lanes_near, band_near, lane_c, x, vx, politeness[i], idm_distance_wanted[i],
                        idm_time_wanted[i], idm_comfort_acc[i], idm_comfort_dec[i], xs[a], ego_speed, v_key[a],
                        targets[a], powers, frames, t, min_acc_gain,
                    )  # fmt: skip
                # model.incentive_times, the others at constant speed (or, incentive_accelerations, at their
                # accelerations now), at one call site: it times the turn-in without incentive_any_speed, and
                # (level_incentive_frames) admits a level car the now-and-end check left out.
                t_const = inf
                frames_check = not turning and not polite and level_incentive_frames and level_any[slot, r]
                if adjacent and timed and (frames_check or (turning and not incentive_any_speed)):
                    t_const = incentive_first(
                        near[r], r, m, near, lanes_near, band_near, x, vx, crashed, brake_max, lin_k0, lin_k1, lin_k2,
                        idm_distance_wanted, idm_time_wanted, idm_comfort_acc, idm_comfort_dec, linear_incentive,
                        linear_incentive_braking, xs[a], ego_speed, v_key[a], targets[a], powers, frames, t,
                        min_acc_gain, now_acc, now_acc.shape[0] > 0,
                    )  # fmt: skip
                    if frames_check:
                        turning = t_const < inf
                if not ((turning or polite) and adjacent):
                    continue
                nominal = False
                follows = True
                lo = lo_cut
                if timed and not polite:  # model.incentive_times(_any_speed)
                    t_inc = t_const
                    if incentive_any_speed:
                        t_inc = incentive_first_any_speed(
                            near[r], r, m, near, lanes_near, band_near, x, vx, vy, crashed, brake_max, accel_max,
                            lin_k0, lin_k1, lin_k2, idm_distance_wanted, idm_time_wanted, idm_comfort_acc,
                            idm_comfort_dec, linear_incentive, xs[a], ego_speed, v_key[a], targets[a], powers, frames,
                            t, min_acc_gain,
                        )  # fmt: skip
                    if t_inc < inf:
                        start = cut_in_time + t_inc
                        lo = 0
                        while lo < n_t and not (t[lo] >= start):
                            lo += 1
            else:
                e_idx, r = divmod(c - n_occ, m)
                lane_c = ego_lanes[e_idx]
                occupied = (lane_c == ego_lane) | (lane_c == ego_target_lane)
                cand = permitted[slot, r] if occupied else unfiltered[slot, r]
                adjacent = abs(lanes_near[r] - lane_c) == 1
                if not (cand and adjacent):
                    continue
                nominal = False
                lo = permit_lo[slot, r] if cut_in_when_permitted and occupied else lo_cut
                i = near[r]
                passing = (
                    passing_cut_ins and cut_in_when_permitted and occupied and not is_ahead[r] and vx[i] >= 0.0
                    and (linear_mobil or not np.isfinite(lin_k0[i]))
                )  # fmt: skip
                if passing:  # model.passing_positions: behind now, it cuts in only ahead of the ego
                    passing_path(
                        pass_x, i, x, vx, vy, brake_max, accel_max, max_braking_imposed, idm_distance_wanted,
                        idm_time_wanted, idm_comfort_acc, idm_comfort_dec, idm_delta, lin_k0, lin_k1, lin_k2,
                        speed_limit, xs[a], ego_speed, powers, frames, v_key[a], targets[a], t, cut_in_time,
                        permit_first[slot, r], turning_allowance,
                    )  # fmt: skip
            for e in range(n_el):
                if ego_lanes[e] != lane_c:
                    continue
                hi = ego_hi[e]
                ahead_r = (is_ahead[r] and not follows) or passing
                sign = 1.0 if ahead_r else -1.0
                motion = foll_x if follows else other_x
                h = half[r]
                if passing:
                    w0 = w1 = w2 = w3 = inf
                    for j in range(lo, hi + 1):
                        o = pass_x[j]
                        w0 = nmin(w0, (o - xs[a, j, 0]) - h)
                        w1 = nmin(w1, (o - xs[a, j, 1]) - h)
                        w2 = nmin(w2, (o - xs[a, j, 2]) - h)
                        w3 = nmin(w3, (o - xs[a, j, 3]) - h)
                    worst[0], worst[1], worst[2], worst[3] = w0, w1, w2, w3
                elif by_idm[r] and not follows and lane_c == ego_lane:
                    idm_follower_window(
                        near[r], x, vx, idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted,
                        accel_max, brake_max, xs[a], vs[a], frame_dt, follower_reaction, h, lo, hi, xf4, vf4, worst,
                    )  # fmt: skip
                else:
                    # The where(window, gap, inf).min(axis=-1) of the reference: the window's running minimum,
                    # the 4 fallbacks side by side (independent chains; min is exact in any order).
                    w0 = w1 = w2 = w3 = inf
                    for j in range(lo, hi + 1):
                        o = motion[r, j]
                        w0 = nmin(w0, sign * (o - xs[a, j, 0]) - h)
                        w1 = nmin(w1, sign * (o - xs[a, j, 1]) - h)
                        w2 = nmin(w2, sign * (o - xs[a, j, 2]) - h)
                        w3 = nmin(w3, sign * (o - xs[a, j, 3]) - h)
                    worst[0], worst[1], worst[2], worst[3] = w0, w1, w2, w3
                best_f = -inf
                for f in range(N_FALLBACKS):
                    joint_gap[a, f] = nmin(joint_gap[a, f], worst[f])
                    if ahead_r:
                        ahead_gap[a, f] = nmin(ahead_gap[a, f], worst[f])
                    if nominal:
                        nominal_joint[a, f] = nmin(nominal_joint[a, f], worst[f])
                        if ahead_r:
                            nominal_ahead[a, f] = nmin(nominal_ahead[a, f], worst[f])
                    best_f = worst[f] if f == 0 else nmax(best_f, worst[f])
                if nominal and not (best_f >= margin):
                    nominal_ok[a] = False

    return available, joint_gap, ahead_gap, nominal_joint, nominal_ahead, nominal_ok, xs, ego_last


@njit(cache=True, error_model="numpy")
def evaluate_rule(
    ego_x: float, ego_speed: float, ego_lane: int, ego_target_lane: int, ego_target_speed: float,
    ego_speed_index: int, ego_length: float, speed_limit: float,
    x: np.ndarray, y: np.ndarray, vx: np.ndarray, vy: np.ndarray, heading: np.ndarray, length: np.ndarray,
    crashed: np.ndarray, brake_max: np.ndarray, accel_max: np.ndarray, can_change_lane: np.ndarray,
    idm_delta: np.ndarray, idm_comfort_acc: np.ndarray, idm_comfort_dec: np.ndarray,
    idm_distance_wanted: np.ndarray, idm_time_wanted: np.ndarray, max_braking_imposed: np.ndarray,
    lin_k0: np.ndarray, lin_k1: np.ndarray, lin_k2: np.ndarray, politeness: np.ndarray, target_speed: np.ndarray,
    ts: np.ndarray, t: np.ndarray, powers: np.ndarray, tie_break: np.ndarray, consts: np.ndarray, flags: int,
    robust: bool, ego_leave_time: float, turning_allowance: float, nominal_allowance: float, forecast_on: bool,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, bool]:  # fmt: skip
    """``model.evaluate`` (formula ``kinematic``) of one state: (mask, safe, available, min_gap, fallback).

    ``consts``: the dynamics' numbers (:func:`dynamics_consts`); ``flags``: the rule's options
    (:attr:`safelane.safety.rule.Rule.flags`); ``turning_allowance``, ``nominal_allowance`` [m] and
    ``forecast_on``: what this pass of :func:`_evaluate` bounds the leaders and ranks the fallback with."""
    available, joint_gap, ahead_gap, nominal_joint, nominal_ahead, nominal_ok, xs, ego_last = rule_gaps_kernel(
        ego_x, ego_speed, ego_lane, ego_target_lane, ego_target_speed, ego_speed_index, ego_length, speed_limit,
        x, y, vx, vy, heading, length, crashed, brake_max, accel_max, can_change_lane, idm_delta,
        idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, max_braking_imposed,
        lin_k0, lin_k1, lin_k2, politeness, target_speed, ts, t, powers, tie_break, consts, flags, robust,
        ego_leave_time, turning_allowance, nominal_allowance,
    )  # fmt: skip
    frame_dt, margin, inf = consts[C_FRAME_DT], consts[C_MARGIN], math.inf
    lanes_count, lane_width = int(consts[C_LANES_COUNT]), consts[C_LANE_WIDTH]
    # --- the verdict ----------------------------------------------------------------------------
    best_gap = np.empty(N_ACTIONS)
    safe = np.empty(N_ACTIONS, dtype=np.bool_)
    for a in range(N_ACTIONS):
        g = joint_gap[a, 0]
        for f in range(1, N_FALLBACKS):
            g = nmax(g, joint_gap[a, f])
        best_gap[a] = g if available[a] else -inf
        safe[a] = ((best_gap[a] >= margin) if robust else nominal_ok[a]) and available[a]
    if not np.isfinite(ego_leave_time):
        safe[LANE_LEFT] = safe[LANE_RIGHT] = False
        nominal_ok[LANE_LEFT] = nominal_ok[LANE_RIGHT] = False
    if safe.any():
        return safe.copy(), safe, available, best_gap, False
    pool = nominal_ok & available
    if robust and pool.any():
        ahead_of, gaps_of = ahead_gap, joint_gap
    else:
        pool = available
        ahead_of, gaps_of = nominal_ahead, nominal_joint
    # model.forecast_ranking: the forecast's keys, ranked first (0 for every action: no forecast).
    forecast = np.zeros(N_ACTIONS)
    n_pool = 0
    for a in range(N_ACTIONS):
        n_pool += 1 if pool[a] else 0
    # The keys rank the pool's actions only: one action is the choice whatever its key (no forecast), and the
    # others' rollouts are not run (forecast_keys_of: the pool's keys are forecast_gaps' keys to the bit).
    if forecast_on and n_pool > 1:
        forecast = forecast_keys_of(
            xs.transpose((0, 2, 1)), ego_last, available, pool, frame_dt, ego_x, ego_length, lanes_count,
            lane_width, speed_limit, x, y, vx, vy, length, crashed, brake_max, accel_max, idm_delta,
            idm_comfort_acc, idm_comfort_dec, idm_distance_wanted, idm_time_wanted, lin_k0, lin_k1, lin_k2,
            target_speed, margin,
        )  # fmt: skip
    # least_bad_action: the largest (forecast, ahead gap, gap, −rank), compared as Python compares tuples.
    choice = IDLE
    found = False
    b0 = b1 = b2 = 0.0
    b3 = 0
    for rank in range(tie_break.shape[0]):
        a = tie_break[rank]
        if not pool[a]:
            continue
        g1, g2 = ahead_of[a, 0], gaps_of[a, 0]
        for f in range(1, N_FALLBACKS):
            g1, g2 = nmax(g1, ahead_of[a, f]), nmax(g2, gaps_of[a, f])
        k0, k1, k2, k3 = forecast[a], nmin(g1, 1e6), nmin(g2, 1e6), -rank
        better = True
        if found:
            better = k0 > b0 if k0 != b0 else (k1 > b1 if k1 != b1 else (k2 > b2 if k2 != b2 else k3 > b3))
        if better:
            found, b0, b1, b2, b3, choice = True, k0, k1, k2, k3, a
    mask = np.zeros(N_ACTIONS, dtype=np.bool_)
    mask[choice] = True
    return mask, safe, available, best_gap, True
